"""A run planned in one pass: the dataset's facts (``facts.py``) → the preset and the user's
``--set`` → every rule's decision in order (``rules.py``) → one frozen ``RunPlan`` with each
decision and its reason (``plan.py``), which ``config.json`` records and the trainer runs."""
