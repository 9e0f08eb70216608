"""The live view in the real Blender program, GUI drawn (Xvfb): a trained run of a real scene
nobody here made (A.blend: a cube, Suzanne and a torus) drawn over Blender's 3D View, with a mesh
in front of the NeRF and one behind it, in Solid and in Rendered shading (EEVEE and Cycles);
the view orbited through Blender's own events (numpad keys); F12 with NeRF in Renders on (the
render as Blender's job, its handlers off the main thread); the server killed, the add-on
disabled and the file reloaded, each checked for what is left.

Run by tests/test_gui_live_view.py inside the Blender GUI chroot as::

    blender --factory-startup --enable-event-simulate A.blend --python live_view_session.py -- WORK BACKEND_PYTHON RUN

The scene's own objects are hidden, so that where the NeRF is drawn the screen shows the NeRF:
a red cube stands between the view and the NeRF, a green plane behind it. Each shot keeps the
viewport's pixels (``NAME.viewport.npy``) and the frame the add-on drew (``NAME.frame.npy``:
RGBA premultiplied and the camera's z, rows bottom-up as the viewport's), the rectangles the
cube and the plane cover, for the test to check pixel by pixel.
"""

from __future__ import annotations

import os
import signal
import statistics
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from bpy_extras.view3d_utils import location_3d_to_region_2d
from mathutils import Matrix, Quaternion, Vector

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gui_session as gui  # noqa: E402  (the same driver as the add-on's GUI session)
from render_composite_check import flat_material  # noqa: E402

RUN = Path(sys.argv[sys.argv.index("--") + 3])
gui.REPORT = gui.WORK / "live_view_report.json"
report = gui.report
report["live"] = {}
FRONT, BEHIND = "Live view front cube", "Live view back plane"


def overlay():
    return sys.modules[gui.MODULE + ".blender.viewport_overlay"]


def viewport():
    return next(r for r in gui.view3d()[1].regions if r.type == "WINDOW")


def region_view():
    return overlay().scheduler.regions.get(viewport().as_pointer())


def full_frame_drawn() -> bool:
    """The whole region drawn exact (after its draft) for the view as it is now."""
    view = region_view()
    exact = sys.modules[gui.MODULE + ".core.live_view"].EXACT
    return (view is not None and view.frame_stage == exact and view.frame_signature == view.signature
            and overlay()._textures.get(viewport().as_pointer()) is not None
            and overlay()._textures[viewport().as_pointer()].request_id == view.frame.request_id)


def wait_for_full_frame(what: str):
    deadline = time.monotonic() + 120
    while not full_frame_drawn():
        assert time.monotonic() < deadline, f"no full frame after 120 s ({what}): {overlay().state()}"
        assert not overlay().state().startswith("stopped"), overlay().state()
        gui.redraw()
        yield 0.1


def scene_box() -> tuple[Vector, float]:
    """The centre and radius of the scene's own meshes (what the NeRF learnt)."""
    corners = [obj.matrix_world @ Vector(c) for obj in bpy.context.scene.objects if obj.type == "MESH"
               for c in obj.bound_box]
    low = Vector(tuple(min(c[i] for c in corners) for i in range(3)))
    high = Vector(tuple(max(c[i] for c in corners) for i in range(3)))
    return (low + high) / 2, (high - low).length / 2


def set_the_stage() -> dict:
    """The scene's meshes hidden, the view aimed at them, a red cube in front and a green
    plane behind; returns where they are."""
    centre, radius = scene_box()
    for obj in list(bpy.context.scene.objects):
        obj.hide_set(True)  # the meshes the NeRF stands for, the camera's and lights' outlines
    space = gui.view3d()[1].spaces.active
    space.show_gizmo = False  # nothing drawn over the pixels compared but the NeRF and the two meshes
    for flag in ("show_floor", "show_axis_x", "show_axis_y", "show_cursor", "show_text", "show_stats"):
        setattr(space.overlay, flag, False)
    rotation = Quaternion(Vector((0, 0, 1)), np.radians(30)) @ Quaternion(Vector((1, 0, 0)), np.radians(70))
    toward_viewer = rotation @ Vector((0, 0, 1))
    r3d = gui.view3d()[1].spaces.active.region_3d
    r3d.view_perspective, r3d.view_location, r3d.view_rotation, r3d.view_distance = "PERSP", centre, rotation, 3.2 * radius
    bpy.ops.mesh.primitive_cube_add(size=0.35 * radius, location=centre + toward_viewer * 1.2 * radius
                                    + rotation @ Vector((0.25 * radius, 0.1 * radius, 0)))
    front = bpy.context.active_object
    front.name, front.color = FRONT, (1.0, 0.0, 0.0, 1.0)
    front.data.materials.append(flat_material("Front red", (1.0, 0.0, 0.0)))
    bpy.ops.mesh.primitive_plane_add(size=20.0 * radius, location=centre - toward_viewer * 1.6 * radius,
                                     rotation=rotation.to_euler())
    behind = bpy.context.active_object
    behind.name, behind.color = BEHIND, (0.0, 1.0, 0.0, 1.0)
    behind.data.materials.append(flat_material("Behind green", (0.0, 1.0, 0.0)))
    shading = gui.view3d()[1].spaces.active.shading
    shading.type, shading.light, shading.color_type = "SOLID", "FLAT", "OBJECT"
    return {"centre": list(centre), "radius": radius}


def screen_rectangle(name: str) -> list[float]:
    """The object's box corners projected into the viewport: x0, y0, x1, y1 in its pixels."""
    obj, region = bpy.data.objects[name], viewport()
    r3d = gui.view3d()[1].spaces.active.region_3d
    points = [location_3d_to_region_2d(region, r3d, obj.matrix_world @ Vector(c)) for c in obj.bound_box]
    points = [p for p in points if p is not None]
    return [min(p.x for p in points), min(p.y for p in points), max(p.x for p in points), max(p.y for p in points)]


def visible_rectangle() -> list[int]:
    """The part of the viewport no other region covers (the sidebar, the toolbar and the
    headers overlap it): x0, y0, x1, y1 in its pixels, rows bottom-up."""
    area, region = gui.view3d()[1], viewport()
    x0, y0, x1, y1 = 0, 0, region.width, region.height
    for other in area.regions:
        if other.type in ("TOOLS", "UI", "HEADER", "TOOL_HEADER") and other.width > 1 and other.height > 1:
            left, bottom = other.x - region.x, other.y - region.y
            if other.type == "TOOLS":
                x0 = max(x0, left + other.width)
            elif other.type == "UI":
                x1 = min(x1, left)
            elif bottom > region.height / 2:  # a header at the top
                y1 = min(y1, bottom)
            else:
                y0 = max(y0, bottom + other.height)
    return [x0, y0, x1, y1]


def wait_for_the_engine(what: str):
    """Until the render engine draws the scene (EEVEE compiles its shaders first, Cycles
    samples): the red cube's centre red on the screen."""
    deadline = time.monotonic() + 300
    while True:
        x0, y0, x1, y1 = screen_rectangle(FRONT)
        pixel = gui.viewport_pixels()[int((y0 + y1) / 2), int((x0 + x1) / 2)]
        if pixel[0] > pixel[1] + 0.4 and pixel[0] > pixel[2] + 0.4:
            return
        assert time.monotonic() < deadline, f"{what} drew no red cube in 300 s: {list(pixel)}"
        yield 2.0


def capture(name: str):
    """A screenshot; the viewport's pixels and the frame drawn in it saved beside it."""
    gui.redraw()
    yield 0.3
    gui.redraw()
    screen = gui.grab(gui.SHOTS / f"{name}.png")
    region = viewport()
    ox, oy = gui.window_origin(screen)
    area = gui.view3d()[1]
    pixels = screen[oy + region.y:oy + region.y + region.height, ox + region.x:ox + region.x + region.width]
    np.save(gui.SHOTS / f"{name}.viewport.npy", pixels)
    view = region_view()
    entry = {"size": [region.width, region.height], "visible": visible_rectangle(), "state": overlay().state(), "shading": area.spaces.active.shading.type,
             "engine": bpy.context.scene.render.engine, "rectangles": {}}
    if view is not None and view.frame is not None and overlay().state() == "ready":
        frame = view.frame
        rgba = np.frombuffer(frame.rgba, dtype=np.float32).reshape(frame.height, frame.width, 4)
        depth = np.frombuffer(frame.depth, dtype=np.float32).reshape(frame.height, frame.width, 1)
        np.save(gui.SHOTS / f"{name}.frame.npy", np.concatenate([rgba, depth], axis=2))
        entry["frame"] = [frame.width, frame.height]
    for obj in (FRONT, BEHIND):
        if obj in bpy.data.objects:
            entry["rectangles"][obj] = screen_rectangle(obj)
    report["live"][name] = entry
    gui.log(f"live view shot {name}")


def orbit(steps: int, interval: float):
    """The view orbited by numpad 6, then back by numpad 4 (15° a press), through Blender's
    event system with the mouse over the viewport: it ends where it began. Returns when the
    last key is pressed."""
    window, region = gui.view3d()[0], viewport()
    x, y = region.x + region.width // 2, region.y + region.height // 2
    window.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    for key in ["NUMPAD_6"] * (steps // 2) + ["NUMPAD_4"] * (steps // 2):
        window.event_simulate(type=key, value="PRESS", x=x, y=y)
        window.event_simulate(type=key, value="RELEASE", x=x, y=y)
        yield interval


def measure_orbit():
    """Frames a second while the view orbits (the quarter-size drafts), then how long until the
    whole region is drawn after it rests, as a draft and exact; the add-on's own cost per frame."""
    stats = overlay().stats
    start, before = time.monotonic(), len(stats.delivered_at)
    changed_at = region_view().changed_at
    yield from orbit(steps=16, interval=0.15)
    rested = time.monotonic()
    view_changes = region_view().changed_at > changed_at
    moving = [entry for entry in stats.delivered_at[before:] if entry[0] <= rested]
    yield from wait_for_full_frame("after orbiting")
    full_upload = stats.upload_seconds[-1]  # the whole region's frame, uploaded by the draw that showed it
    whole = [at for at, w, h in stats.delivered_at if at > rested and (w, h) == (viewport().width, viewport().height)]
    full_at, exact_at = (whole[0], whole[-1]) if whole else (time.monotonic(), time.monotonic())
    report["live"]["orbit"] = {
        "view_changes": view_changes,
        "moving_frames": len(moving), "moving_seconds": rested - start,
        "moving_fps": len(moving) / (rested - start), "moving_sizes": sorted({(w, h) for _, w, h in moving}),
        "rest_to_full_seconds": full_at - rested, "rest_to_exact_seconds": exact_at - rested,
        "region": [viewport().width, viewport().height],
        "render_seconds_median": statistics.median(stats.render_seconds),
        "upload_seconds_median": statistics.median(stats.upload_seconds), "full_upload_seconds": full_upload,
        "draw_seconds_median": statistics.median(stats.draw_seconds)}
    gui.log(f"orbit: {report['live']['orbit']}")


def server_leftovers() -> dict:
    """The live view's server and frames folder, to check later that neither is left."""
    client = overlay().client
    return {"pid": client._process.pid if client._process is not None else None,
            "folder": str(client._folder) if client._folder is not None else None}


def gone(leftovers: dict) -> dict:
    alive = leftovers["pid"] is not None and Path(f"/proc/{leftovers['pid']}").exists()
    if alive:  # a zombie until reaped is gone as a process
        status = Path(f"/proc/{leftovers['pid']}/status").read_text()
        alive = "zombie" not in status
    return {"process_alive": alive, "folder_exists": leftovers["folder"] is not None and Path(leftovers["folder"]).exists()}


def start_live_view():
    yield from gui.press("nerf.live_view", "Live View")
    yield from gui.wait(lambda: overlay().state() == "ready", 120, "the live view's server to be ready")
    yield from wait_for_full_frame("started")


def faults():
    # The server killed: the panel says so, nothing stale is drawn, a click restarts it.
    os.kill(overlay().client._process.pid, signal.SIGKILL)
    yield from gui.wait(lambda: overlay().state().startswith("stopped"), 30, "the killed server to be noticed")
    yield from capture("live_4_killed")
    yield from gui.shot("live_4_killed_panel")
    report["live"]["killed_state"] = overlay().state()
    yield from gui.press("nerf.live_view", "Restart Live View")
    yield from gui.wait(lambda: overlay().state() == "ready", 120, "the restarted server")
    yield from wait_for_full_frame("restarted")
    yield from capture("live_5_restarted")
    # The add-on disabled: no process, no frames left.
    leftovers = server_leftovers()
    bpy.ops.preferences.addon_disable(module=gui.MODULE)
    yield 1.0
    report["live"]["disabled"] = {**leftovers, **gone(leftovers)}
    yield from gui.enable_add_on()
    bpy.context.scene.nerf.run_dir = str(RUN)
    bpy.ops.nerf.live_view()
    yield from gui.wait(lambda: overlay().state() == "ready", 120, "the server after enabling again")
    # The file reloaded: the same.
    leftovers = server_leftovers()
    bpy.ops.wm.open_mainfile(filepath=bpy.data.filepath)
    yield 2.0
    report["live"]["reloaded"] = {**leftovers, **gone(leftovers)}
    # Left on for Blender's quit: the test checks after Blender has gone.
    bpy.context.scene.nerf.run_dir = str(RUN)
    bpy.ops.nerf.live_view()
    yield from gui.wait(lambda: overlay().state() == "ready", 120, "the server before quitting")
    report["live"]["at_quit"] = server_leftovers()


_renders_done = []


@bpy.app.handlers.persistent
def _render_done(*_args) -> None:
    _renders_done.append(time.monotonic())


def f12(name: str, timeout: float = 300):
    """F12 pressed, as a user does: Blender renders as a job, its handlers (the add-on's too)
    off the main thread; the Render Result saved as ``NAME.png`` when it completes."""
    done = len(_renders_done)
    yield from gui.key("F12")
    yield from gui.wait(lambda: len(_renders_done) > done, timeout, f"F12's render ({name})")
    yield 0.5
    bpy.data.images["Render Result"].save_render(str(gui.SHOTS / f"{name}.png"))
    gui.close_extra_windows()  # the render's own window
    yield 0.5


def f12_with_the_nerf():
    """NeRF in Renders in the GUI: a camera where the view is, F12 without the NeRF and with
    it (Cycles); the test compares the two where the cube stands and where the NeRF is."""
    from bpy_extras.object_utils import world_to_camera_view

    scene = bpy.context.scene
    window, area, region = gui.view3d()
    camera = bpy.data.objects.new("F12 camera", bpy.data.cameras.new("F12 camera"))
    scene.collection.objects.link(camera)
    camera.matrix_world = area.spaces.active.region_3d.view_matrix.inverted()
    scene.camera = camera
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 120, 80, 100
    scene.render.engine, scene.cycles.samples, scene.view_settings.view_transform = "CYCLES", 8, "Standard"
    for obj in scene.objects:  # the scene's own meshes are hidden from the render too: the NeRF stands for them
        obj.hide_render = obj.hide_render or (obj.type == "MESH" and obj.name not in (FRONT, BEHIND))
    bpy.app.handlers.render_complete.append(_render_done)
    yield from f12("f12_alone")
    with bpy.context.temp_override(window=window, area=area, region=region):
        turned_on = sorted(bpy.ops.nerf.render_composite())
    yield from f12("f12_nerf")
    composite = sys.modules[gui.MODULE + ".blender.render_composite"]
    corners = [world_to_camera_view(scene, camera, bpy.data.objects[FRONT].matrix_world @ Vector(c))
               for c in bpy.data.objects[FRONT].bound_box]
    report["live"]["f12"] = {"turned_on": turned_on, "message": composite.last_message,
                             "server": composite.client.state(), "size": [120, 80],
                             "cube": [min(c.x for c in corners), min(c.y for c in corners),
                                      max(c.x for c in corners), max(c.y for c in corners)]}
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.nerf.render_composite()
    bpy.app.handlers.render_complete.remove(_render_done)
    gui.log(f"F12 with the NeRF: {report['live']['f12']}")


def flow():
    yield from gui.enable_add_on()
    yield from gui.open_nerf_tab()
    bpy.context.scene.nerf.run_dir = str(RUN)
    report["live"]["stage"] = set_the_stage()
    yield 1.0
    yield from capture("live_0_before")
    yield from start_live_view()
    yield from capture("live_1_solid")
    yield from measure_orbit()
    yield from capture("live_2_solid_orbited")
    shading = gui.view3d()[1].spaces.active.shading
    shading.type = "RENDERED"
    bpy.context.scene.render.engine = "BLENDER_EEVEE_NEXT" if bpy.app.version >= (4, 2, 0) and bpy.app.version < (5, 0, 0) \
        else "BLENDER_EEVEE"
    yield from wait_for_the_engine("EEVEE")
    yield from wait_for_full_frame("EEVEE")
    yield from capture("live_3_rendered_eevee")
    bpy.context.scene.render.engine = "CYCLES"
    bpy.context.scene.cycles.preview_samples = 4
    yield from wait_for_the_engine("Cycles")
    yield 2.0  # its last samples
    yield from capture("live_3_rendered_cycles")
    shading.type = "SOLID"
    yield from f12_with_the_nerf()
    yield from faults()
    gui.log("live view flow finished")


if __name__ == "__main__":
    gui.main(flow)
