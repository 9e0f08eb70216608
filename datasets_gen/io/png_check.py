"""Is this PNG a complete 8-bit RGBA image of the expected size?  (standard library only)

--resume keeps views whose files pass this check and re-renders the others.  Images are
written under a temporary name and moved into place, so a half-written PNG should never
exist; the check still decodes the whole file (every chunk's CRC, the zlib stream, the
amount of pixel data) so that a damaged file is re-rendered rather than trusted.
"""

from __future__ import annotations

import struct
import zlib
from typing import Iterator

SIGNATURE = b"\x89PNG\r\n\x1a\n"
RGBA = 6


class PngError(ValueError):
    """Why a PNG is not acceptable."""


def chunks(path: str, data: bytes) -> Iterator[tuple[bytes, bytes]]:
    """(kind, body) of each chunk of the PNG file ``data`` (read from ``path``), every CRC
    checked; PngError names the file and what is wrong."""
    if not data.startswith(SIGNATURE):
        raise PngError(f"{path}: not a PNG file")
    pos = len(SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        crc_bytes = data[pos + 8 + length:pos + 12 + length]
        if len(body) != length or len(crc_bytes) != 4:
            raise PngError(f"{path}: truncated {kind.decode('latin-1')} chunk")
        if zlib.crc32(kind + body) != struct.unpack(">I", crc_bytes)[0]:
            raise PngError(f"{path}: corrupt {kind.decode('latin-1')} chunk (CRC mismatch)")
        pos += 12 + length
        yield kind, body


def check_rgba8(path: str, width: int, height: int) -> None:
    """Raise PngError (or OSError) unless `path` decodes to a width x height 8-bit RGBA image."""
    with open(path, "rb") as handle:
        data = handle.read()
    header = None
    decompressor = zlib.decompressobj()
    pixels = 0
    ended = False
    for kind, body in chunks(path, data):
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            try:
                pixels += len(decompressor.decompress(body))
            except zlib.error as error:
                raise PngError(f"{path}: corrupt image data ({error})") from None
        elif kind == b"IEND":
            ended = True
            break
    if header is None or not ended:
        raise PngError(f"{path}: incomplete PNG (no {'IHDR' if header is None else 'IEND'} chunk)")
    file_width, file_height, depth, colour, _compression, _filter, interlace = header
    if (file_width, file_height) != (width, height):
        raise PngError(f"{path}: size {file_width}x{file_height}, expected {width}x{height}")
    if (depth, colour) != (8, RGBA):
        raise PngError(f"{path}: not 8-bit RGBA (bit depth {depth}, colour type {colour})")
    if interlace != 0:
        raise PngError(f"{path}: interlaced")
    try:
        pixels += len(decompressor.flush())
    except zlib.error as error:
        raise PngError(f"{path}: corrupt image data ({error})") from None
    if not decompressor.eof or pixels != height * (1 + 4 * width):
        raise PngError(f"{path}: incomplete image data")
