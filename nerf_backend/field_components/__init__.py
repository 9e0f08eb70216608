"""Layer 1: encodings a field is built from: Fourier features, factorised (vector-matrix) grids, the
multiresolution hash grid. Pure tensor maths; imports ``core`` only."""
