"""Images the add-on shows: files loaded (or reloaded) as image datablocks, and shown in an
Image Editor where the user looks."""

from __future__ import annotations

from pathlib import Path

import bpy

PREVIEW_IMAGE = "NeRF preview"
COMPARISON_IMAGE = "NeRF comparison"


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
