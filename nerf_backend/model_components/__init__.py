"""Layer 1: what a model does with a field, field-agnostic: samplers, volume rendering, ray bounds, the
occupancy grid and the marcher (nerfacc-style functions: the caller passes a density function).
Imports ``core`` only."""
