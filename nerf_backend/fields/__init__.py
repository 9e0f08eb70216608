"""Layer 2: fields, ``x -> (density, colour)``: the NeRF MLP; ``MarchableField`` and the fields a marched
model can use (factorised grid, hash grid). Import ``field_components`` and ``core``."""
