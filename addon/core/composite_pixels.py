"""A NeRF frame made ready for Blender's compositor (``render_composite`` puts it in two float
images that a Z Combine node lays over the render): plain Python and numpy, no bpy, so tests
check it without Blender.

The frame's colour is what the NeRF learnt: the dataset's images, display-referred sRGB under
the Standard view (the generator's colour management). The compositor works in scene-linear
light and applies the scene's view transform at the end, so the colour is decoded back to
linear here; with the Standard view the render shows the frame's own values again, and with
another view (AgX, Filmic) the NeRF is shown through it as the rest of the scene is.

Example:
    >>> import numpy as np
    >>> from addon.core.live_view import LiveFrame
    >>> rgba = np.array([0.5, 0.5, 0.5, 1.0, 0, 0, 0, 0], np.float32)   # grey, then empty
    >>> depth = np.array([2.5, np.inf], np.float32)
    >>> colour, z = compositor_pixels(LiveFrame(1, 2, 1, rgba.tobytes(), depth.tobytes(), 0.1, 0))
    >>> [round(float(v), 4) for v in colour[:4]], float(z[0]), bool(z[4] == np.float32(EMPTY_DEPTH))
    ([0.214, 0.214, 0.214, 1.0], 2.5, True)
"""

from __future__ import annotations

import numpy as np

# Where the NeRF is empty: farther than anything a render holds (Cycles and EEVEE write 1e10
# where they see the background), so Z Combine keeps the scene there. Finite: the compositor's
# filters and the depth output mishandle infinities.
EMPTY_DEPTH = 1.0e20


def render_size(resolution_x: int, resolution_y: int, percentage: int) -> tuple[int, int]:
    """The pixels a render makes: the scene's resolution at its percentage (rounded down, as
    Blender does), at least one each way."""
    return max(1, resolution_x * percentage // 100), max(1, resolution_y * percentage // 100)


def empty_pixels(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(colour, depth)`` as ``compositor_pixels`` makes them, for a frame without the NeRF:
    colour transparent black, depth ``EMPTY_DEPTH`` (alpha 1), so Z Combine keeps the scene."""
    depth = np.full((width * height, 4), EMPTY_DEPTH, np.float32)
    depth[:, 3] = 1.0
    return np.zeros(width * height * 4, np.float32), depth.ravel()


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer function undone (IEC 61966-2-1), as Blender's Standard view encodes."""
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def compositor_pixels(frame) -> tuple[np.ndarray, np.ndarray]:
    """``(colour, depth)`` of a ``LiveFrame``, each flat float32 RGBA as ``Image.pixels`` takes
    it (rows bottom to top, as the frame's): colour scene-linear and premultiplied by the
    NeRF's opacity (Blender's float images are premultiplied); depth the camera's z in each of
    R, G and B, ``EMPTY_DEPTH`` where the NeRF is empty, alpha 1."""
    rgba = np.frombuffer(frame.rgba, dtype=np.float32).reshape(-1, 4).astype(np.float64)
    alpha = rgba[:, 3:4]
    straight = np.clip(np.divide(rgba[:, :3], alpha, out=np.zeros_like(rgba[:, :3]), where=alpha > 0), 0.0, 1.0)
    colour = np.concatenate([srgb_to_linear(straight) * alpha, alpha], axis=1).astype(np.float32)
    z = np.frombuffer(frame.depth, dtype=np.float32).astype(np.float64)
    z = np.where(np.isfinite(z) & (alpha[:, 0] > 0), z, EMPTY_DEPTH)
    depth = np.repeat(z[:, None], 4, axis=1)
    depth[:, 3] = 1.0
    return colour.ravel(), depth.astype(np.float32).ravel()
