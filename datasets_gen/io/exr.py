"""Minimal OpenEXR reading and writing in pure Python (standard library only).

Why not a library: the generator must also run in Blender builds without numpy or the
OpenEXR module (Debian's `blender`), and Blender itself can only save an image with channels
named R, G, B, A, while the dataset's depth and normal files name theirs Z, A and X, Y, Z.

What is supported, which is all the generator needs:
* reading scanline files, single-part (Blender 3.x multilayer) or multi-part (Blender 5
  multilayer), uncompressed, FLOAT or HALF channels: Blender's render passes saved with
  codec NONE;
* writing single-part scanline FLOAT files with ZIP compression (16 lines per block),
  readable by any OpenEXR reader;
* checking that a file is a complete EXR with the expected size and channels (for --resume).

The file layout follows the OpenEXR file-format specification: magic, version, header
attributes, offset table, then chunks (part number for multi-part files, y, size, data).
"""

from __future__ import annotations

import struct
import zlib
from array import array
from typing import Mapping, Sequence

MAGIC = 20000630
VERSION = 2
_TILED, _LONG_NAMES, _NON_IMAGE, _MULTI_PART = 0x200, 0x400, 0x800, 0x1000
NO_COMPRESSION, ZIP_COMPRESSION = 0, 3
HALF, FLOAT = 1, 2
_ZIP_LINES = 16
_PIXEL_BYTES = {0: 4, HALF: 2, FLOAT: 4}


class ExrError(ValueError):
    """A file that is not an EXR this module can read (the message says why)."""


# --- reading -----------------------------------------------------------------------------


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, size: int) -> bytes:
        if self.pos + size > len(self.data):
            raise ExrError("file is truncated")
        chunk = self.data[self.pos:self.pos + size]
        self.pos += size
        return chunk

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ExrError("file is truncated")
        text = self.data[self.pos:end].decode("latin-1")
        self.pos = end + 1
        return text

    def unpack(self, fmt: str) -> tuple:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))


def _parse_channels(value: bytes) -> list[tuple[str, int]]:
    reader = _Reader(value)
    channels = []
    while True:
        name = reader.cstring()
        if not name:
            return channels
        pixel_type, _linear, x_sampling, y_sampling = reader.unpack("<iB3xii")
        if (x_sampling, y_sampling) != (1, 1):
            raise ExrError(f"channel {name!r} is subsampled")
        channels.append((name, pixel_type))


def _parse_header(reader: _Reader) -> dict[str, tuple[str, bytes]]:
    header: dict[str, tuple[str, bytes]] = {}
    while True:
        name = reader.cstring()
        if not name:
            return header
        kind = reader.cstring()
        (size,) = reader.unpack("<i")
        header[name] = (kind, reader.take(size))


def _part_layout(header: Mapping[str, tuple[str, bytes]]) -> tuple[int, int, int, int, list[tuple[str, int]]]:
    """(x_min, y_min, width, height, channels) of a scanline part."""
    if header.get("type", ("", b"scanlineimage\0"))[1].rstrip(b"\0") not in (b"scanlineimage",):
        raise ExrError("only scanline images are supported")
    try:
        x_min, y_min, x_max, y_max = struct.unpack("<iiii", header["dataWindow"][1])
        channels = _parse_channels(header["channels"][1])
        compression = header["compression"][1][0]
    except KeyError as missing:
        raise ExrError(f"header has no {missing.args[0]!r} attribute") from None
    if compression not in (NO_COMPRESSION, ZIP_COMPRESSION):
        raise ExrError(f"compression {compression} is not supported (write with codec NONE)")
    return x_min, y_min, x_max - x_min + 1, y_max - y_min + 1, channels


def _header_compression(header: Mapping[str, tuple[str, bytes]]) -> int:
    return header["compression"][1][0]


def _open(data: bytes) -> tuple[_Reader, list[dict[str, tuple[str, bytes]]], bool]:
    reader = _Reader(data)
    magic, version = reader.unpack("<ii")
    if magic != MAGIC:
        raise ExrError("not an OpenEXR file")
    if version & 0xFF != VERSION:
        raise ExrError(f"unsupported OpenEXR version {version & 0xFF}")
    if version & (_TILED | _NON_IMAGE):
        raise ExrError("tiled and deep images are not supported")
    multi_part = bool(version & _MULTI_PART)
    headers = [_parse_header(reader)]
    if multi_part:
        while True:
            if reader.data[reader.pos:reader.pos + 1] == b"\0":
                reader.pos += 1
                break
            headers.append(_parse_header(reader))
    return reader, headers, multi_part


def _chunk_count(header: Mapping[str, tuple[str, bytes]], height: int) -> int:
    lines = _ZIP_LINES if _header_compression(header) == ZIP_COMPRESSION else 1
    return (height + lines - 1) // lines


def read_channels(path: str, names: Sequence[str]) -> tuple[int, int, dict[str, "array[float]"]]:
    """(width, height, {name: values}) of the named channels, rows top to bottom.

    Channels may live in any part of a multi-part file; all must have the same data window.
    Raises ExrError (or OSError) naming what is wrong.
    """
    with open(path, "rb") as handle:
        data = handle.read()
    reader, headers, multi_part = _open(data)
    tables = []
    for header in headers:
        x_min, y_min, width, height, channels = _part_layout(header)
        count = _chunk_count(header, height)
        tables.append(reader.unpack(f"<{count}Q"))
    wanted = set(names)
    found: dict[str, array] = {}
    size = None
    for part, header in enumerate(headers):
        x_min, y_min, width, height, channels = _part_layout(header)
        present = [name for name, _ in channels if name in wanted]
        if not present:
            continue
        if _header_compression(header) != NO_COMPRESSION:
            raise ExrError(f"{path}: part {part} is compressed; only uncompressed parts are read")
        if size is not None and size != (width, height):
            raise ExrError(f"{path}: channels have different sizes")
        size = (width, height)
        rows: dict[str, list[bytes]] = {name: [b""] * height for name in present}
        for offset in tables[part]:
            chunk = _Reader(data)
            chunk.pos = offset
            if multi_part:
                (chunk_part,) = chunk.unpack("<i")
                if chunk_part != part:
                    raise ExrError(f"{path}: chunk of part {chunk_part} in the table of part {part}")
            y, length = chunk.unpack("<ii")
            line = chunk.take(length)
            pos = 0
            for name, pixel_type in channels:
                step = _PIXEL_BYTES[pixel_type] * width
                if name in rows:
                    rows[name][y - y_min] = line[pos:pos + step]
                pos += step
        types = dict(channels)
        for name in present:
            values = array("f")
            blob = b"".join(rows[name])
            if types[name] == FLOAT:
                values.frombytes(blob)
            elif types[name] == HALF:
                values.extend(struct.unpack(f"<{len(blob) // 2}e", blob))
            else:
                raise ExrError(f"{path}: channel {name!r} holds integers")
            if len(values) != width * height:
                raise ExrError(f"{path}: channel {name!r} is incomplete")
            if array("f").itemsize != 4:  # pragma: no cover - every supported platform has 4-byte floats
                raise ExrError("this Python's float32 array is not 4 bytes")
            found[name] = values
    missing = [name for name in names if name not in found]
    if missing:
        raise ExrError(f"{path}: no channel {', '.join(repr(name) for name in missing)}")
    assert size is not None
    return size[0], size[1], found


def check_file(path: str, width: int, height: int, channels: Sequence[str]) -> None:
    """Raise ExrError unless `path` is a complete single-part EXR of that size with exactly those channels.

    Every chunk is located and, when compressed, decompressed: a truncated or corrupt file fails.
    """
    with open(path, "rb") as handle:
        data = handle.read()
    reader, headers, multi_part = _open(data)
    if multi_part or len(headers) != 1:
        raise ExrError(f"{path}: expected a single-part file")
    header = headers[0]
    _x, _y, file_width, file_height, file_channels = _part_layout(header)
    if (file_width, file_height) != (width, height):
        raise ExrError(f"{path}: size {file_width}x{file_height}, expected {width}x{height}")
    if sorted(name for name, _ in file_channels) != sorted(channels):
        raise ExrError(f"{path}: channels {[name for name, _ in file_channels]}, expected {sorted(channels)}")
    count = _chunk_count(header, height)
    lines = _ZIP_LINES if _header_compression(header) == ZIP_COMPRESSION else 1
    line_bytes = sum(_PIXEL_BYTES[kind] for _, kind in file_channels) * width
    for block, offset in enumerate(reader.unpack(f"<{count}Q")):
        chunk = _Reader(data)
        chunk.pos = offset
        _y, length = chunk.unpack("<ii")
        payload = chunk.take(length)
        expected = line_bytes * min(lines, height - block * lines)
        if length < expected:
            try:
                payload = zlib.decompress(payload)
            except zlib.error as error:
                raise ExrError(f"{path}: corrupt block {block} ({error})") from None
        if len(payload) != expected:
            raise ExrError(f"{path}: block {block} holds {len(payload)} bytes, expected {expected}")


# --- writing -----------------------------------------------------------------------------


def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _zip_predict(raw: bytes) -> bytes:
    """OpenEXR's ZIP pre-pass: interleave bytes (even then odd), then byte-wise deltas + 128.

    The delta is done on whole buffers with big-integer arithmetic (SWAR byte-wise subtraction),
    which is linear-time in C rather than a per-byte Python loop.
    """
    reordered = raw[0::2] + raw[1::2]
    size = len(reordered)
    if size == 0:
        return reordered
    high = int.from_bytes(b"\x80" * size, "little")
    low = high ^ int.from_bytes(b"\xff" * size, "little")
    current = int.from_bytes(reordered, "little")
    previous = (current << 8) & (high | low)
    # Byte-wise (current - previous) mod 256 without borrows crossing bytes, then +128 (flip bit 7).
    delta = ((current | high) - (previous & low)) ^ ((current ^ ~previous) & high)
    delta ^= high
    out = bytearray(delta.to_bytes(size, "little"))
    out[0] = reordered[0]
    return bytes(out)


def write_float_channels(path: str, width: int, height: int, channels: Mapping[str, Sequence[float]]) -> None:
    """Write a single-part scanline EXR of FLOAT channels (rows top to bottom), ZIP-compressed."""
    names = sorted(channels)
    for name in names:
        if len(channels[name]) != width * height:
            raise ValueError(f"channel {name!r} has {len(channels[name])} values, expected {width * height}")
    channel_list = b"".join(name.encode() + b"\0" + struct.pack("<iB3xii", FLOAT, 0, 1, 1) for name in names) + b"\0"
    box = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    header = b"".join([
        struct.pack("<ii", MAGIC, VERSION),
        _attribute("channels", "chlist", channel_list),
        _attribute("compression", "compression", bytes([ZIP_COMPRESSION])),
        _attribute("dataWindow", "box2i", box),
        _attribute("displayWindow", "box2i", box),
        _attribute("lineOrder", "lineOrder", b"\0"),
        _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        _attribute("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)),
        b"\0",
    ])
    planes = {}
    for name in names:
        values = array("f", channels[name])
        if struct.pack("=I", 1) != struct.pack("<I", 1):  # pragma: no cover - big-endian hosts
            values.byteswap()
        planes[name] = values.tobytes()
    row_bytes = 4 * width
    chunks = []
    for first in range(0, height, _ZIP_LINES):
        last = min(first + _ZIP_LINES, height)
        raw = b"".join(
            planes[name][row * row_bytes:(row + 1) * row_bytes] for row in range(first, last) for name in names
        )
        packed = zlib.compress(_zip_predict(raw), 6)
        payload = packed if len(packed) < len(raw) else raw
        chunks.append(struct.pack("<ii", first, len(payload)) + payload)
    offset = len(header) + 8 * len(chunks)
    table = bytearray()
    for chunk in chunks:
        table += struct.pack("<Q", offset)
        offset += len(chunk)
    with open(path, "wb") as handle:
        handle.write(header)
        handle.write(table)
        for chunk in chunks:
            handle.write(chunk)
