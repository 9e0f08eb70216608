"""NeRF training backend: PyTorch only, never imports bpy.

Modules, one idea each (after nerfstudio's layout):

- ``cameras``: rays through pixel centres from exact intrinsics and camera-to-world poses.
- ``encodings`` / ``grid_encodings``: positional (Fourier) encoding; factorised feature grids.
- ``fields`` / ``grid_field``: the NeRF MLP; the fast model's grid field.
- ``samplers``: stratified and importance (inverse-CDF) sampling along rays.
- ``volume_rendering``: weights, colour, depth and opacity from densities (nerfacc-style functions).
- ``ray_rendering``: coarse-to-fine rendering of a batch of rays with a pair of fields.
- ``occupancy``: the occupancy grid that skips empty space.
- ``models``: a field plus its way of sampling rays (the paper's NeRF, the fast grid model).
- ``config`` / ``auto``: the presets; the ``auto`` preset's decisions from the scene profile.
- ``dataset`` / ``ray_bounds``: datasets in the nerf_synthetic layout; near/far per ray.
- ``trainer`` / ``run_folder``: the training loop, event log, checkpoints, resume and cancel.
- ``render_views`` / ``inference``: rendering views in bounded-memory chunks from a trained run.
- ``metrics`` / ``lpips_metric`` / ``evaluate``: PSNR, SSIM, LPIPS and depth error against the ground truth.
- ``report``: the HTML comparison page.
- ``bench`` / ``plain_nerf``: the speed/accuracy trade of presets; a plain NeRF as a cost yardstick.
"""

__version__ = "0.1.0"
