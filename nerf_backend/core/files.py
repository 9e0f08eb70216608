"""File I/O that never leaves a half-written file: write to a temporary name beside the
target, flush to disk, then rename over it (atomic on POSIX and Windows)."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import imageio.v3 as iio
import numpy as np

from .errors import NerfError

# The prefix and suffix of atomic_write's temporary files: a process killed mid-write (kill -9,
# power loss) leaves one behind, which whoever next writes that folder removes.
TEMPORARY_SUFFIX = ".tmp"


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp_path)`` then atomically move ``tmp_path`` to ``path``.

    If ``write`` fails (full disk, crash), ``path`` keeps its previous content and the
    temporary file is removed; a failure to write (a full disk, a file-size limit, no
    permission) raises ``NerfError`` naming ``path`` and the system's reason.
    """
    path = Path(path)
    tmp: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX, dir=path.parent)
        os.close(fd)
        tmp = Path(tmp_name)
        write(tmp)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        # mkstemp makes its file 0600; the result must have the mode any new file gets here,
        # or a shared report shows broken images.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as exc:
        _discard(tmp)
        kept = f"; the previous {path.name} is unchanged" if path.exists() else ""
        raise NerfError(f"{path}: cannot write ({exc.strerror or exc}){kept}") from exc
    except BaseException:
        _discard(tmp)
        raise


def _umask() -> int:
    """The process's umask (reading it means setting it: set it straight back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _discard(tmp: Path | None) -> None:
    if tmp is not None:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete the temporary files a killed writer left in ``folder``; call it only while no
    other process writes there (e.g. holding the run folder's lock)."""
    stale = [p for p in Path(folder).glob(f".*{TEMPORARY_SUFFIX}") if p.is_file()]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def write_json(path: Path, data: Any) -> None:
    def _write(tmp: Path) -> None:
        tmp.write_text(json.dumps(data, indent=2) + "\n")

    atomic_write(path, _write)


def eight_bit(image: np.ndarray) -> np.ndarray:
    """A float image in [0, 1] as the 8-bit pixels ``write_png`` stores: rounded to nearest."""
    return np.clip(np.round(np.asarray(image, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write a float image in [0, 1] (H×W×C) as an 8-bit PNG (``eight_bit``'s pixels)."""
    pixels = eight_bit(image)
    # Encoded in memory, then written by atomic_write: a failed write is then one clean
    # OSError, not one raised again when imageio's file object is garbage-collected.
    # zlib's fastest level: an 800×800 render in 21 ms instead of 68, its file 16 % larger.
    encoded = iio.imwrite("<bytes>", pixels, extension=".png", compress_level=1)
    atomic_write(path, lambda tmp: tmp.write_bytes(encoded))


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    """Write float32 single-channel images (H×W each) to one EXR file."""
    import OpenEXR  # imported here: only rendering depth/opacity needs it

    data = {name: np.ascontiguousarray(values, dtype=np.float32) for name, values in channels.items()}
    # Run-length: lossless, and an 800×800 render's depth and opacity (lego) in 11 ms and 1.42 MB,
    # where ZIP took 38 ms for 1.16 MB (eval writes one a view beside the next view's render).
    header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.RLE_COMPRESSION}
    atomic_write(path, lambda tmp: OpenEXR.File(header, data).write(str(tmp)))


def read_exr(path: Path) -> dict[str, np.ndarray]:
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        return {name: np.array(channel.pixels) for name, channel in exr.channels().items()}
