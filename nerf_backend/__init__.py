"""NeRF training backend: PyTorch only, never imports bpy.

Modules, one idea each (after nerfstudio's layout):

- ``cameras``: rays through pixel centres from exact intrinsics and camera-to-world poses.
- ``encodings``: positional (Fourier) encoding.
- ``fields``: the NeRF MLP (density from position, colour from position and direction).
- ``samplers``: stratified and importance (inverse-CDF) sampling along rays.
- ``volume_rendering``: weights, colour, depth and opacity from densities (nerfacc-style functions).
- ``ray_rendering``: coarse-to-fine rendering of a batch of rays with a pair of fields.
- ``dataset``: loading datasets in the nerf_synthetic layout.
- ``config``: the presets.
- ``trainer``: the training loop, event log, checkpoints and resume.
- ``render_views``: rendering a split in bounded-memory chunks.
- ``metrics`` / ``evaluate``: PSNR and SSIM against the ground truth.
"""

__version__ = "0.1.0"
