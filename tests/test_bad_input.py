"""Bad input (issue 7): each broken dataset gives one clear line and leaves nothing behind.

A catalogue of broken datasets, each a copy of the tiny demo dataset with one thing damaged,
run through the real command line: exit status 2, exactly one stderr line ``error: FILE:
PROBLEM``, no traceback (only with ``--debug``), and no run folder created or changed. Then
property-based tests: mutated dataset JSON, camera JSON, scene profiles and PNG bytes make
the loaders return valid data or raise ``DatasetError``, never anything else.
"""

from __future__ import annotations

import copy
import errno
import json
import math
import os
import shutil
import struct
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from PIL import Image

from conftest import run_python
from nerf_backend.cli import main
from nerf_backend.data.dataset import (
    MAX_IMAGE_SIDE, StillCameras, DatasetSplit, SceneBounds, load_cameras, load_scene_bounds, load_scene_profile,
    load_split,
)
from nerf_backend.core.errors import DatasetError

FLOAT32_MAX = float(np.finfo(np.float32).max)
DAMAGED_VIEW = 3  # the training view each image case damages: train/r_3.png


# ---------------------------------------------------------------- building broken datasets


def _edit_json(dataset: Path, name: str, edit: Callable[[dict], None]) -> None:
    path = dataset / name
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data, indent=2))  # NaN / Infinity written as JSON's NaN / Infinity literals


def _edit_train(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    return lambda dataset: _edit_json(dataset, "transforms_train.json", edit)


def _edit_frame(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    return _edit_train(lambda data: edit(data["frames"][DAMAGED_VIEW]))


def _set(key: str, value) -> Callable[[dict], None]:
    return lambda data: data.__setitem__(key, value)


def _delete(*keys: str) -> Callable[[dict], None]:
    def edit(data: dict) -> None:
        for key in keys:
            del data[key]
    return edit


def _set_rotation(value) -> Callable[[dict], None]:
    def edit(frame: dict) -> None:
        for row in frame["transform_matrix"][:3]:
            row[:3] = [value] * 3
    return edit


def _damaged_image(dataset: Path) -> Path:
    return dataset / "train" / f"r_{DAMAGED_VIEW}.png"


def _png_bytes(pixels: np.ndarray, bit_depth: int) -> bytes:
    """An RGBA PNG of ``pixels`` (uint8 or uint16) at ``bit_depth``, written by hand (Pillow
    cannot write 16-bit RGBA)."""
    height, width = pixels.shape[:2]
    big_endian = pixels.astype(">u2" if bit_depth == 16 else "u1")
    raw = b"".join(b"\x00" + big_endian[row].tobytes() for row in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, bit_depth, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


def _write_16_bit(dataset: Path) -> None:
    path = _damaged_image(dataset)
    pixels = np.asarray(Image.open(path).convert("RGBA")).astype(np.uint16) * 257
    path.write_bytes(_png_bytes(pixels, 16))
    with Image.open(path) as image:  # why the loader reads the PNG header: Pillow says "RGBA"
        assert image.mode == "RGBA"


def _resize(dataset: Path) -> None:
    path = _damaged_image(dataset)
    Image.open(path).convert("RGBA").resize((30, 30)).save(path)


def _to_rgb(dataset: Path) -> None:
    path = _damaged_image(dataset)
    Image.open(path).convert("RGB").save(path)


def _truncate(dataset: Path) -> None:
    path = _damaged_image(dataset)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _outside_image(dataset: Path) -> Path:
    """A real PNG beside the dataset folder, so only the escape is wrong."""
    outside = dataset.parent / "outside"
    outside.mkdir(exist_ok=True)
    shutil.copy(_damaged_image(dataset), outside / "r_3.png")
    return outside / "r_3.png"


def _file_path_parent(dataset: Path) -> None:
    _outside_image(dataset)
    _edit_frame(_set("file_path", "../outside/r_3"))(dataset)


def _file_path_absolute(dataset: Path) -> None:
    absolute = _outside_image(dataset)
    _edit_frame(_set("file_path", str(absolute.with_suffix(""))))(dataset)


def _write(name: str, content: bytes | str) -> Callable[[Path], None]:
    def damage(dataset: Path) -> None:
        path = dataset / name
        path.write_bytes(content) if isinstance(content, bytes) else path.write_text(content)
    return damage


def _half_json(name: str) -> Callable[[Path], None]:
    def damage(dataset: Path) -> None:
        text = (dataset / name).read_text()
        (dataset / name).write_text(text[: len(text) // 2])
    return damage


# (id, damage, file the line names, what it says is wrong); ``{outside}`` stands for a folder
# beside the dataset.
CASES = [
    ("malformed-json", _half_json("transforms_train.json"), "transforms_train.json", "not valid JSON ("),
    ("not-an-object", _write("transforms_train.json", "[1, 2]"), "transforms_train.json",
     "expected a JSON object at the top level, got list"),
    ("missing-frames", _edit_train(_delete("frames")), "transforms_train.json", "'frames' is missing"),
    ("empty-frames", _edit_train(_set("frames", [])), "transforms_train.json", "'frames' is empty"),
    ("frame-not-object", _edit_train(lambda d: d["frames"].__setitem__(3, "r_3")), "transforms_train.json",
     "frame 3 is not an object"),
    ("missing-camera_angle_x", _edit_train(_delete("camera_angle_x", "fl_x", "fl_y", "cx", "cy")),
     "transforms_train.json", "'camera_angle_x' is missing"),
    ("camera_angle_x-NaN", _edit_train(_set("camera_angle_x", math.nan)), "transforms_train.json",
     "'camera_angle_x' must be a finite positive number, got nan"),
    ("camera_angle_x-Infinity", _edit_train(_set("camera_angle_x", math.inf)), "transforms_train.json",
     "'camera_angle_x' must be a finite positive number, got inf"),
    ("camera_angle_x-negative-Infinity", _edit_train(_set("camera_angle_x", -math.inf)), "transforms_train.json",
     "'camera_angle_x' must be a finite positive number, got -inf"),
    ("camera_angle_x-string", _edit_train(_set("camera_angle_x", "0.69")), "transforms_train.json",
     "'camera_angle_x' must be a number, got '0.69'"),
    ("camera_angle_x-bool", _edit_train(_set("camera_angle_x", True)), "transforms_train.json",
     "'camera_angle_x' must be a number, got True"),
    ("camera_angle_x-above-pi", _edit_train(_set("camera_angle_x", 4.0)), "transforms_train.json",
     "'camera_angle_x' = 4.0 is not a field of view below π"),
    # Found by test_load_split_mutated_json's fuzzing (session 58): tan(angle / 2) underflowed to zero.
    ("camera_angle_x-subnormal", _edit_train(lambda d: (_delete("fl_x", "fl_y", "cx", "cy")(d),
                                                        _set("camera_angle_x", 5e-324)(d))),
     "transforms_train.json", "'camera_angle_x' = 5e-324 is too small a field of view"),
    ("fl_x-zero", _edit_train(_set("fl_x", 0)), "transforms_train.json",
     "'fl_x' must be a finite positive number, got 0"),
    ("w-mismatch", _edit_train(_set("w", 41)), "transforms_train.json", "'w' is 41 but the images are 40×40"),
    ("w-not-a-number", _edit_train(_set("w", "forty")), "transforms_train.json",
     "'w' must be a whole number of pixels, got 'forty'"),
    ("pose-singular", _edit_frame(lambda f: _set_rotation(0.0)(f)), "transforms_train.json",
     "frame 3 'transform_matrix' is not invertible"),
    ("pose-NaN", _edit_frame(lambda f: f["transform_matrix"][0].__setitem__(3, math.nan)), "transforms_train.json",
     "frame 3 'transform_matrix' has NaN or infinite values"),
    ("pose-huge-int", _edit_frame(lambda f: f["transform_matrix"][0].__setitem__(3, 10**400)),
     "transforms_train.json", "frame 3 'transform_matrix' has NaN or infinite values"),
    ("pose-beyond-float32", _edit_frame(lambda f: f["transform_matrix"][0].__setitem__(3, 1e39)),
     "transforms_train.json", "frame 3 'transform_matrix' has values beyond float32's range"),
    ("pose-3x4", _edit_frame(lambda f: f["transform_matrix"].pop()), "transforms_train.json",
     "frame 3 'transform_matrix' is not a 4×4 list of lists"),
    ("pose-bool", _edit_frame(lambda f: f["transform_matrix"][3].__setitem__(3, True)), "transforms_train.json",
     "frame 3 'transform_matrix' holds True, not a number"),
    ("pose-missing", _edit_frame(_delete("transform_matrix")), "transforms_train.json",
     "frame 3 has no 'transform_matrix'"),
    ("missing-image", lambda d: _damaged_image(d).unlink(), "r_3.png", "image not found"),
    ("zero-byte-png", lambda d: _damaged_image(d).write_bytes(b""), "r_3.png",
     "image file is empty (0 bytes); expected an 8-bit RGBA PNG"),
    ("truncated-png", _truncate, "r_3.png", "cannot read image (image file is truncated)"),
    ("not-a-png", lambda d: _damaged_image(d).write_text("hello"), "r_3.png",
     "not an image Pillow can read; expected an 8-bit RGBA PNG"),
    ("image-is-a-folder", lambda d: (_damaged_image(d).unlink(), _damaged_image(d).mkdir()), "r_3.png",
     "expected a file, found a folder"),
    ("different-size", _resize, "r_3.png", "size 30×30 differs from r_0.png's 40×40"),
    ("rgb-not-rgba", _to_rgb, "r_3.png", "image has no alpha channel (RGB); expected RGBA as in nerf_synthetic"),
    ("16-bit-png", _write_16_bit, "r_3.png", "16-bit PNG is not supported; write 8-bit RGBA PNGs"),
    ("file_path-parent", _file_path_parent, "transforms_train.json",
     "frame 3 'file_path' '../outside/r_3.png' points outside the dataset folder"),
    ("file_path-absolute", _file_path_absolute, "transforms_train.json",
     "frame 3 'file_path' '{outside}/r_3.png' points outside the dataset folder"),
    ("file_path-NUL", _edit_frame(_set("file_path", "./train/r_\x003")), "transforms_train.json",
     "frame 3 'file_path' './train/r_\\x003.png' contains a NUL character"),
    ("file_path-missing", _edit_frame(_delete("file_path")), "transforms_train.json", "frame 3 has no 'file_path'"),
    ("file_path-number", _edit_frame(_set("file_path", 3)), "transforms_train.json",
     "frame 3 'file_path' must be a relative path, got 3"),
    ("depth_file_path-parent", _edit_frame(_set("depth_file_path", "../depth.exr")), "transforms_train.json",
     "frame 3 'depth_file_path' '../depth.exr' points outside the dataset folder"),
    ("val-malformed-json", _half_json("transforms_val.json"), "transforms_val.json", "not valid JSON"),
    ("scene_profile-malformed-json", _half_json("scene_profile.json"), "scene_profile.json", "not valid JSON"),
    ("scene_profile-bounds-string", lambda d: _edit_json(d, "scene_profile.json",
                                                         lambda p: p["bounds"].__setitem__("min", "123")),
     "scene_profile.json", "'bounds' 'min' must be three numbers, got '123'"),
    ("scene_profile-bounds-inverted", lambda d: _edit_json(d, "scene_profile.json",
                                                           lambda p: p["bounds"].__setitem__("min", [2, 2, 2])),
     "scene_profile.json", "'bounds' min [2.0, 2.0, 2.0] is not below max"),
    ("dataset-missing", lambda d: shutil.rmtree(d), "dataset", "dataset folder not found"),
]
# These go through a real `python -m nerf_backend` process; the rest call cli.main in-process.
SUBPROCESS_CASES = {"malformed-json", "16-bit-png", "file_path-parent"}


@pytest.fixture
def dataset_copy(tiny_demo_dataset, tmp_path) -> Path:
    copy_ = tmp_path / "dataset"
    shutil.copytree(tiny_demo_dataset, copy_)
    return copy_


def _train_args(dataset: Path, out: Path, *extra: str) -> list[str]:
    return ["train", str(dataset), "--out", str(out), "--iters", "1", "--device", "cpu", "--no-progress", *extra]


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file's bytes and every folder (None) under ``folder``, by relative path."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))}


def _assert_one_error_line(stderr: str, *expected: str) -> str:
    lines = stderr.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got:\n{stderr}"
    line = lines[0]
    assert line.startswith("error: ") and "Traceback" not in stderr
    for text in expected:
        assert text in line, f"{text!r} not in {line!r}"
    return line


def _run_cli(args: list[str], capsys, subprocess_: bool) -> tuple[int, str, str]:
    if subprocess_:
        result = run_python("-m", "nerf_backend", *args, check=False, timeout=300)
        return result.returncode, result.stdout, result.stderr
    capsys.readouterr()
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("case_id, damage, file_name, problem", CASES, ids=[case[0] for case in CASES])
def test_bad_dataset_one_line_and_no_run_folder(case_id, damage, file_name, problem, dataset_copy, tmp_path, capsys):
    damage(dataset_copy)
    out = tmp_path / "runs" / "new_run"
    code, stdout, stderr = _run_cli(_train_args(dataset_copy, out), capsys, case_id in SUBPROCESS_CASES)
    assert code == 2, stderr
    _assert_one_error_line(stderr, file_name, problem.format(outside=dataset_copy.parent / "outside"))
    assert stdout == ""
    assert not (tmp_path / "runs").exists(), "a failing train created its run folder"


def _existing_run(out: Path) -> dict:
    """A run folder with a config and a render; returns its snapshot."""
    (out / "renders").mkdir(parents=True)
    (out / "config.json").write_text('{"preset": "preview"}')
    (out / "renders" / "r_0.png").write_bytes(b"old render")
    return _snapshot(out)


def test_bad_dataset_leaves_an_existing_run_untouched_even_with_overwrite(dataset_copy, tmp_path, capsys):
    """--overwrite replaces a run only once the new dataset has been read whole."""
    out = tmp_path / "run"
    before = _existing_run(out)
    _write_16_bit(dataset_copy)
    code = main(_train_args(dataset_copy, out, "--overwrite"))
    _assert_one_error_line(capsys.readouterr().err, "r_3.png", "16-bit")
    assert code == 2 and _snapshot(out) == before


def test_existing_run_folder_without_overwrite(tiny_demo_dataset, tmp_path, capsys):
    """Refused before anything is touched: not even a lock file is added."""
    out = tmp_path / "run"
    before = _existing_run(out)
    code = main(_train_args(tiny_demo_dataset, out))
    _assert_one_error_line(capsys.readouterr().err, str(out), "run folder exists and is not empty",
                           "--overwrite")
    assert code == 2
    assert _snapshot(out) == before, "a refused train changed the existing run"


def test_debug_shows_the_traceback(dataset_copy, tmp_path):
    _write_16_bit(dataset_copy)
    out = tmp_path / "runs" / "new_run"
    result = run_python("-m", "nerf_backend", "--debug", *_train_args(dataset_copy, out), check=False, timeout=300)
    assert result.returncode != 0
    assert "Traceback (most recent call last)" in result.stderr
    assert "DatasetError" in result.stderr and "16-bit PNG" in result.stderr
    assert not (tmp_path / "runs").exists()


def test_os_error_is_one_line(tiny_demo_dataset, tmp_path, capsys):
    """An OSError that escapes (here: --out below a regular file) prints ``error: FILE: strerror``."""
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file, not a folder")
    out = blocker / "run"
    code = main(_train_args(tiny_demo_dataset, out))
    line = _assert_one_error_line(capsys.readouterr().err, str(out))
    assert code == 2
    assert line == f"error: {out}: Not a directory"
    assert blocker.read_text() == "a file, not a folder"
    with pytest.raises(NotADirectoryError):
        main(["--debug", *_train_args(tiny_demo_dataset, out)])


def test_permission_denied_is_one_line(tiny_demo_dataset, tmp_path, capsys):
    locked = tmp_path / "read_only"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        probe = locked / "probe"
        try:
            probe.touch()
        except PermissionError:
            pass
        else:
            probe.unlink()
            pytest.skip("running as root (or on a file system without permissions): chmod 0o500 does not "
                        "stop writes here; test_os_error_is_one_line covers the OSError path")
        out = locked / "run"
        code = main(_train_args(tiny_demo_dataset, out))
        line = _assert_one_error_line(capsys.readouterr().err, str(out))
        assert code == 2 and line == f"error: {out}: Permission denied"
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)


@pytest.mark.parametrize("error, line", [
    (OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/runs/a/checkpoint.pt.tmp"),
     f"error: /runs/a/checkpoint.pt.tmp: {os.strerror(errno.ENOSPC)}"),
    (OSError(errno.EFBIG, os.strerror(errno.EFBIG), "/runs/a/events.jsonl"),
     f"error: /runs/a/events.jsonl: {os.strerror(errno.EFBIG)}"),
    (OSError(errno.EACCES, os.strerror(errno.EACCES), "/runs/a/tmp", None, "/runs/a/checkpoint.pt"),
     f"error: /runs/a/tmp -> /runs/a/checkpoint.pt: {os.strerror(errno.EACCES)}"),
    (OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), f"error: {os.strerror(errno.ENOSPC)}"),
    (OSError("image file is\ntruncated"), "error: image file is\\ntruncated"),
], ids=["full-disk", "file-too-large", "rename", "no-file-name", "no-errno"])
def test_os_error_line_format(error, line, monkeypatch, capsys):
    """How main words the OSErrors a real disk gives (a full disk, EFBIG, a failed rename)."""
    def fail(args):
        raise error

    monkeypatch.setattr("nerf_backend.cli._run", fail)
    assert main(["report", "somewhere"]) == 2
    assert _assert_one_error_line(capsys.readouterr().err) == line
    with pytest.raises(OSError):
        main(["--debug", "report", "somewhere"])


def test_newline_in_a_message_stays_on_one_line(dataset_copy, tmp_path, capsys):
    _edit_frame(_set("file_path", "./train/r_3\nsecond line"))(dataset_copy)
    code = main(_train_args(dataset_copy, tmp_path / "runs" / "new_run"))
    line = _assert_one_error_line(capsys.readouterr().err, "r_3\\nsecond line.png", "image not found")
    assert code == 2 and line.startswith("error: ")


# ---------------------------------------------------------------- property-based tests

INTRINSIC_KEYS = ("camera_angle_x", "w", "h", "fl_x", "fl_y", "cx", "cy")
KEYS = st.one_of(st.sampled_from([*INTRINSIC_KEYS, "frames", "file_path", "transform_matrix", "depth_file_path",
                                  "bounds", "min", "max", "view_dependent"]), st.text(max_size=4))
NUMBERS = st.one_of(
    st.integers(),
    st.floats(),
    st.sampled_from([0, 1, -1, 40, 41, 2**31, 2**63, 10**20, 10**400, -10**400, 0.0, -0.0, 1e-300, 5e-324, 1e38,
                     3.5e38, 1e308, math.pi, 3.15, math.nan, math.inf, -math.inf]),
)
STRINGS = st.one_of(
    st.text(max_size=12),
    st.sampled_from(["", ".", "..", "/", "../", "../outside/r_0", "/etc/passwd", "\x00", "./train/r_\x000",
                     "./train/r_0", "./train/r_1", "./train/r_1.png", "./train/", "train", "a\nb", "NaN", "40",
                     "x" * 300, "transforms_fuzz.json", "./r_0"]),
)
SCALARS = st.one_of(st.none(), st.booleans(), NUMBERS, STRINGS)
MATRICES = st.lists(st.lists(NUMBERS, min_size=4, max_size=4), min_size=3, max_size=5)
# Values known to be hard for a loader, drawn as often as everything else together (copied:
# a drawn list may be edited in place by a later mutation).
IDENTITY_ROWS = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
HARD_VALUES = st.sampled_from([
    None, True, False, 0, -1, 1, 40, 41, 40.0, 40.5, 10**400, -10**400, 1e308, 1e39, -1e39, 5e-324,
    math.nan, math.inf, -math.inf,
    "", "\x00", "../", "..", "/", "/etc/passwd", "../outside/r_0", "./train/r_\x000", "a\nb", "40", "123",
    "./train/r_0", "./train/r_1",
    [], {}, [1, 2, 3], ["1", "2", "3"], [True, True, True], [0, 0, 0], [1e308, 1e308, 1e308], [-1e308, 0, 0],
    {"min": "123", "max": "456"},
    [[1, 0, 0, 0]] * 4, [[0.0] * 4] * 4, [[math.nan] * 4] * 4, IDENTITY_ROWS[:3], [row * 2 for row in IDENTITY_ROWS],
    [[1e20 * v for v in row[:3]] + row[3:] for row in IDENTITY_ROWS],  # rotation part's determinant 1e60
    [[1e-3 * v for v in row[:3]] + row[3:] for row in IDENTITY_ROWS],  # determinant 1e-9: singular
    [row[:3] + [1e39 if i == 0 else row[3]] for i, row in enumerate(IDENTITY_ROWS)],  # beyond float32
]).map(copy.deepcopy)
VALUES = st.one_of(
    HARD_VALUES,
    st.one_of(
        st.recursive(SCALARS, lambda children: st.lists(children, max_size=5)
                     | st.dictionaries(KEYS, children, max_size=4), max_leaves=12),
        MATRICES,
    ),
)


def _paths(node, prefix: tuple = ()):
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, prefix + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _paths(value, prefix + (index,))


def _at(node, path: tuple):
    for step in path:
        node = node[step]
    return node


@st.composite
def mutated(draw, base: dict):
    """``base`` with 1–4 random edits: a value replaced by any JSON, a key or element
    deleted, a key or element inserted, a list cut short or grown."""
    document = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 4))):
        paths = list(_paths(document))
        keyed = [path for path in paths if path and isinstance(path[-1], str)]  # "file_path", "w"...: half the time
        path = draw(st.sampled_from(keyed) if keyed and draw(st.booleans()) else st.sampled_from(paths))
        operation = draw(st.sampled_from(["replace", "replace", "delete", "insert", "resize"]))
        if operation == "replace":
            value = draw(VALUES)
            if path:
                _at(document, path[:-1])[path[-1]] = value
            else:
                document = value
        elif operation == "delete" and path:
            del _at(document, path[:-1])[path[-1]]
        elif operation == "insert":
            node = _at(document, path)
            if isinstance(node, dict):
                node[draw(KEYS)] = draw(VALUES)
            elif isinstance(node, list):
                node.insert(draw(st.integers(0, len(node))), draw(VALUES))
        elif operation == "resize":
            node = _at(document, path)
            if isinstance(node, list):
                size = draw(st.integers(0, len(node) + 2))
                grown = node + [copy.deepcopy(node[-1]) if node else None] * 2
                node[:] = grown[:size]
    return document


def _write_json(path: Path, document) -> None:
    path.write_text(json.dumps(document))  # NaN, Infinity and huge ints as JSON literals


def _check_intrinsics(intrinsics, width: int, height: int) -> None:
    assert (intrinsics.width, intrinsics.height) == (width, height)
    assert isinstance(intrinsics.width, int) and isinstance(intrinsics.height, int)
    for value in (intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy):
        assert isinstance(value, float) and math.isfinite(value) and abs(value) <= FLOAT32_MAX
    assert intrinsics.fl_x > 0 and intrinsics.fl_y > 0


def _check_poses(poses: torch.Tensor, count: int) -> None:
    assert poses.shape == (count, 4, 4) and poses.dtype == torch.float32
    assert torch.isfinite(poses).all()
    assert (torch.linalg.det(poses[:, :3, :3].double()).abs() >= 1e-8).all()


def _check_split(split: DatasetSplit, root: Path) -> None:
    assert isinstance(split, DatasetSplit)
    count = len(split)
    assert count >= 1
    _check_poses(split.poses, count)
    assert split.rgba.dtype == torch.uint8 and split.rgba.dim() == 4 and split.rgba.shape[0] == count
    height, width = split.rgba.shape[1:3]
    assert split.rgba.shape[3] == 4 and height >= 1 and width >= 1
    _check_intrinsics(split.intrinsics, width, height)
    assert len(split.image_paths) == len(split.depth_paths) == count
    for path in split.image_paths:
        assert path.is_file() and path.is_relative_to(root.resolve())
    for path in split.depth_paths:
        assert path is None or path.is_relative_to(root.resolve())


def _expect_valid_or_dataset_error(load: Callable, check: Callable) -> None:
    try:
        result = load()
    except DatasetError as exc:
        assert str(exc), "a DatasetError without a message"
        return
    check(result)


FUZZ = settings(max_examples=250, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def fuzz_dataset(tiny_demo_dataset, tmp_path_factory) -> tuple[Path, dict]:
    """A two-view copy of the training split and its JSON, reduced to what the loader reads."""
    root = tmp_path_factory.mktemp("fuzz") / "dataset"
    (root / "train").mkdir(parents=True)
    outside = root.parent / "outside"
    outside.mkdir()
    data = json.loads((tiny_demo_dataset / "transforms_train.json").read_text())
    frames = data["frames"][:2]
    for frame in frames:
        shutil.copy(tiny_demo_dataset / (frame["file_path"] + ".png"), root / "train")
    shutil.copy(root / "train" / "r_0.png", outside)  # a real image outside, for "../outside/r_0"
    base = {key: data[key] for key in INTRINSIC_KEYS}
    base["frames"] = [{"file_path": frame["file_path"], "transform_matrix": frame["transform_matrix"]}
                      for frame in frames]
    base["frames"][1]["depth_file_path"] = "./train/r_1_depth.exr"
    _write_json(root / "transforms_base.json", base)
    _check_split(load_split(root, "base"), root)
    return root, base


def test_fuzz_base_documents_are_valid(fuzz_dataset):
    root, base = fuzz_dataset
    _check_split(load_split(root, "base"), root)


@FUZZ
@given(data=st.data())
def test_load_split_mutated_json(fuzz_dataset, data):
    root, base = fuzz_dataset
    _write_json(root / "transforms_fuzz.json", data.draw(mutated(base)))
    _expect_valid_or_dataset_error(lambda: load_split(root, "fuzz"), lambda split: _check_split(split, root))


def _check_cameras(cameras: StillCameras) -> None:
    assert isinstance(cameras, StillCameras)
    count = cameras.poses.shape[0]
    _check_poses(cameras.poses, count)
    assert 1 <= cameras.intrinsics.width <= MAX_IMAGE_SIDE and 1 <= cameras.intrinsics.height <= MAX_IMAGE_SIDE
    _check_intrinsics(cameras.intrinsics, cameras.intrinsics.width, cameras.intrinsics.height)
    assert len(cameras.stems) == count and len(set(cameras.stems)) == count, "two views would share a file"
    for stem in cameras.stems:
        assert isinstance(stem, str) and stem and "/" not in stem and "\x00" not in stem


@FUZZ
@given(data=st.data())
def test_load_cameras_mutated_json(fuzz_dataset, data):
    root, base = fuzz_dataset
    cameras = copy.deepcopy(base)
    for index, frame in enumerate(cameras["frames"]):
        frame["file_path"] = f"./r_{index}"
        frame.pop("depth_file_path", None)
    path = root / "cameras_fuzz.json"
    _write_json(path, data.draw(mutated(cameras)))
    _expect_valid_or_dataset_error(lambda: load_cameras(path), _check_cameras)


PROFILE = {"version": 2, "source": "demo", "bounds": {"min": [-0.85, -0.85, -0.62], "max": [0.85, 0.85, 0.98]},
           "view_dependent": True, "transparency": False}


def _check_bounds(bounds: SceneBounds | None) -> None:
    assert isinstance(bounds, SceneBounds)
    assert len(bounds.box_min) == len(bounds.box_max) == 3
    for lo, hi in zip(bounds.box_min, bounds.box_max):
        assert isinstance(lo, float) and isinstance(hi, float)
        assert np.float32(lo) < np.float32(hi) and abs(lo) <= FLOAT32_MAX and abs(hi) <= FLOAT32_MAX
        assert math.isfinite(hi - lo) and hi - lo <= FLOAT32_MAX
    padded = bounds.padded(0.05)
    assert all(map(math.isfinite, padded.box_min + padded.box_max))


@pytest.fixture(scope="module")
def profile_dir(tmp_path_factory) -> Path:
    """One folder for every example (hypothesis refuses function-scoped fixtures such as tmp_path)."""
    return tmp_path_factory.mktemp("profile_fuzz")


@FUZZ
@given(data=st.data())
def test_scene_profile_mutated_json(profile_dir, data):
    root = profile_dir
    _write_json(root / "scene_profile.json", data.draw(mutated(PROFILE)))
    _expect_valid_or_dataset_error(lambda: load_scene_profile(root), lambda profile: isinstance(profile, dict))
    _expect_valid_or_dataset_error(lambda: load_scene_bounds(root), _check_bounds)


@settings(max_examples=150, deadline=None, database=None)
@given(raw=st.one_of(st.binary(max_size=64), st.text(max_size=64).map(str.encode),
                     st.sampled_from([b"", b"\xef\xbb\xbf{}", b"\xff\xfe{\x00}\x00", b"{" * 100_000,
                                      b"[" * 100_000, b'{"bounds": 1e999}', b"1" * 5000, b"NaN", b"{}"])))
@example(raw=b"[" * 100_000)
def test_json_bytes(profile_dir, raw):
    root = profile_dir
    (root / "scene_profile.json").write_bytes(raw)
    _expect_valid_or_dataset_error(lambda: load_scene_profile(root), lambda profile: isinstance(profile, dict))
    _expect_valid_or_dataset_error(lambda: load_scene_bounds(root), _check_bounds)


def _chunks(png: bytes) -> list[tuple[bytes, bytes]]:
    chunks, offset = [], 8
    while offset + 8 <= len(png):
        length, kind = struct.unpack(">I4s", png[offset:offset + 8])
        chunks.append((kind, png[offset + 8:offset + 8 + length]))
        offset += 12 + length
    return chunks


def _assemble(chunks: list[tuple[bytes, bytes]]) -> bytes:
    return b"\x89PNG\r\n\x1a\n" + b"".join(
        struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        for kind, data in chunks
    )


@st.composite
def damaged_png(draw, good: bytes):
    """A PNG with its header rewritten (valid CRC, so Pillow reads on), bytes flipped or cut."""
    operation = draw(st.sampled_from(["header", "flip", "cut", "idat"]))
    if operation == "header":
        chunks = _chunks(good)
        width = draw(st.one_of(st.integers(0, 64), st.just(100_000), st.just(2**31)))
        height = draw(st.one_of(st.integers(0, 64), st.just(100_000)))
        header = struct.pack(">IIBBBBB", width, height, draw(st.sampled_from([1, 2, 4, 8, 16, 7, 0])),
                             draw(st.sampled_from([0, 2, 3, 4, 6, 5])), draw(st.integers(0, 1)), 0,
                             draw(st.integers(0, 1)))
        return _assemble([(b"IHDR", header)] + chunks[1:])
    if operation == "flip":
        data = bytearray(good)
        for _ in range(draw(st.integers(1, 8))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        return bytes(data)
    if operation == "idat":  # a valid CRC around rubbish or a re-compressed stream of the wrong length
        chunks = _chunks(good)
        raw = zlib.decompress(b"".join(data for kind, data in chunks if kind == b"IDAT"))
        cut = draw(st.integers(0, len(raw)))
        body = draw(st.one_of(st.binary(max_size=64), st.just(zlib.compress(raw[:cut]))))
        return _assemble([chunks[0], (b"IDAT", body), (b"IEND", b"")])
    return good[: draw(st.integers(0, len(good)))]


@FUZZ
@given(data=st.data())
def test_damaged_png_bytes(fuzz_dataset, data):
    root, base = fuzz_dataset
    good = (root / "train" / "r_1.png").read_bytes()
    (root / "train" / "fuzz.png").write_bytes(data.draw(damaged_png(good)))
    document = copy.deepcopy(base)
    document["frames"][1]["file_path"] = "./train/fuzz"
    _write_json(root / "transforms_png.json", document)
    _expect_valid_or_dataset_error(lambda: load_split(root, "png"), lambda split: _check_split(split, root))


class _RunsCodeWhenUnpickled:
    """What a malicious checkpoint could carry: unpickling it calls Path.touch(marker)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_checkpoint_carrying_a_python_object_is_refused_and_runs_nothing(trained_run, tmp_path, capsys):
    """Checkpoints hold data only (weights_only=True): a run folder someone else made cannot
    run code when it is opened, resumed or rendered."""
    import shutil

    import torch

    run = tmp_path / "foreign_run"
    shutil.copytree(trained_run, run)
    marker = tmp_path / "code_ran"
    state = torch.load(run / "checkpoint.pt", weights_only=True)  # the project's own: data only
    state["payload"] = _RunsCodeWhenUnpickled(marker)
    torch.save(state, run / "checkpoint.pt")
    before = _snapshot(run)
    dataset = json.loads((run / "config.json").read_text())["dataset"]  # resumed on its own dataset
    for args in (["render", str(run), "--device", "cpu", "--no-progress"],
                 ["train", dataset, "--out", str(run), "--resume", "--iters", "5", "--no-progress"]):
        code = main(args)
        _assert_one_error_line(capsys.readouterr().err, str(run / "checkpoint.pt"), "refused", "could run code")
        assert code == 2 and not marker.exists(), args
    assert _snapshot(run) == before
