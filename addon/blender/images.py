"""Images the add-on shows: files loaded (or reloaded) as image datablocks, and shown in an
Image Editor where the user looks."""

from __future__ import annotations

from pathlib import Path

import bpy

PREVIEW_IMAGE = "NeRF preview"
COMPARISON_IMAGE = "NeRF comparison"
ANIMATION_IMAGE = "NeRF animation"


def show_image(name: str, path: Path):
    """Load (or reload) ``path`` as the image datablock ``name``; returns it."""
    image = bpy.data.images.get(name)
    if image is not None and Path(bpy.path.abspath(image.filepath)).resolve() == Path(path).resolve():
        image.reload()
    else:
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.load(str(path), check_existing=False)
        image.name = name
    return image


def show_in_image_editor(context, image) -> str:
    """Show ``image`` where the user looks: in an open Image Editor, else in a new window
    turned into one. Returns where ("" without a window: the ``bpy`` module, ``blender -b``)."""
    if bpy.app.background:  # no screen to show it on (the bpy module, blender -b)
        return ""
    windows = list(getattr(context.window_manager, "windows", []))
    for window in windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                _fit_when_drawn(window, area)
                return "an open Image Editor"
    window = context.window or (windows[0] if windows else None)
    if window is None:
        return ""
    area = context.area or window.screen.areas[0]
    with context.temp_override(window=window, area=area):
        bpy.ops.wm.window_new()
    new_window = context.window_manager.windows[-1]
    editor = max(new_window.screen.areas, key=lambda a: a.width * a.height)
    editor.type = "IMAGE_EDITOR"
    editor.spaces.active.image = image
    _fit_when_drawn(new_window, editor)
    return "a new Image Editor window"


def _fit_when_drawn(window, area) -> None:
    """Zoom the editor so the image fills it (a 100-pixel render is a speck at 1:1); once the
    area has been drawn, since a new window's regions have no size before."""
    def fit():
        if window not in bpy.context.window_manager.windows[:]:
            return None  # closed meanwhile: nothing to fit
        region = next((r for r in area.regions if r.type == "WINDOW"), None)
        if region is not None:
            with bpy.context.temp_override(window=window, area=area, region=region):
                bpy.ops.image.view_all(fit_view=True)
        return None
    area.tag_redraw()
    bpy.app.timers.register(fit, first_interval=0.3)


def show_animation(context, record: dict, sequencer: bool) -> dict:
    """The finished animation's video (side by side with Cycles when there is one) in an Image
    Editor, and, with ``sequencer``, as a movie strip in the Video Sequencer at the
    path's first frame. Returns what was loaded."""
    video = Path(record.get("side_by_side_video") or record["video"])
    image = bpy.data.images.get(ANIMATION_IMAGE)
    if image is not None:
        bpy.data.images.remove(image)
    image = bpy.data.images.load(str(video), check_existing=False)
    image.name = ANIMATION_IMAGE
    frames = record["frames"]
    shown = {"image": image.name, "source": image.source, "video": str(video), "frames": image.frame_duration}
    where = show_in_image_editor(context, image)
    for window in getattr(context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR" and area.spaces.active.image == image:
                user = area.spaces.active.image_user
                user.frame_duration, user.frame_start, user.use_auto_refresh = len(frames), frames[0], True
    shown["where"] = where
    if sequencer:
        shown["strip"] = _add_strip(context.scene, video, frames[0])
    return shown


def _add_strip(scene, video: Path, first_frame: int) -> dict:
    """A movie strip of ``video`` on the first free channel (replacing this add-on's earlier one)."""
    editor = scene.sequence_editor or scene.sequence_editor_create()
    strips = getattr(editor, "strips", None)  # Blender 4.4+ (``sequences`` is gone in 5.0)
    strips = strips if strips is not None else editor.sequences
    for old in [strip for strip in strips if strip.name.startswith(ANIMATION_IMAGE)]:
        strips.remove(old)
    channel = 1 + max((strip.channel for strip in strips), default=0)
    strip = strips.new_movie(name=ANIMATION_IMAGE, filepath=str(video), channel=channel, frame_start=first_frame)
    return {"name": strip.name, "channel": strip.channel, "frame_start": strip.frame_start,
            "frames": strip.frame_final_duration}
