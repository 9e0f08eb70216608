"""Run as a script: LPIPS distances from the ``lpips`` package itself (version 0.1, AlexNet),
for the image pairs in an .npz file, with the backbone weights in $LPIPS_TEST_BACKBONE.
Needs tests/reference_torchvision on PYTHONPATH (see its docstring)."""

import sys

import numpy as np
import torch

import lpips

pairs = np.load(sys.argv[1])
metric = lpips.LPIPS(net="alex", version="0.1", verbose=False).eval()
with torch.no_grad():
    a = torch.from_numpy(pairs["a"]).permute(0, 3, 1, 2)
    b = torch.from_numpy(pairs["b"]).permute(0, 3, 1, 2)
    distances = metric(a, b, normalize=True).flatten().numpy()
np.save(sys.argv[2], distances)
