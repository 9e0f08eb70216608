"""Layer 3: models: fields plus their way of rendering rays, behind the ``Model`` contract
(``base.py``); ``registry.py`` maps a preset's model name to its class."""
