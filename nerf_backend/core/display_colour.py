"""Light as the dataset's images show it. ``datasets_gen`` renders with Blender's 'Standard' view
transform, exposure 0 and no look (datasets_gen/blender/render.py): a pixel is the sRGB transfer
of the linear light Cycles gathered, clipped to [0, 1]."""

from __future__ import annotations

from nerf_contract.dataset_layout import WORLD_UNIFORM


def srgb_encoded(linear: float) -> float:
    """The sRGB transfer of one linear value, clipped to [0, 1] first.

    Example:
        >>> round(srgb_encoded(0.72), 3)  # a world of colour 0.9 at strength 0.8, as a pixel
        0.865
        >>> round(srgb_encoded(2.0), 6), srgb_encoded(-1.0)
        (1.0, 0.0)
    """
    value = min(max(float(linear), 0.0), 1.0)
    return 12.92 * value if value <= 0.0031308 else 1.055 * value ** (1.0 / 2.4) - 0.055


def uniform_world_light(world: object) -> tuple[float, float, float] | None:
    """The colour a pixel shows of a world that is one uniform colour (the profile's ``world``
    record: its ``color`` times its ``strength``), as the images encode it; None for any other
    world (an image, a sky, a node tree, none) or a record without those numbers.

    Example:
        >>> uniform_world_light({"kind": "uniform colour", "color": [0.9, 0.9, 0.9, 1.0], "strength": 0.8})
        (0.865..., 0.865..., 0.865...)
        >>> uniform_world_light({"kind": "sky texture"}) is None
        True
    """
    if not isinstance(world, dict) or world.get("kind") != WORLD_UNIFORM:
        return None
    colour, strength = world.get("color"), world.get("strength", 1.0)
    numbers = (*colour[:3], strength) if isinstance(colour, list) and len(colour) >= 3 else ()
    if len(numbers) != 4 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        return None
    return tuple(srgb_encoded(c * strength) for c in colour[:3])  # type: ignore[return-value]
