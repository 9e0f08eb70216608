"""Layer 1: what is on disk: datasets in the nerf_synthetic layout, the occupancy prior, run folders
(config, event log, checkpoints loaded with ``weights_only=True``). Imports ``core`` only."""
