"""The contract between the add-on and the two backends, in one place: the dataset folder's
names (`dataset_layout`), the run folder's names (`run_layout`), the training process's events
(`training_events`), the command lines the add-on runs (`commands`) and the live view's requests,
events and frame files (`view_frames`).

Standard library only, no torch, no bpy: `datasets_gen`, `nerf_backend` and the add-on import it
statically, so a renamed file, flag or event field is one edit here, seen by all three (and by
grep, an IDE and tests/test_import_graph.py). Each backend builds its parser from the flag names
here; tests/test_contract.py parses every command line the add-on builds with the backends'
real parsers.
"""
