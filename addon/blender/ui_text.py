"""Text that fits where it is drawn: Blender cuts a label that is too wide with "…", so
messages (errors, warnings, paths) are wrapped to the width they get, measured in Blender's
own UI font (a count of characters is wrong at other widths, scales and fonts). The wrapping
itself is ``core.panel_text``'s; here are the font's measure and the labels."""

from __future__ import annotations

import blf

from ..core import panel_text

# The width a label loses, in pixels at UI scale 1, to the sidebar's tab column, the panel's
# and a box's margins and an icon (measured on Blender 4.3's screenshots: 291-px region, 209-px text).
LABEL_INSET_PX = 84


def _room(context, width_px: float | None) -> float:
    """Pixels for text, with Blender's UI font set at its size."""
    preferences = context.preferences
    scale = preferences.system.ui_scale
    style = preferences.ui_styles[0]
    blf.size(0, (getattr(style, "widget", None) or style.widget_label).points * scale)
    room = width_px * scale if width_px is not None else context.region.width - LABEL_INSET_PX * scale
    return max(room, 60 * scale)


def _width(text: str) -> float:
    return blf.dimensions(0, text)[0]


def first_fitting(context, candidates: list[str], width_px: float | None = None) -> str:
    """The first of ``candidates`` (longest first) that fits on one line: for a progress bar,
    whose text cannot wrap."""
    return panel_text.first_fitting(candidates, _room(context, width_px), _width)


def wrapped(context, text: str, width_px: float | None = None) -> list[str]:
    """``text`` in lines no wider than ``width_px`` (UI scale 1; default: the region's width less
    its margins). Long paths break after a slash."""
    return panel_text.wrap(text, _room(context, width_px), _width)


def draw_text(layout, context, text: str, icon: str = "NONE", limit: int = 8, width_px: float | None = None) -> None:
    """Wrapped text as labels, the icon on the first line and the others indented to match;
    beyond ``limit`` lines the end is kept (the end of an error says the most)."""
    lines = panel_text.last_lines(wrapped(context, text, width_px), limit)
    for number, line in enumerate(lines):
        layout.label(text=line, icon=icon if number == 0 else ("BLANK1" if icon != "NONE" else "NONE"))
