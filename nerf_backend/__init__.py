"""NeRF training backend: PyTorch only, never imports bpy.

One idea a module, in layers (after nerfstudio's layout); a package imports only from its own
layer and those below it (tests/test_import_graph.py checks this):

- ``core``: errors, files, devices, progress, cameras, the scene's box.
- ``data``, ``field_components``, ``model_components``, ``metrics``: datasets and run folders;
  encodings; samplers, volume rendering, occupancy, the marcher; PSNR/SSIM/LPIPS.
- ``fields``: the NeRF MLP, the factorised grid field, the hash-grid field.
- ``models``: the ``Model`` contract, the paper's NeRF, marched models, the registry.
- ``configs``: ``TrainConfig`` and the presets.
- ``evaluation``: rendering, scoring, the report.
- ``training``: the loop, ``auto``, the collapse guard.
- ``bench``: the speed/accuracy trade; ``cli`` and ``demo`` on top.
"""

__version__ = "0.1.0"
