"""The add-on's settings: per-scene (saved in the .blend, so reopening it finds the dataset
and the run again) and per-user preferences (the backend's Python).

No property has an update callback: with one, the bpy module of Blender 4.2 crashed on exit
after the add-on was disabled (a setting that must act is an operator, as NeRF in Renders is)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from datasets_gen.core.options import EXTRA_FORMATS

from ..core import sources
from ..core.torch_builds import CUDA_BUILDS, ROCM_BUILD
from .paths import ADDON_PACKAGE, backend_python, torch_build

PRESETS = sources.backend_presets()  # presets.json, the backend's own list
DEVICES = (("auto", "Auto", "CUDA, then Apple's MPS, then the CPU"), ("cpu", "CPU", "The CPU"),
           ("cuda", "CUDA", "NVIDIA GPU"), ("mps", "MPS", "Apple GPU"))


class NerfSettings(bpy.types.PropertyGroup):
    # Dataset
    dataset_dir: StringProperty(name="Folder", subtype="DIR_PATH", default="//nerf_dataset",
                                 description="Where the dataset is written (// is the .blend's folder)")
    train_views: IntProperty(name="Train Views", default=100, min=1, max=10000,
                              description="Training views, at random on the hemisphere (the protocol: 100)")
    val_views: IntProperty(name="Validation", default=10, min=1, max=10000,
                            description="Validation views, at random on the hemisphere (the protocol: 100)")
    test_views: IntProperty(name="Test", default=50, min=1, max=10000,
                             description="Test views, on the protocol's two-turn spiral (the protocol: 200)")
    resolution: IntProperty(name="Resolution", default=100, min=8, max=8192, description="Square image size in pixels")
    samples: IntProperty(name="Samples", default=64, min=1, max=65536,
                          description="Cycles samples per pixel of every view")
    render_device: EnumProperty(name="Device", items=(("CPU", "CPU", "Render on the CPU"), ("GPU", "GPU", "Cycles' GPU backend")),
                                default="CPU", description="What Cycles renders the views on")
    sphere: BoolProperty(name="Full Sphere", default=False, description="Train/val views on the full sphere, not the upper hemisphere")
    depth_normals: EnumProperty(name="Depth/Normals", default="test", description="Which views also get ground-truth depth and normal EXRs", items=(
        ("none", "None", "No depth or normals"), ("test", "Test Views", "Ground-truth depth and normals for the test views"),
        ("all", "All Views", "Ground-truth depth and normals for every view")))
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the random camera positions (and of training)")
    dataset_formats: EnumProperty(
        name="Also Write", options={"ENUM_FLAG"}, default=set(),
        description="Layouts written beside nerf_synthetic's, from the same render",
        items=tuple((name, label, text) for name, (label, text) in EXTRA_FORMATS.items()))
    # Training
    run_dir: StringProperty(name="Folder", subtype="DIR_PATH", default="//nerf_run",
                             description="Where training writes its checkpoint, events and renders")
    preset: EnumProperty(name="Preset", items=PRESETS, default="auto", description="The model and its training settings")
    budget_kind: EnumProperty(name="Budget", default="TIME", description="Stop training after a time or a number of steps", items=(
        ("TIME", "Time", "Train for a number of seconds"), ("ITERATIONS", "Iterations", "Train for a number of steps")))
    budget_seconds: FloatProperty(name="Seconds", default=120.0, min=1.0, description="Training seconds for the whole run: the learning rate and the grid's growth are scheduled to end with them")
    budget_iterations: IntProperty(name="Iterations", default=3000, min=1, description="Training steps for the whole run")
    train_device: EnumProperty(name="Device", items=DEVICES, default="auto", description="What the backend trains on")
    # Results: the camera animation and the mesh
    animation_step: IntProperty(name="Frame Step", default=1, min=1, max=1000,
                                description="Render every Nth frame of the scene's frame range")
    animation_cycles: BoolProperty(name="Beside Cycles", default=True,
                                   description="Also render the frames with Cycles (the dataset's settings) and make a "
                                               "side-by-side video with PSNR and SSIM per frame")
    animation_sequencer: BoolProperty(name="Add Strip", default=False,
                                      description="Add the finished video to the Video Sequencer as a movie strip")
    mesh_resolution: IntProperty(name="Mesh Grid", default=256, min=16, max=1024,
                                 description="Grid vertices along the scene box's longest side for the NeRF mesh")
    asset_triangles: IntProperty(
        name="Triangles", default=50000, min=100, max=5000000,
        description="The most triangles the NeRF asset keeps (its surface is decimated to them)")
    asset_texture_size: EnumProperty(
        name="Texture", default="2048", description="The NeRF asset's texture size",
        items=tuple((str(n), f"{n} px", f"A {n}×{n} texture") for n in (512, 1024, 2048, 4096)))
    # The live view
    live_view_anchor: PointerProperty(
        name="Move With", type=bpy.types.Object, poll=lambda _settings, obj: obj.type == "EMPTY",
        description="An Empty whose transform moves the NeRF in the live view (none: the NeRF sits where the "
                    "dataset's scene was, over its objects)")
    render_composite: BoolProperty(  # state, drawn as the button's pressed look, not as a checkbox
        name="NeRF in Renders", default=False, options={"HIDDEN"},
        description="Whether F12 renders and animations have the run's NeRF composited in by depth (set by the "
                    "NeRF in Renders button, which adds or removes its compositor nodes)")
    # Results of the last comparison (shown in the panel).
    # The last comparison's metrics as the backend lists them (compare.json's "metrics" table):
    # JSON rows {"key", "label", "value", "text"}; "" before any comparison.
    compare_metrics: StringProperty(name="Metrics", default="", description="The metrics of the last comparison with Cycles")


TORCH_BUILDS = (("auto", "Detect", "The build for this machine's GPU (NVIDIA: a CUDA build its driver runs; AMD on "
                                  "Linux: ROCm; Apple silicon: MPS; otherwise the CPU build)"),
                ("cpu", "CPU Only", "PyTorch's CPU build, the smallest download")) + tuple(
    (key, f"CUDA {needs[0]}.{needs[1]}", f"PyTorch's CUDA {needs[0]}.{needs[1]} build (the NVIDIA driver must support "
                                          f"CUDA {needs[0]}.{needs[1]} or newer)") for key, needs in CUDA_BUILDS) + (
    (ROCM_BUILD, f"ROCm {ROCM_BUILD[4:]}", "PyTorch's ROCm build for AMD GPUs (Linux)"),)


class NerfPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    python_path: StringProperty(
        name="Backend Python", subtype="FILE_PATH", default="",
        description="The Python that runs training (needs torch). Empty: the one Set Up Backend makes")
    torch_build: EnumProperty(name="PyTorch Build", items=TORCH_BUILDS, default="auto",
                              description="Which PyTorch build Set Up Backend installs")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "python_path")
        layout.label(text=f"In use: {backend_python(context) or 'none yet'}")
        layout.prop(self, "torch_build")
        build = torch_build(context)
        layout.label(text=f"Set Up Backend installs: {build.describe()}")
        layout.label(text=build.reason)
        layout.operator("nerf.setup_backend")


CLASSES = (NerfSettings, NerfPreferences)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.nerf = PointerProperty(type=NerfSettings)


def unregister() -> None:
    del bpy.types.Scene.nerf
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
