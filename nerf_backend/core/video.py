"""H.264 MP4 videos from image files, through imageio-ffmpeg (its wheel ships an ffmpeg
binary, so nothing is installed system-wide).

yuv420p, the pixel format every player decodes, halves the chroma resolution and so needs an
even width and height: an odd side is padded by repeating its last row or column, never
scaled (scaling would blur the frames being compared). The file is written under a temporary
name and renamed, so an interrupted encode leaves no truncated video.

Example:
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> folder = Path(tempfile.mkdtemp())
    >>> frames = [np.full((6, 9, 3), i / 4) for i in range(4)]
    >>> video_info(write_video(folder / "v.mp4", frames, fps=12.0))
    {'frames': 4, 'width': 10, 'height': 6, 'fps': 12.0}
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import imageio_ffmpeg
import numpy as np

from .errors import NerfError

#: libx264's constant rate factor: 18 is visually lossless for renders (the default, 23, smears noise).
QUALITY_CRF = "18"


def even_padded(image: np.ndarray) -> np.ndarray:
    """``H×W×3`` uint8 with odd sides padded by edge replication to even ones."""
    pad_rows, pad_columns = image.shape[0] % 2, image.shape[1] % 2
    if pad_rows or pad_columns:
        image = np.pad(image, ((0, pad_rows), (0, pad_columns), (0, 0)), mode="edge")
    return image


def _as_bytes(image: np.ndarray) -> np.ndarray:
    if image.dtype != np.uint8:
        image = np.clip(np.round(np.asarray(image, np.float32) * 255.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(even_padded(image[..., :3]))


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Encode ``frames`` (``H×W×3``, uint8 or floats in [0, 1], all one size) as H.264 at ``fps``."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial")
    writer = None
    size = None
    try:
        for frame in frames:
            pixels = _as_bytes(frame)
            if writer is None:
                size = (pixels.shape[1], pixels.shape[0])
                writer = imageio_ffmpeg.write_frames(
                    str(partial), size, fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=1,
                    quality=None, ffmpeg_log_level="error", output_params=["-crf", QUALITY_CRF, "-f", "mp4"])
                writer.send(None)
            elif (pixels.shape[1], pixels.shape[0]) != size:
                raise NerfError(f"{path}: a frame of {pixels.shape[1]}×{pixels.shape[0]} among frames of "
                                f"{size[0]}×{size[1]}")
            writer.send(pixels)
        if writer is None:
            raise NerfError(f"{path}: no frames to encode")
        writer.close()
        writer = None
        os.replace(partial, path)
    except (OSError, RuntimeError) as exc:
        raise NerfError(f"{path}: cannot encode the video ({str(exc).strip().splitlines()[-1] if str(exc) else exc})") \
            from exc
    finally:
        if writer is not None:
            writer.close()
        if partial.exists():
            partial.unlink()
    return path


def video_info(path: Path) -> dict:
    """Frame count, size and frame rate of a video, as ffmpeg decodes it."""
    reader = imageio_ffmpeg.read_frames(str(path))
    try:
        meta = next(reader)
        count = sum(1 for _ in reader)
    finally:
        reader.close()
    width, height = meta["size"]
    return {"frames": count, "width": width, "height": height, "fps": float(meta["fps"])}
