"""The live view drawn in Blender's 3D Views: a ``SpaceView3D`` draw handler that draws each
region's newest NeRF frame through the ``gpu`` module only (OpenGL, Vulkan and Metal alike; no
``bgl``, which Blender 5.0 removed), its depth tested against the scene's, and a timer on the
main thread that hands the server's frames to the regions and sends the next request
(``core.live_view``: the server's client and the scheduler, plain Python).

Each frame is drawn as one full-region quad whose fragment shader writes the NeRF's depth
(the camera's z from the frame, taken through the region's own projection into the depth
buffer's range), so the scene's meshes in front hide the NeRF and those behind are hidden by
it: in Solid, Material Preview and Rendered shading (Cycles fills that depth buffer for the
overlays, EEVEE with its own). bpy and gpu are touched on the main thread only: the timer
and the draw handler; the textures are made in the draw handler, where a GPU context is
current.
"""

from __future__ import annotations

import atexit
import time
from dataclasses import dataclass, field

import bpy
import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader
from mathutils import Matrix

from ..core import sources
from ..core.live_view import LiveFrame, LiveViewClient, ViewScheduler

TICK_SECONDS = 0.02  # the timer's period while the live view is on: frames reach the screen within it
# The frames hold the NeRF's colour as its training images held it: display-referred sRGB
# (the view transform of the render that made the dataset is in them), as a PNG shown in
# Blender's Image Editor with the Standard view. The overlay's framebuffer takes linear values
# and encodes them to sRGB itself, so the shader decodes first and the screen gets the
# image's own values back.
FRAGMENT_SOURCE = """
vec3 srgb_to_linear(vec3 c)
{
  return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), c));
}

void main()
{
  vec4 colour = texture(colour_image, uv);
  float z = texture(depth_image, uv).r;
  if (colour.a < 0.002 || !(z < 1e30)) {
    discard;
  }
  vec4 clip = projection * vec4(0.0, 0.0, -z, 1.0);
  gl_FragDepth = clamp(clip.z / clip.w * 0.5 + 0.5, 0.0, 1.0);
  vec3 straight = clamp(colour.rgb / colour.a, 0.0, 1.0);
  vec3 shown = decode_srgb != 0 ? srgb_to_linear(straight) : straight;
  fragColor = vec4(shown * colour.a, colour.a);
}
"""
VERTEX_SOURCE = """
void main()
{
  uv = position * 0.5 + 0.5;
  gl_Position = vec4(position, 0.0, 1.0);
}
"""


@dataclass
class RegionTextures:
    request_id: int
    colour: object  # gpu.types.GPUTexture
    depth: object


@dataclass
class OverlayStats:
    """What the panel and the benchmark read: frames drawn, the server's render time and the
    add-on's own cost per frame (upload, and the draw call's CPU side)."""

    frames: int = 0
    iteration: int | None = None  # the checkpoint's, of the newest frame (the server reloads a training run's)
    render_seconds: list = field(default_factory=list)
    upload_seconds: list = field(default_factory=list)
    draw_seconds: list = field(default_factory=list)
    delivered_at: list = field(default_factory=list)  # (monotonic time, width, height) of each frame

    def keep_last(self, count: int = 200) -> None:
        for values in (self.render_seconds, self.upload_seconds, self.draw_seconds, self.delivered_at):
            del values[:-count]


client = LiveViewClient()
scheduler = ViewScheduler()
stats = OverlayStats()
_textures: dict[int, RegionTextures] = {}
_handler = None
_shader = None
_batch = None
_last_state = ""


def is_on() -> bool:
    return _handler is not None


def state() -> str:
    """``off``, ``starting``, ``ready`` or ``stopped: WHY``, as the panel says it."""
    return client.state() if is_on() else "off"


def start(python: str, run, device: str) -> None:
    """Starts the server on ``run`` and draws its frames in every 3D View (a restart where on)."""
    global _handler
    stop()
    client.start(python, sources.backend_root(), run, device=device)
    _handler = bpy.types.SpaceView3D.draw_handler_add(_draw, (), "WINDOW", "POST_VIEW")
    if not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=TICK_SECONDS)
    _tag_redraw()


def stop() -> None:
    """Stops the server, removes its frames and the drawing; nothing is left running."""
    global _handler, stats
    if _handler is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handler, "WINDOW")
        _handler = None
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    client.stop()
    scheduler.clear()
    _textures.clear()
    stats = OverlayStats()
    _tag_redraw()


def _view3d_regions():
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                for region in area.regions:
                    if region.type == "WINDOW":
                        yield area, region


def _tag_redraw(key: int | None = None) -> None:
    for area, region in _view3d_regions():
        if key is None or region.as_pointer() == key:
            area.tag_redraw()


def placement(scene, server: LiveViewClient):
    """Where the NeRF's frame sits: the dataset's placement (``server``'s ``ready`` event),
    moved by the anchor object's transform where one is chosen; None for the server's default.
    The live view's and F12's."""
    anchor = scene.nerf.live_view_anchor if scene is not None else None
    if anchor is None or server.ready is None:
        return None
    return anchor.matrix_world @ Matrix(server.ready["nerf_to_world"])


def _send_next() -> None:
    request = scheduler.next_request(time.monotonic())
    if request is None:
        return
    request_id = client.request(request.view_matrix, request.projection_matrix, request.width, request.height,
                                nerf_to_world=request.nerf_to_world, step_scale=request.step_scale)
    if request_id is not None:
        scheduler.sent(request_id, request, time.monotonic())


def _tick():
    """Blender's timer: frames in, requests out, the panel told when the state changes."""
    global _last_state
    now_state = client.state()
    if now_state != _last_state:
        _last_state = now_state
        _tag_redraw()  # the panel's line, and a stopped server's frames erased
    if not client.running():
        return 0.5
    scheduler.keep_only({region.as_pointer() for _, region in _view3d_regions()})
    scheduler.failed(client.take_failed())
    frame = client.poll_frame()
    if frame is not None:
        key = scheduler.delivered(frame)
        stats.frames += 1
        stats.iteration = frame.iteration
        stats.render_seconds.append(frame.seconds)
        stats.delivered_at.append((time.monotonic(), frame.width, frame.height))
        stats.keep_last()
        _tag_redraw(key)
    _send_next()
    return TICK_SECONDS


def _upload(frame: LiveFrame) -> RegionTextures:
    size = (frame.width, frame.height)
    colour = np.frombuffer(frame.rgba, dtype=np.float32)
    depth = np.frombuffer(frame.depth, dtype=np.float32)
    return RegionTextures(
        frame.request_id,
        gpu.types.GPUTexture(size, format="RGBA32F", data=gpu.types.Buffer("FLOAT", colour.size, colour)),
        gpu.types.GPUTexture(size, format="R32F", data=gpu.types.Buffer("FLOAT", depth.size, depth)))


def _make_shader():
    interface = gpu.types.GPUStageInterfaceInfo("nerf_live_view_interface")
    interface.smooth("VEC2", "uv")
    info = gpu.types.GPUShaderCreateInfo()
    info.push_constant("MAT4", "projection")
    info.push_constant("INT", "decode_srgb")
    info.sampler(0, "FLOAT_2D", "colour_image")
    info.sampler(1, "FLOAT_2D", "depth_image")
    info.vertex_in(0, "VEC2", "position")
    info.vertex_out(interface)
    info.fragment_out(0, "VEC4", "fragColor")
    if hasattr(info, "depth_write"):  # Blender 4.4+: Vulkan and Metal must be told the shader writes depth
        info.depth_write("ANY")
    info.vertex_source(VERTEX_SOURCE)
    info.fragment_source(FRAGMENT_SOURCE)
    shader = gpu.shader.create_from_info(info)
    batch = batch_for_shader(shader, "TRI_FAN", {"position": ((-1, -1), (1, -1), (1, 1), (-1, 1))})
    return shader, batch


def _draw() -> None:
    """The draw handler (POST_VIEW, every 3D View's main region): the region's newest frame."""
    global _shader, _batch
    context = bpy.context
    region, view = context.region, context.region_data
    if region is None or view is None or not client.running():
        return
    key = region.as_pointer()
    scheduler.update(key, view.view_matrix, view.window_matrix, region.width, region.height, time.monotonic(),
                     nerf_to_world=placement(context.scene, client))
    _send_next()  # a view that moved asks at once, not at the next tick
    region_view = scheduler.regions.get(key)
    frame = region_view.frame if region_view is not None else None
    if frame is None:
        return
    textures = _textures.get(key)
    if textures is None or textures.request_id != frame.request_id:
        start = time.perf_counter()
        textures = _textures[key] = _upload(frame)
        stats.upload_seconds.append(time.perf_counter() - start)
    start = time.perf_counter()
    if _shader is None:
        _shader, _batch = _make_shader()
    gpu.state.depth_test_set("LESS_EQUAL")
    gpu.state.depth_mask_set(False)
    gpu.state.blend_set("ALPHA_PREMULT")
    _shader.bind()
    _shader.uniform_float("projection", view.window_matrix)
    _shader.uniform_int("decode_srgb", 1)
    _shader.uniform_sampler("colour_image", textures.colour)
    _shader.uniform_sampler("depth_image", textures.depth)
    _batch.draw(_shader)
    gpu.state.blend_set("NONE")
    gpu.state.depth_test_set("NONE")
    stats.draw_seconds.append(time.perf_counter() - start)


@bpy.app.handlers.persistent
def _stop_on_load(*_args) -> None:
    """A file loaded (or a new one): the old scene's live view stops, its server with it."""
    stop()


def register() -> None:
    bpy.app.handlers.load_pre.append(_stop_on_load)
    atexit.register(client.stop)  # Blender quitting: the server and its frames go too


def unregister() -> None:
    stop()
    atexit.unregister(client.stop)
    if _stop_on_load in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_stop_on_load)
