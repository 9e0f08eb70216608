"""Layer 6: training: the loop, the ``auto`` preset's decisions from the scene, the collapse guard."""
