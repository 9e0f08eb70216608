"""Layer 4: what a run is asked to do: ``TrainConfig`` and the presets (presets.json, the one list the
CLI, the trainer and the add-on read)."""
