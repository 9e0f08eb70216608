"""What the panel says, worked out without Blender: text wrapped to a width, the progress bar's
shorter forms for a narrow sidebar, the live view's rate, and the asset's warning. Plain
Python; ``blender/ui_text`` measures the widths in Blender's UI font and ``blender/panel``
draws the lines.

Example (``width_of``: one pixel a character here; in Blender, the UI font's measure):
    >>> wrap("/data/runs/lego", 10, len)
    ['/data/', 'runs/lego']
    >>> first_fitting(["Iteration 300, 31.2 dB, 12 s left", "300, 31.2 dB, 12 s", "300"], 20, len)
    '300, 31.2 dB, 12 s'
"""

from __future__ import annotations

import re
from typing import Callable

ELLIPSIS = "…"  # first of the lines kept when a text is longer than its place


def wrap(text: str, room: float, width_of: Callable[[str], float]) -> list[str]:
    """``text`` in lines no wider than ``room`` (as ``width_of`` measures), broken after a space
    or a slash (long paths break there); a single word wider than ``room`` keeps a line of its
    own."""
    lines = []
    for paragraph in text.splitlines() or [""]:
        line = ""
        for piece in re.split(r"(?<=[ /])", paragraph):
            if line and width_of((line + piece).rstrip()) > room:
                lines.append(line.rstrip())
                line = piece.lstrip()
            else:
                line += piece
        lines.append(line.rstrip())
    return lines


def first_fitting(candidates: list[str], room: float, width_of: Callable[[str], float]) -> str:
    """The first of ``candidates`` (longest first) no wider than ``room``; the last where none is."""
    return next((text for text in candidates if width_of(text) <= room), candidates[-1])


def last_lines(lines: list[str], limit: int) -> list[str]:
    """At most ``limit`` lines: beyond it the end is kept (the end of an error says the most)."""
    return [ELLIPSIS, *lines[-limit + 1:]] if len(lines) > limit else lines


def progress_texts(detail: str, seconds_left: float | None, iteration: int | None, psnr: float | None) -> list[str]:
    """A running job's progress bar texts, longest first: a bar's text cannot wrap, so the
    panel draws the first that fits its width."""
    left = f"{seconds_left:.0f} s left" if seconds_left is not None else ""
    candidates = [", ".join(filter(None, (detail, left)))]
    if iteration is not None:  # training: shorter forms for a narrow sidebar
        quality = f"{psnr:.1f} dB" if psnr is not None else ""
        candidates += [", ".join(filter(None, (f"Iteration {iteration}", quality, left))),
                       ", ".join(filter(None, (str(iteration), quality, left.replace(" left", "")))),
                       str(iteration)]
    return candidates


RATE_WINDOW_S = 2.0  # the live view's rate is over the frames of the last two seconds


def live_view_rate(delivered_at: list[tuple[float, int, int]], render_seconds: list[float], iteration: int | None,
                   now: float) -> str:
    """'7.5 frames/s, 0.13 s each, iteration 3000': the live view's frames of the last
    ``RATE_WINDOW_S`` (``delivered_at``: (time, width, height) of each, on ``now``'s clock),
    the server's time for the newest one and its checkpoint's iteration."""
    recent = [at for at, _, _ in delivered_at if now - at < RATE_WINDOW_S]
    parts = [f"{len(recent) / RATE_WINDOW_S:.1f} frames/s" if len(recent) > 1 else "Drawn",
             f"{render_seconds[-1]:.2f} s each" if render_seconds else "",
             f"iteration {iteration}" if iteration is not None else ""]
    return ", ".join(filter(None, parts))


def asset_view_warning(view_transform: str) -> str:
    """What the user must know to see the asset as the NeRF shows it ("" under the Standard
    view): its texture holds the dataset images' colours, already through a view transform;
    another one maps them again."""
    if view_transform == "Standard":
        return ""
    return (f"The asset's texture holds the colours its images show; the scene's view transform '{view_transform}' "
            "maps them again. Render with the Standard view transform to see them as the NeRF does.")
