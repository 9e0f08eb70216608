"""8-bit PNG images as numpy arrays: read (any of PNG's row filters) and written (unfiltered).

Why not Pillow or imageio: this runs inside Blender (the generator, `--merge` on a farm), whose
Python has numpy but neither.  Rows filtered with None, Sub or Up are undone with numpy;
Average and Paeth depend on the byte just decoded, so those rows are undone byte by byte (a
Cycles render from Blender mixes all five; a 800x800 RGBA render decodes in a fraction of a
second).  Only what renders are: 8-bit grey, RGB or RGBA, not interlaced.

Example:
    >>> import tempfile, os
    >>> image = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
    >>> path = os.path.join(tempfile.mkdtemp(), "tiny.png")
    >>> with open(path, "wb") as handle:
    ...     _ = handle.write(png_bytes(image))
    >>> bool((read_png(path) == image).all())
    True
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from .png_check import SIGNATURE, PngError, chunks

#: PNG colour type of 1, 3 and 4 channels (grey, RGB, RGBA).
COLOUR_TYPES = {1: 0, 3: 2, 4: 6}
CHANNELS = {value: key for key, value in COLOUR_TYPES.items()}


def read_png(path: str) -> np.ndarray:
    """The 8-bit image at ``path`` as a [H, W, C] uint8 array (C = 1, 3 or 4)."""
    with open(path, "rb") as handle:
        data = handle.read()
    header, compressed = None, []
    for kind, body in chunks(path, data):
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            compressed.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise PngError(f"{path}: no IHDR chunk")
    width, height, depth, colour, _, _, interlace = header
    if depth != 8 or colour not in CHANNELS or interlace:
        raise PngError(f"{path}: a {depth}-bit PNG of colour type {colour}{' (interlaced)' if interlace else ''}; "
                       "expected 8-bit grey, RGB or RGBA, not interlaced")
    channels = CHANNELS[colour]
    try:
        raw = zlib.decompress(b"".join(compressed))
    except zlib.error as error:
        raise PngError(f"{path}: corrupt image data ({error})") from None
    stride = width * channels
    if len(raw) != height * (stride + 1):
        raise PngError(f"{path}: {len(raw)} bytes of pixel data, expected {height * (stride + 1)}")
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, stride + 1)
    pixels = np.empty((height, stride), dtype=np.uint8)
    prior = np.zeros(stride, dtype=np.uint8)
    for y in range(height):
        kind, row = rows[y, 0], rows[y, 1:]
        if kind == 0:
            pixels[y] = row
        elif kind == 1:  # Sub: a running sum per channel, modulo 256
            pixels[y] = np.cumsum(row.reshape(width, channels), axis=0, dtype=np.uint8).reshape(stride)
        elif kind == 2:  # Up
            pixels[y] = row + prior
        elif kind in (3, 4):
            pixels[y] = np.frombuffer(_unfilter_sequential(kind, row.tobytes(), prior.tobytes(), channels),
                                      dtype=np.uint8)
        else:
            raise PngError(f"{path}: row {y} has an unknown filter type {kind}")
        prior = pixels[y]
    return pixels.reshape(height, width, channels)


def _unfilter_sequential(kind: int, row: bytes, prior: bytes, channels: int) -> bytearray:
    """Undo the Average (3) or Paeth (4) filter of one row."""
    out = bytearray(row)
    if kind == 3:
        for i in range(len(out)):
            left = out[i - channels] if i >= channels else 0
            out[i] = (out[i] + ((left + prior[i]) >> 1)) & 0xFF
        return out
    for i in range(len(out)):
        if i >= channels:
            a, b, c = out[i - channels], prior[i], prior[i - channels]
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            predictor = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
        else:
            predictor = prior[i]  # a = c = 0: Paeth picks b
        out[i] = (out[i] + predictor) & 0xFF
    return out


def png_bytes(image: np.ndarray, level: int = 6) -> bytes:
    """An 8-bit PNG of a [H, W] or [H, W, C] uint8 array (C = 1, 3 or 4), rows unfiltered."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"png_bytes takes uint8 pixels, not {image.dtype}")
    if image.ndim == 2:
        image = image[:, :, None]
    height, width, channels = image.shape
    rows = np.zeros((height, width * channels + 1), dtype=np.uint8)  # filter byte 0: None
    rows[:, 1:] = image.reshape(height, width * channels)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, COLOUR_TYPES[channels], 0, 0, 0)
    return (SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
            + chunk(b"IEND", b""))
