"""A user's session with the add-on in the real Blender program, GUI drawn (Xvfb), every button
pressed through Blender's own event system (``--enable-event-simulate``).

Run by tests/test_gui.py inside the Blender GUI chroot (tests/blender_gui.py) as::

    blender --factory-startup --enable-event-simulate --python gui_session.py -- WORK BACKEND_PYTHON

with the extension installed in the user repository. The flow, on Blender's default scene
(a cube, a light, a camera): open the sidebar's NeRF tab; press Train before any dataset
(a failed run); Generate Dataset (its dialog, confirmed with Return); Train, Cancel, Resume to
the end; Render Test Views; Compare with Cycles; Open Report (``$BROWSER`` is a stub that
records the URL). A screenshot of the whole screen is taken in each state the panel can
show (``import -window root``: Blender's own screenshot is black under llvmpipe), and
everything measured goes to WORK/gui_report.json.

A button is found the way a user finds it, by looking: the panel is drawn once more with
only that button in Blender's alert colour, and the pixels that changed are the button.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import traceback
from pathlib import Path

import blf
import bpy
import mathutils
import numpy as np

WORK, BACKEND_PYTHON = Path(sys.argv[sys.argv.index("--") + 1]), sys.argv[sys.argv.index("--") + 2]
MODULE = "bl_ext.user_default.nerf_from_blender"
SHOTS = WORK / "screenshots"
REPORT = WORK / "gui_report.json"
report: dict = {"blender": bpy.app.version_string, "steps": [], "shots": {}, "panel_regions": {}, "progress": [],
                "labels": {}, "clicks": {}}


def save() -> None:
    REPORT.write_text(json.dumps(report, indent=1, default=str))


def log(message: str) -> None:
    print(f"gui_session: {message}", flush=True)
    report["steps"].append(message)
    save()


def job_timer():
    return sys.modules[MODULE + ".blender.job_timer"]


def panel_classes() -> list:
    return list(sys.modules[MODULE + ".blender.panel"].CLASSES)


def view3d():
    window = bpy.context.window_manager.windows[0]
    area = next(a for a in window.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "UI")
    return window, area, region


def redraw() -> None:
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            area.tag_redraw()
    window, area, region = view3d()
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.wm.redraw_timer(type="DRAW_WIN_SWAP", iterations=1)


def grab(path: Path) -> np.ndarray:
    """The whole X screen as RGB floats, rows bottom-up (as Blender's window coordinates)."""
    subprocess.run(["import", "-window", "root", str(path)], check=True, timeout=60)
    image = bpy.data.images.load(str(path), check_existing=False)
    width, height = image.size
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return pixels.reshape(height, width, 4)[..., :3]


def window_origin(screen: np.ndarray) -> tuple[int, int]:
    """Where the main window's (0, 0) lies in the screen image (rows bottom-up). Without a
    window manager Blender's window sits at the screen's top left."""
    window = view3d()[0]
    return 0, screen.shape[0] - window.height


def region_box(screen: np.ndarray) -> tuple[int, int, int, int]:
    """The sidebar's rectangle in the screen image: x0, y0, x1, y1 (rows bottom-up)."""
    _, _, region = view3d()
    ox, oy = window_origin(screen)
    return ox + region.x, oy + region.y, ox + region.x + region.width, oy + region.y + region.height


def editor_box(screen: np.ndarray) -> tuple[int, int, int, int] | None:
    """The Image Editor's rectangle in the screen image (rows bottom-up), in whichever window
    shows one; None without one."""
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                region = next(r for r in area.regions if r.type == "WINDOW")
                # Without a window manager a window's x, y are its bottom-left corner on the screen.
                x0, y0 = window.x + region.x, window.y + region.y
                return max(x0, 0), max(y0, 0), min(x0 + region.width, screen.shape[1]), min(y0 + region.height, screen.shape[0])
    return None


def shot(name: str):
    """A screenshot of state ``name``: kept as WORK/screenshots/NAME.png, with the statistics of
    what the state is about: the sidebar, or the Image Editor the add-on opened."""
    redraw()
    yield 0.3
    redraw()
    path = SHOTS / f"{name}.png"
    screen = grab(path)
    editor = editor_box(screen)
    x0, y0, x1, y1 = editor if editor is not None else region_box(screen)
    panel = screen[y0:y1, x0:x1]
    np.save(SHOTS / f"{name}.panel.npy", panel)
    report["shots"][name] = {"path": str(path), "std": float(screen.std()), "panel_std": float(panel.std()),
                             "size": [screen.shape[1], screen.shape[0]], "panel_box": [x0, y0, x1, y1],
                             "focus": "image editor" if editor is not None else "sidebar"}
    log(f"screenshot {name}")


class _Probe:
    """A layout that draws like the real one, except that the target button is in alert colour."""

    def __init__(self, layout, matches) -> None:
        object.__setattr__(self, "_layout", layout)
        object.__setattr__(self, "_matches", matches)

    def __getattr__(self, name):
        attribute = getattr(self._layout, name)
        if name in ("row", "column", "box", "split", "grid_flow", "column_flow"):
            return lambda *args, **kwargs: _Probe(attribute(*args, **kwargs), self._matches)
        if name == "operator":
            def operator(idname, *args, **kwargs):
                if not self._matches(idname, kwargs):
                    return attribute(idname, *args, **kwargs)
                alert = self._layout.alert
                self._layout.alert = True  # read when the button is made
                try:
                    return attribute(idname, *args, **kwargs)
                finally:
                    self._layout.alert = alert
            return operator
        return attribute

    def __setattr__(self, name, value):
        setattr(self._layout, name, value)


class _PanelSelf:
    def __init__(self, layout) -> None:
        self.layout = layout


def _probing_draw(original, matches):
    # A closure, not a default argument: Blender passes a method as many arguments as its code
    # declares, so draw(self, context, _original=...) would be called with a missing third one.
    def draw(self, context):
        original(_PanelSelf(_Probe(self.layout, matches)), context)
    return draw


def _find_alert_button(matches):
    """One look: the panel drawn as it is, then again with the matching button in the alert
    colour. Returns the box (x0, y0, x1, y1, rows bottom-up, in the sidebar crop) of what
    turned red, or None; the sidebar's box in the screen image; the window's origin there."""
    redraw()  # the panel as it is now (a setting changed since the last draw moves buttons)
    yield 0.3
    redraw()
    before = grab(SHOTS / "_locate_before.png")
    originals = {cls: cls.draw for cls in panel_classes()}
    for cls, original in originals.items():
        cls.draw = _probing_draw(original, matches)
    try:
        redraw()
        yield 0.3
        redraw()
        after = grab(SHOTS / "_locate_after.png")
    finally:
        for cls, draw in originals.items():
            cls.draw = draw
        redraw()
    x0, y0, x1, y1 = region_box(before)
    # Pixels that turned red: a progress bar or a label redrawn meanwhile changes too, but not to red.
    crop = after[y0:y1, x0:x1]
    redness = crop[..., 0] - crop[..., 1:].max(axis=2)
    changed = (np.abs(crop - before[y0:y1, x0:x1]).max(axis=2) > 0.08) & (redness > 0.15)
    # A button is a filled bar; the 3D View's red axis line, seen through the sidebar where a
    # panel shrank, is a thin diagonal: keep rows and columns with many changed pixels.
    changed &= (changed.sum(axis=1) >= 30)[:, None] & (changed.sum(axis=0) >= 8)[None, :]
    rows, columns = np.nonzero(changed)
    found = None if rows.size == 0 else (columns.min(), rows.min(), columns.max(), rows.max())
    return found, (x0, y0, x1, y1), window_origin(before)


def locate(idname: str, text: str | None = None):
    """Find the button by drawing it in the alert colour and looking at what changed,
    scrolling the sidebar down (mouse wheel events) as a user would when it is below the
    edge; its centre in window coordinates is left in report['clicks'][key]."""
    key = f"{idname}:{text or ''}"

    def matches(name, kwargs):
        return name == idname and kwargs.get("text") == text

    for attempt in range(8):
        found, (x0, y0, x1, y1), (ox, oy) = yield from _find_alert_button(matches)
        if found is not None and found[1] > 2:  # whole, not cut by the sidebar's lower edge
            break
        # Below the edge: scroll down, over the sidebar.
        window = view3d()[0]
        x, y = (x0 + x1) // 2 - ox, (y0 + y1) // 2 - oy
        window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
        for _ in range(4):
            window.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=x, y=y)
        report.setdefault("scrolled", []).append(key)
        yield 0.5
    else:
        raise AssertionError(f"button {key} is not drawn in the sidebar, even scrolled down")
    cx0, cy0, cx1, cy1 = found
    centre = (int(x0 + (cx0 + cx1) / 2) - ox, int(y0 + (cy0 + cy1) / 2) - oy)
    report["clicks"][key] = {"centre": centre, "size": [int(cx1 - cx0 + 1), int(cy1 - cy0 + 1)]}
    yield 0.1


def press(idname: str, text: str | None = None):
    """Move the mouse onto the button and click it, as events."""
    yield from locate(idname, text)
    x, y = report["clicks"][f"{idname}:{text or ''}"]["centre"]
    window = view3d()[0]
    window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    yield 0.3
    window.event_simulate(type="LEFTMOUSE", value="PRESS", x=x, y=y)
    window.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x, y=y)
    log(f"pressed {idname} {text or ''} at {x}, {y}")
    yield 0.5


def key(type_: str):
    window = view3d()[0]
    window.event_simulate(type=type_, value="PRESS")
    window.event_simulate(type=type_, value="RELEASE")
    yield 0.5


def job(folder: str):
    return job_timer().status.get(str(Path(folder).resolve()))


def wait(predicate, timeout: float, what: str):
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > timeout:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        yield 0.25


def state_of(folder: str) -> str | None:
    status = job(folder)
    return status.state if status is not None else None


def close_extra_windows():
    """Windows the add-on opened (the Image Editor), closed again so the sidebar is visible."""
    for window in list(bpy.context.window_manager.windows)[1:]:
        with bpy.context.temp_override(window=window):
            bpy.ops.wm.window_close()
    yield 0.5


def label_widths() -> None:
    """Every property label's width in pixels at the UI's font size, against the label column
    of the property split at this sidebar width (a label wider than that is cut off)."""
    preferences = bpy.context.preferences
    style = preferences.ui_styles[0]
    points = (getattr(style, "widget", None) or style.widget_label).points
    scale = preferences.system.ui_scale
    blf.size(0, points * scale)
    _, _, region = view3d()
    # Property split: 40 % of the panel's inner width (the region less its margins) for the label.
    column = 0.4 * (region.width - 2 * 10 * scale) - 0.4 * 20 * scale
    settings = bpy.context.scene.nerf
    labels = {prop.identifier: prop.name for prop in settings.bl_rna.properties
              if prop.identifier not in ("rna_type", "name") and not prop.identifier.startswith("compare_")
              and not prop.is_hidden}  # state an operator sets, drawn as a button, not a label
    # A set of flags (ENUM_FLAG) is drawn as one row of toggle buttons sharing the value column.
    value_column = 0.6 * (region.width - 2 * 10 * scale)
    flags = {prop.identifier: {"button_px": value_column / len(prop.enum_items),
                               "widths_px": {item.name: blf.dimensions(0, item.name)[0] for item in prop.enum_items}}
             for prop in settings.bl_rna.properties if prop.type == "ENUM" and prop.is_enum_flag}
    report["labels"] = {"column_px": column, "region_width_px": region.width, "text_margins_px": 2 * 0.4 * 20 * scale,
                        "widths_px": {name: blf.dimensions(0, text)[0] for name, text in labels.items()},
                        "texts": labels, "flag_buttons": flags}


def enable_add_on():
    """The add-on enabled, the backend's Python chosen and checked (as a user does once)."""
    bpy.ops.preferences.addon_enable(module=MODULE)
    preferences = bpy.context.preferences.addons[MODULE].preferences
    preferences.python_path = BACKEND_PYTHON
    log(f"enabled {MODULE}; backend {BACKEND_PYTHON}")
    ok, message = sys.modules[MODULE + ".core.backend_setup"].check_backend(BACKEND_PYTHON)
    assert ok, f"the backend's Python cannot run from this Blender: {message}"
    log(f"backend: {message}")
    yield 0.1


def open_nerf_tab():
    """The splash closed, the 3D View's sidebar opened on its NeRF tab."""
    yield from key("ESC")  # the splash screen, which --factory-startup shows over the 3D View
    window, area, region = view3d()
    area.spaces.active.show_region_ui = True
    yield 1.0
    for _ in range(40):  # read-only until the sidebar has drawn once
        try:
            view3d()[2].active_panel_category = "NeRF"
            break
        except (TypeError, AttributeError):
            redraw()
            yield 0.25
    else:
        raise AssertionError("the sidebar's NeRF tab could not be opened")


def flow():
    yield from enable_add_on()
    settings = bpy.context.scene.nerf
    yield from open_nerf_tab()
    window = view3d()[0]
    report["panel_regions"] = {"window": [window.width, window.height], "sidebar": [view3d()[2].width, view3d()[2].height]}
    settings.dataset_dir = str(WORK / "dataset")
    settings.run_dir = str(WORK / "run_too_early")
    settings.train_views, settings.val_views, settings.test_views = 16, 2, 3
    settings.resolution, settings.samples = 48, 128  # a few seconds of rendering: long enough to be seen
    # An iteration budget: what the run reaches does not depend on the machine's speed.
    # Long enough that Cancel comes before the end on a quiet machine; the resume is then short.
    settings.preset, settings.budget_kind, settings.budget_iterations = "fast", "ITERATIONS", 3000
    label_widths()
    yield from shot("01_idle")

    # Train before there is a dataset: the backend fails and the panel says why.
    yield from press("nerf.train", None)
    yield from wait(lambda: state_of(settings.run_dir) == "failed", 120, "the early training to fail")
    report["failed_error"] = job(settings.run_dir).error
    yield from shot("02_failed")

    # Generate Dataset: its dialog lists the scene checks; Return confirms.
    yield from press("nerf.generate_dataset", None)
    yield 1.0
    yield from shot("03_dataset_dialog")
    yield from key("RET")
    yield from wait(lambda: state_of(settings.dataset_dir) == "running" and job(settings.dataset_dir).fraction > 0,
                    120, "the dataset to start rendering")
    report["progress"].append(["dataset", job(settings.dataset_dir).fraction])
    yield from shot("04_dataset_rendering")
    yield from wait(lambda: state_of(settings.dataset_dir) == "done", 600, "the dataset to finish")
    yield from shot("05_dataset_done")

    # Train, watch the bar move, cancel, resume to the end.
    settings.run_dir = str(WORK / "run")
    yield from press("nerf.train", None)
    yield from wait(lambda: state_of(settings.run_dir) == "running" and (job(settings.run_dir).iteration or 0) > 0,
                    120, "training to start")
    for _ in range(6):
        report["progress"].append(["train", job(settings.run_dir).fraction, job(settings.run_dir).iteration])
        yield 1.0
    yield from shot("06_training")
    yield from press("nerf.cancel_training", None)
    yield from wait(lambda: state_of(settings.run_dir) == "cancelled", 120, "training to stop")
    report["cancelled_at"] = job(settings.run_dir).iteration
    yield from shot("07_cancelled")
    settings.budget_iterations = report["cancelled_at"] + 100
    yield from press("nerf.train", "Resume")
    yield from wait(lambda: state_of(settings.run_dir) == "done", 600, "the resumed training to finish")
    report["done"] = {"iteration": job(settings.run_dir).iteration, "detail": job(settings.run_dir).detail,
                      "preview": sys.modules[MODULE + ".blender.images"].PREVIEW_IMAGE in bpy.data.images}
    yield from shot("08_trained")

    # Results where the user looks: an Image Editor.
    yield from press("nerf.render_test_views", None)
    yield from wait(lambda: "NeRF test r_0" in bpy.data.images, 300, "the test renders")
    report["render_test_views"] = {"windows": len(bpy.context.window_manager.windows),
                                   "editor_image": _editor_image()}
    yield 1.0  # the editor zooms to fit once drawn
    yield from shot("09_results")
    yield from close_extra_windows()
    yield from press("nerf.compare", None)
    yield from wait(lambda: bool(settings.compare_metrics), 300, "the comparison")
    rows = {row["key"]: row for row in json.loads(settings.compare_metrics)}
    report["compare"] = {"psnr": rows["psnr"]["value"], "ssim": rows["ssim"]["value"], "lpips": rows["lpips"]["text"],
                         "windows": len(bpy.context.window_manager.windows), "editor_image": _editor_image()}
    yield 1.0
    yield from shot("10_compared")
    yield from close_extra_windows()
    yield from shot("11_compare_numbers")
    yield from press("nerf.open_report", None)
    urls = WORK / "browser_urls.txt"
    yield from wait(urls.is_file, 300, "the report to open in the browser")
    report["open_report"] = urls.read_text().split()

    # The scene camera's animation beside Cycles (a background Blender, then the backend), and
    # the NeRF's mesh imported over the cube.
    scene = bpy.context.scene
    camera = scene.camera
    for frame, dx in ((1, -0.3), (2, 0.0), (3, 0.3)):
        camera.location.x += dx
        camera.keyframe_insert("location", index=0, frame=frame)
        camera.location.x -= dx
    scene.frame_start, scene.frame_end = 1, 3
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 48, 100
    settings.animation_cycles, settings.animation_sequencer = True, True
    folder = str(WORK / "run" / "animation" / "Camera")
    yield from press("nerf.render_animation", None)
    yield from wait(lambda: state_of(folder) not in (None, "idle"), 120, "the animation job to start")
    stages = set()
    for _ in range(600):
        status = job(folder)
        if status is not None and status.state == "running":
            stages.add(status.detail.split(":")[0])
        if status is not None and status.state != "running":
            break
        yield 0.25
    status = job(folder)
    report["animation"] = {"state": status.state, "detail": status.detail, "error": status.error,
                           "stages": sorted(stages), "editor_image": _editor_image(),
                           "strips": [[strip.name, strip.frame_final_duration] for strip in
                                      (getattr(scene.sequence_editor, "strips", None) or scene.sequence_editor.sequences)]
                           if scene.sequence_editor else []}
    yield 1.0
    yield from shot("12_animation")
    yield from close_extra_windows()
    yield from press("nerf.import_mesh", None)
    yield from wait(lambda: "NeRF mesh" in bpy.data.objects, 300, "the NeRF mesh")
    mesh = bpy.data.objects["NeRF mesh"]
    report["mesh"] = {"vertices": len(mesh.data.vertices), "material": mesh.active_material.name,
                      "bounds": [list(mesh.matrix_world @ mathutils.Vector(corner)) for corner in mesh.bound_box]}
    yield from shot("13_mesh")

    # The NeRF baked into an asset (a job with its bar), imported over the cube and drawn in the
    # viewport with its texture (Material Preview), the cube and the mesh hidden.
    _, area, _ = view3d()
    area.spaces.active.shading.type = "MATERIAL"
    for obj in (bpy.data.objects["Cube"], mesh):
        obj.hide_set(True)
    yield 1.0
    empty_view = viewport_pixels()
    settings.asset_triangles, settings.asset_texture_size = 2000, "512"
    folder = str(WORK / "run" / "asset")
    yield from press("nerf.import_asset", None)
    yield from wait(lambda: state_of(folder) not in (None, "idle"), 120, "the asset job to start")
    report["asset_progress"] = []
    for _ in range(1200):
        status = job(folder)
        if status is not None and status.state == "running":
            report["asset_progress"].append([status.fraction, status.detail])
        if status is not None and status.state != "running":
            break
        yield 0.1
    yield from wait(lambda: "NeRF asset" in bpy.data.objects, 60, "the asset to be imported")
    yield 2.0  # Material Preview compiles the new material's shader
    status, asset = job(folder), bpy.data.objects["NeRF asset"]
    yield from shot("14_asset")
    shown_view = viewport_pixels()
    window, area, region = view3d()
    viewport = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=window, area=area, region=viewport):
        start = time.perf_counter()
        bpy.ops.wm.redraw_timer(type="DRAW", iterations=20)  # the viewport alone, redrawn 20 times
        frame_seconds = (time.perf_counter() - start) / 20
    report["asset"] = {"state": status.state, "detail": status.detail, "error": status.error,
                       "triangles": sum(len(p.vertices) - 2 for p in asset.data.polygons),
                       "bounds": [list(asset.matrix_world @ mathutils.Vector(corner)) for corner in asset.bound_box],
                       "viewport_changed": float((np.abs(shown_view - empty_view).max(axis=2) > 0.05).mean()),
                       "viewport_fps": 1.0 / frame_seconds}
    log("flow finished")


def viewport_pixels() -> np.ndarray:
    """The 3D viewport's own pixels (its WINDOW region) in a fresh screenshot."""
    redraw()
    screen = grab(SHOTS / "viewport.png")
    _, area, _ = view3d()
    region = next(r for r in area.regions if r.type == "WINDOW")
    ox, oy = window_origin(screen)
    return screen[oy + region.y:oy + region.y + region.height, ox + region.x:ox + region.x + region.width]


def _editor_image() -> str | None:
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR" and area.spaces.active.image is not None:
                return area.spaces.active.image.name
    return None


def quit_blender() -> None:
    with bpy.context.temp_override(window=bpy.context.window_manager.windows[0]):
        bpy.ops.wm.quit_blender()


def main(flow) -> None:
    """Runs the generator ``flow`` from Blender's timers (each yield: seconds until the next
    step), then quits; every failure goes to the report."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    steps = flow()

    def tick():
        try:
            return next(steps)
        except StopIteration:
            report["finished"] = True
        except Exception:  # noqa: BLE001 - every failure goes to the report, then Blender quits
            report["error"] = traceback.format_exc()
            print(report["error"], flush=True)
            if MODULE + ".blender.job_timer" in sys.modules:  # the add-on may be disabled at the time
                report["status_at_error"] = {folder: repr(status) for folder, status in job_timer().status.items()}
                for job in job_timer()._jobs.values():  # a backend left running would slow every later test
                    if job.is_running():
                        job.kill()
            if MODULE + ".blender.viewport_overlay" in sys.modules:
                sys.modules[MODULE + ".blender.viewport_overlay"].stop()
            try:
                subprocess.run(["import", "-window", "root", str(SHOTS / "zz_at_error.png")], timeout=60)
            except (OSError, subprocess.SubprocessError):
                pass
        save()
        bpy.app.timers.register(quit_blender, first_interval=0.5)
        return None

    bpy.app.timers.register(tick, first_interval=2.0, persistent=True)


if __name__ == "__main__":
    main(flow)
