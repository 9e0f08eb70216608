"""A user's session with the installed extension, in real Blender (the bpy module), headless.

Run as ``python addon_session.py EXTENSION.zip WORK_DIR REPORT.json`` with a Python that has bpy
and torch (the add-on's training subprocess uses it as its backend Python), or with
``NERF_BACKEND_PYTHON`` naming the backend's Python when this one has only bpy. Steps, each
recorded in REPORT.json:

1. install the zip into a fresh user extensions repository and enable it; list what registered;
2. open ../shared/scenes/A.blend, generate a tiny dataset from the panel's operator (in this
   process: the bpy module has no Blender binary to spawn);
3. train the fast preset through the Train operator (a real backend subprocess), polling the
   add-on's own job code as its timer would, until done;
4. render the test views (loaded as images) and compare the active camera with Cycles; the
   camera's animation; NeRF in Renders (F12 with the NeRF composited by depth); the NeRF mesh,
   and the baked asset (a job, imported, F12 in Cycles and EEVEE);
5. disable and remove the extension; list what is left.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import bpy

ZIP, WORK, REPORT = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
# NERF_TEST_SCENE: where the test found it (inside a chroot ../shared may be elsewhere).
SCENE = Path(os.environ.get("NERF_TEST_SCENE", Path(__file__).resolve().parents[3] / "shared" / "scenes" / "A.blend"))
PACKAGE_ID = "nerf_from_blender"
report: dict = {"blender": bpy.app.version_string}
stage_seconds: dict[str, float] = {}  # each step's wall time, under its report key: where the session's time goes
_last_save = time.time()


def save() -> None:
    global _last_save
    now = time.time()
    stage_seconds[[key for key in report if key != "stage_seconds"][-1]] = round(now - _last_save, 1)
    _last_save = now
    report["stage_seconds"] = stage_seconds
    REPORT.write_text(json.dumps(report, indent=1, default=str))


def nerf_classes() -> list[str]:
    return sorted(name for name in dir(bpy.types) if name.startswith(("NERF_PT_", "NERF_OT_")))


# 1. install and enable
repo = bpy.context.preferences.extensions.repos.new(name="test", module="test_repo", custom_directory=str(WORK / "repo"))
result = bpy.ops.extensions.package_install_files(filepath=str(ZIP), repo=repo.module, enable_on_install=True)
module = f"bl_ext.{repo.module}.{PACKAGE_ID}"
report["install"] = {"result": sorted(result), "enabled": module in bpy.context.preferences.addons,
                     "classes": nerf_classes(), "installed_files": sorted(p.name for p in (WORK / "repo" / PACKAGE_ID).iterdir()),
                     "datasets_gen": getattr(sys.modules.get("datasets_gen"), "__file__", None)}

def _tooltips(rna) -> dict[str, str]:
    """Every user-facing property's tooltip, and each enum item's, as Blender shows them."""
    tips = {}
    for prop in rna.properties:
        if prop.identifier in ("rna_type", "name", "bl_idname"):
            continue
        tips[prop.identifier] = prop.description
        if prop.type == "ENUM":
            tips.update({f"{prop.identifier}.{item.identifier}": item.description for item in prop.enum_items})
    return tips


from nerf_contract import training_events  # noqa: E402  (from the extension's wheel, installed just now)
from nerf_contract.run_layout import EVENTS_NAME  # noqa: E402

addon = bpy.context.preferences.addons[module]
report["tooltips"] = {**_tooltips(bpy.types.Scene.bl_rna.properties["nerf"].fixed_type.bl_rna),
                      **{f"preferences.{k}": v for k, v in _tooltips(addon.preferences.bl_rna).items()}}
# The PyTorch build Set Up Backend would install here, detected and forced in the preferences.
builds = {}
for choice in ("auto", "cu128"):
    addon.preferences.torch_build = choice
    build = sys.modules[f"{module}.blender.paths"].torch_build(bpy.context)
    builds[choice] = {"key": build.key, "index_url": build.index_url, "text": build.describe()}
addon.preferences.torch_build = "auto"
report["torch_builds"] = builds
save()

# 2. a dataset from a real scene, through the panel's operator
bpy.ops.wm.open_mainfile(filepath=str(SCENE))
addon = bpy.context.preferences.addons[module]
# The backend's Python: this one (it has torch), or the one named (a bpy-only LTS venv).
addon.preferences.python_path = os.environ.get("NERF_BACKEND_PYTHON", sys.executable)
settings = bpy.context.scene.nerf
settings.dataset_dir = str(WORK / "dataset")
settings.run_dir = str(WORK / "run")
settings.train_views, settings.val_views, settings.test_views = 24, 2, 3
settings.resolution, settings.samples = 32, 8
job_timer, paths = sys.modules[f"{module}.blender.job_timer"], sys.modules[f"{module}.blender.paths"]
report["scene_warnings"] = sys.modules[f"{module}.blender.dataset_ops"].scene_warnings(bpy.context)
start = time.time()
report["generate"] = {"result": sorted(bpy.ops.nerf.generate_dataset("EXEC_DEFAULT")), "seconds": time.time() - start,
                      "files": sorted(p.name for p in (WORK / "dataset").iterdir())}
save()

def follow(folder: str, states: list):
    """Call the add-on's timer as Blender would (it does not fire in the background module) until
    it unregisters itself (returns None), recording the job in ``folder`` each time; its last status."""
    deadline = time.time() + 600
    while time.time() < deadline:
        again = job_timer._tick()
        state = job_timer.status[folder]
        states.append([state.state, round(state.fraction, 3), state.detail])
        if again is None:
            break
        time.sleep(again)
    return state


# 3. training in a backend subprocess, watched through the add-on's job code
settings.preset, settings.budget_kind, settings.budget_iterations = "fast", "ITERATIONS", 300
start = time.time()
report["train"] = {"result": sorted(bpy.ops.nerf.train()), "returned_after_s": time.time() - start, "states": []}
report["train"]["timer_registered"] = bpy.app.timers.is_registered(job_timer._tick)
state = follow(str(paths.run_dir(bpy.context)), report["train"]["states"])
report["train"]["final"] = {"state": state.state, "detail": state.detail, "error": state.error,
                            "preview_image": sys.modules[f"{module}.blender.images"].PREVIEW_IMAGE in bpy.data.images,
                            "cpu_threads": [e.cpu_threads for e in training_events.read_events(
                                paths.run_dir(bpy.context) / EVENTS_NAME) if isinstance(e, training_events.Start)],
                            "cpu_threads_asked": sys.modules[f"{module}.core.jobs"].training_cpu_threads()}
save()

# 4. results: test views as images, and the active camera against Cycles
report["render_test_views"] = {"result": sorted(bpy.ops.nerf.render_test_views())}
report["render_test_views"]["images"] = {image.name: list(image.size) for image in bpy.data.images
                                         if image.name.startswith("NeRF test")}
test_frame = json.loads((WORK / "dataset" / "transforms_test.json").read_text())
frame = test_frame["frames"][1]["transform_matrix"]
similarity = test_frame["world_to_nerf"]
scale, translation = similarity["scale"], similarity["translation"]
# The active camera: test view 1's pose mapped back from the NeRF frame into Blender's world.
camera_data = bpy.data.cameras.new("compare")
camera = bpy.data.objects.new("compare", camera_data)
bpy.context.scene.collection.objects.link(camera)
import mathutils  # noqa: E402

matrix = mathutils.Matrix(frame)
matrix.translation = (mathutils.Vector(matrix.translation) - mathutils.Vector(translation)) / scale
camera.matrix_world = matrix
bpy.context.scene.camera = camera
report["render_active_camera"] = {"result": sorted(bpy.ops.nerf.render_active_camera()),
                                  "size": list(bpy.data.images["NeRF active camera"].size)}


def scene_settings() -> tuple:
    scene = bpy.context.scene
    return (scene.render.engine, scene.render.resolution_x, scene.render.resolution_y, scene.render.film_transparent,
            scene.render.filepath, scene.cycles.samples, scene.cycles.device, scene.cycles.use_denoising,
            scene.view_settings.view_transform, scene.render.image_settings.file_format)


settings_before_compare = scene_settings()
compare_result = sorted(bpy.ops.nerf.compare())
rows = {row["key"]: row for row in json.loads(settings.compare_metrics)}
report["compare"] = {"result": compare_result, "psnr": rows["psnr"]["value"],
                     "ssim": rows["ssim"]["value"], "lpips": rows["lpips"]["text"],
                     "images": {name: list(bpy.data.images[name].size) for name in
                                ("Cycles active camera", "NeRF active camera", "NeRF difference", "NeRF comparison")
                                if name in bpy.data.images}}
# Compare renders through the generator's settings journal: the scene's own settings come back
# (checked above and below), and a generator error (a GPU asked for where there is none) is a
# report, not a traceback.
report["compare"]["scene_settings_kept"] = scene_settings() == settings_before_compare
settings.render_device = "GPU"
try:
    report["compare_gpu"] = {"result": sorted(bpy.ops.nerf.compare()), "message": ""}
except RuntimeError as error:  # the bpy module turns an operator's error report into this
    report["compare_gpu"] = {"result": ["CANCELLED"], "message": str(error)}
report["compare_gpu"]["scene_settings_kept"] = scene_settings() == settings_before_compare
settings.render_device = "CPU"
save()

# The active camera's animation: three keyed poses (frames 1-3), Cycles' frames and the NeRF's,
# as a job; the finished video in an image and a sequencer strip.
scene = bpy.context.scene
for frame, x in ((1, -0.2), (2, 0.0), (3, 0.2)):
    camera.location.x = matrix.translation.x + x
    camera.keyframe_insert("location", index=0, frame=frame)
scene.frame_start, scene.frame_end = 1, 3
scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 40, 30, 100
settings.animation_cycles, settings.animation_sequencer = True, True
report["animation"] = {"result": sorted(bpy.ops.nerf.render_animation()), "states": []}
state = follow(str(paths.animation_dir(bpy.context)), report["animation"]["states"])
report["animation"]["final"] = {"state": state.state, "detail": state.detail, "error": state.error,
                                "warning": state.warning, "shown": state.extra.get("shown")}
save()

# NeRF in Renders: F12 of a frame and of the camera's animation with the NeRF composited by
# depth (render_composite_check.py says how; tests/test_addon.py scores the images).
sys.path.insert(0, str(Path(__file__).resolve().parent))
import render_composite_check  # noqa: E402

# EEVEE in 4.2 and 5.0 only, one of each of Z Combine's APIs (properties, inputs): an EEVEE render
# after the first takes the bpy module about 50 s here.
report["render_composite"] = render_composite_check.run(
    bpy.context, module, WORK, [obj for obj in scene.objects if obj.type == "MESH" and obj.visible_get()],
    eevee=bpy.app.version[:2] in ((4, 2), (5, 0)))
save()

# The NeRF's surface as a mesh over the original: its bounds, and where rays from outside hit it.
from mathutils.bvhtree import BVHTree  # noqa: E402

settings.mesh_resolution = 96
originals = [obj for obj in scene.objects if obj.type == "MESH" and obj.visible_get()]
report["mesh"] = {"result": sorted(bpy.ops.nerf.import_mesh())}
nerf_mesh = bpy.data.objects.get("NeRF mesh")


def world_bounds(objects) -> list[list[float]]:
    corners = [obj.matrix_world @ mathutils.Vector(corner) for obj in objects for corner in obj.bound_box]
    return [[min(c[i] for c in corners) for i in range(3)], [max(c[i] for c in corners) for i in range(3)]]


def scene_tree(objects) -> BVHTree:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    vertices, polygons = [], []
    for obj in objects:
        mesh = obj.evaluated_get(depsgraph).to_mesh()
        offset = len(vertices)
        vertices += [obj.matrix_world @ v.co for v in mesh.vertices]
        polygons += [[offset + i for i in p.vertices] for p in mesh.polygons]
        obj.evaluated_get(depsgraph).to_mesh_clear()
    return BVHTree.FromPolygons(vertices, polygons)


if nerf_mesh is not None:
    truth, ours = world_bounds(originals), world_bounds([nerf_mesh])
    radius = (mathutils.Vector(truth[1]) - mathutils.Vector(truth[0])).length / 2
    truth_tree, our_tree = scene_tree(originals), scene_tree([nerf_mesh])
    hits = []  # rays from outside aimed at each object's centre, from five sides
    for obj in originals:
        low, high = world_bounds([obj])
        target = (mathutils.Vector(low) + mathutils.Vector(high)) / 2
        for direction in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1)):
            d = mathutils.Vector(direction)
            origin = target + 3 * radius * d
            a, b = truth_tree.ray_cast(origin, -d), our_tree.ray_cast(origin, -d)
            hits.append([None if a[0] is None else (a[0] - origin).length,
                         None if b[0] is None else (b[0] - origin).length])
    material = nerf_mesh.active_material
    report["mesh"].update(bounds_truth=truth, bounds_nerf=ours, radius=radius, hits=hits,
                          vertices=len(nerf_mesh.data.vertices),
                          colour_attributes=[a.name for a in nerf_mesh.data.color_attributes],
                          material=material.name if material else None,
                          material_nodes=sorted(n.bl_idname for n in material.node_tree.nodes) if material else [])
save()

# The NeRF baked into an asset (a job), imported over the original, rendered with F12 by Cycles
# and EEVEE from the active camera beside the originals' own Cycles render.
settings.asset_triangles, settings.asset_texture_size = 5000, "512"
report["asset"] = {"result": sorted(bpy.ops.nerf.import_asset()), "states": []}
state = follow(str(paths.asset_dir(bpy.context)), report["asset"]["states"])
report["asset"]["final"] = {"state": state.state, "detail": state.detail, "error": state.error,
                            "warning": state.warning, "imported": state.extra.get("imported")}
asset = bpy.data.objects.get(report["asset"]["final"]["imported"] or "")
if asset is not None:
    material = asset.active_material
    image_nodes = [n for n in material.node_tree.nodes if n.type == "TEX_IMAGE" and n.image] if material else []
    images = [n.image for n in image_nodes]
    report["asset"].update(bounds_truth=world_bounds(originals), bounds_asset=world_bounds([asset]),
                           triangles=sum(len(p.vertices) - 2 for p in asset.data.polygons),
                           material_nodes=sorted(n.type for n in material.node_tree.nodes) if material else [],
                           texture=list(images[0].size) if images else None,
                           texture_extension=image_nodes[0].extension if image_nodes else None)

    def f12(engine: str, shown: list, view_transform: str, stem: str) -> str:
        """The scene rendered by ``engine`` with only ``shown`` visible, on a transparent film."""
        hidden = {obj.name: obj.hide_render for obj in scene.objects}
        for obj in scene.objects:
            if obj.type == "MESH":
                obj.hide_render = obj not in shown
        try:
            scene.render.engine = engine
        except TypeError:  # EEVEE is BLENDER_EEVEE_NEXT in 4.2-4.5
            scene.render.engine = "BLENDER_EEVEE_NEXT"
        if engine == "CYCLES":
            scene.cycles.samples, scene.cycles.device = 16, "CPU"
        scene.render.film_transparent, scene.view_settings.view_transform = True, view_transform
        scene.render.use_sequencer = False  # the animation's video strip, added above, would be rendered instead
        scene.render.filepath = str(WORK / f"f12_{stem}.png")
        result = sorted(bpy.ops.render.render(write_still=True))
        for obj in scene.objects:
            obj.hide_render = hidden[obj.name]
        return [result[0], scene.render.filepath]

    view_transform = scene.view_settings.view_transform  # the scene's own (A.blend: Filmic)
    # The dataset was rendered with the Standard view (the generator's colour management), and
    # the texture holds its images' colours: both shown through Standard.
    report["asset"]["f12"] = {
        "truth": f12("CYCLES", originals, "Standard", "truth"),
        "cycles": f12("CYCLES", [asset], "Standard", "asset_cycles"),
        "eevee": f12("BLENDER_EEVEE", [asset], "Standard", "asset_eevee"),
    }
    scene.view_settings.view_transform = view_transform
save()

# The report, written by the backend and opened (where there is a browser; none here).
report["open_report"] = {"result": sorted(bpy.ops.nerf.open_report()),
                         "page": (WORK / "run" / "report" / "index.html").is_file()}

# Train more, then Cancel from the panel: the backend saves and stops.
settings.budget_iterations = 100_000
report["cancel"] = {"resume": sorted(bpy.ops.nerf.train(resume=True))}
while job_timer.status[str(paths.run_dir(bpy.context))].state != "running" or \
        (job_timer.status[str(paths.run_dir(bpy.context))].iteration or 0) < 320:
    job_timer._tick()
    time.sleep(0.5)
report["cancel"]["result"] = sorted(bpy.ops.nerf.cancel_training())
while job_timer._tick() is not None:
    time.sleep(0.5)
state = job_timer.status[str(paths.run_dir(bpy.context))]
report["cancel"]["final"] = [state.state, state.iteration]
save()

# 5. disable and remove
import addon_utils  # noqa: E402

addon_utils.disable(module, default_set=True)
report["disable"] = {"enabled": module in bpy.context.preferences.addons, "classes": nerf_classes(),
                     "scene_property": hasattr(bpy.types.Scene, "nerf")}
result = bpy.ops.extensions.package_uninstall(repo_index=list(bpy.context.preferences.extensions.repos).index(repo),
                                              pkg_id=PACKAGE_ID)
report["uninstall"] = {"result": sorted(result), "left": (WORK / "repo" / PACKAGE_ID).exists()}
save()
