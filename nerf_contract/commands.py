"""The command lines the add-on runs, built from keywords: the backend's commands
(``python -m nerf_backend COMMAND ...``) and the generator's own flags beside its options
(``blender -b SCENE --python datasets_gen/generate.py -- ...``).

The flag names are defined here once: nerf_backend's and datasets_gen's parsers are built with
them, and tests/test_contract.py parses every command line built here with the backends' real
parsers. The generator's options (``--out``, ``--device``, ``--overwrite``...) are not here:
they come from its options table, ``datasets_gen.core.options.options_to_argv``.

Example:
    >>> train_argv("ds", "run", device="cpu", preset="auto", max_seconds=600.0)
    ['train', 'ds', '--out', 'run', '--no-progress', '--device', 'cpu', '--preset', 'auto', '--max-seconds', '600.0']
    >>> backend_command("python3", report_argv("run"))
    ['python3', '-m', 'nerf_backend', 'report', 'run']
"""

from __future__ import annotations

from typing import Optional, Sequence

BACKEND_MODULE = "nerf_backend"
TRAIN, RENDER, COMPARE, MESH, REPORT, EXPORT, SERVE = "train", "render", "compare", "mesh", "report", "export", "serve"


class BackendFlag:
    """The backend's flags that the add-on passes."""

    OUT = "--out"
    DEVICE = "--device"
    NO_PROGRESS = "--no-progress"
    OVERWRITE = "--overwrite"
    PRESET = "--preset"
    RESUME = "--resume"
    ITERATIONS = "--iters"
    MAX_SECONDS = "--max-seconds"
    CPU_THREADS = "--cpu-threads"
    SPLIT = "--split"
    CAMERAS = "--cameras"
    CAMERA_PATH = "--camera-path"
    CYCLES = "--cycles"
    REFERENCE = "--reference"
    RENDER = "--render"
    RESOLUTION = "--resolution"
    TRIANGLES = "--triangles"
    TEXTURE_SIZE = "--texture-size"
    FRAMES = "--frames"
    IDLE_SECONDS = "--idle-seconds"


class GeneratorFlag:
    """The generator's flags of its own (beside its options' flags) that the add-on passes."""

    CAMERA_PATH = "--camera-path"
    FRAMES = "--frames"
    WITH_CYCLES = "--with-cycles"
    NO_PROGRESS = "--no-progress"
    RENDER_ASSET = "--render-asset"
    DATASET = "--dataset"
    ENGINE = "--engine"


def backend_command(python: str, argv: Sequence[str]) -> list[str]:
    """The process to start: the backend's Python running the backend's command line."""
    return [str(python), "-m", BACKEND_MODULE, *argv]


def train_argv(dataset: str, run: str, *, device: str, preset: Optional[str] = None, resume: bool = False,
               iterations: Optional[int] = None, max_seconds: Optional[float] = None,
               cpu_threads: Optional[int] = None, overwrite: bool = False) -> list[str]:
    """Train (or ``resume``, with the run's own preset) the run in ``run`` on ``dataset``."""
    argv = [TRAIN, str(dataset), BackendFlag.OUT, str(run), BackendFlag.NO_PROGRESS, BackendFlag.DEVICE, device]
    if cpu_threads:
        argv += [BackendFlag.CPU_THREADS, str(cpu_threads)]
    argv += [BackendFlag.RESUME] if resume else [BackendFlag.PRESET, str(preset)]
    if iterations:
        argv += [BackendFlag.ITERATIONS, str(iterations)]
    if max_seconds:
        argv += [BackendFlag.MAX_SECONDS, str(max_seconds)]
    if overwrite:
        argv.append(BackendFlag.OVERWRITE)
    return argv


def render_split_argv(run: str, split: str) -> list[str]:
    """Render a split's views into ``RUN/renders/SPLIT``."""
    return [RENDER, str(run), BackendFlag.SPLIT, split, BackendFlag.NO_PROGRESS]


def render_cameras_argv(run: str, cameras: str, out: str) -> list[str]:
    """Render the cameras of a transforms JSON (no images) into ``out``."""
    return [RENDER, str(run), BackendFlag.CAMERAS, str(cameras), BackendFlag.OUT, str(out)]


def render_camera_path_argv(run: str, camera_path: str, out: str, *, device: str, cycles: bool) -> list[str]:
    """Render a camera path's frames and video into ``out``; with ``cycles``, beside Cycles' frames."""
    argv = [RENDER, str(run), BackendFlag.CAMERA_PATH, str(camera_path), BackendFlag.OUT, str(out),
            BackendFlag.DEVICE, device, BackendFlag.NO_PROGRESS]
    return argv + ([BackendFlag.CYCLES] if cycles else [])


def compare_argv(reference: str, render: str, out: str) -> list[str]:
    """Score one render against one reference image, into ``out``."""
    return [COMPARE, BackendFlag.REFERENCE, str(reference), BackendFlag.RENDER, str(render), BackendFlag.OUT, str(out)]


def mesh_argv(run: str, out: str, *, resolution: int, device: str, overwrite: bool) -> list[str]:
    """Extract the run's surface into the mesh file ``out``."""
    argv = [MESH, str(run), BackendFlag.OUT, str(out), BackendFlag.RESOLUTION, str(resolution), BackendFlag.DEVICE, device]
    return argv + ([BackendFlag.OVERWRITE] if overwrite else [])


def export_argv(run: str, out: str, *, triangles: int, texture_size: int, device: str,
                cpu_threads: Optional[int] = None) -> list[str]:
    """Bake the run's surface into the asset ``out`` (glTF binary), replacing an earlier one."""
    argv = [EXPORT, str(run), BackendFlag.OUT, str(out), BackendFlag.TRIANGLES, str(triangles),
            BackendFlag.TEXTURE_SIZE, str(texture_size), BackendFlag.DEVICE, device, BackendFlag.NO_PROGRESS,
            BackendFlag.OVERWRITE]
    return argv + ([BackendFlag.CPU_THREADS, str(cpu_threads)] if cpu_threads else [])


def report_argv(run: str) -> list[str]:
    """Write the run's comparison page, ``RUN/report/index.html``."""
    return [REPORT, str(run)]


def serve_argv(run: str, frames: str, *, device: str, idle_seconds: Optional[float] = None) -> list[str]:
    """Keep the run's model loaded and render the views asked for on stdin into frame files in
    the folder ``frames`` (``view_frames``: the requests, events and frame files)."""
    argv = [SERVE, str(run), BackendFlag.FRAMES, str(frames), BackendFlag.DEVICE, device]
    return argv + ([BackendFlag.IDLE_SECONDS, str(idle_seconds)] if idle_seconds else [])


def render_asset_argv(asset: str, dataset: str, engine: str) -> list[str]:
    """The generator rendering a baked asset from the dataset's test cameras (its ``--out``, an
    option of the generator's, comes from ``options_to_argv``)."""
    return [GeneratorFlag.RENDER_ASSET, str(asset), GeneratorFlag.DATASET, str(dataset), GeneratorFlag.ENGINE, engine,
            GeneratorFlag.NO_PROGRESS]


def blender_script_command(blender: str, scene: str, script: str, argv: Sequence[str]) -> list[str]:
    """A background Blender opening ``scene`` and running ``script`` with ``argv`` after ``--``."""
    return [str(blender), "-b", str(scene), "--python", str(script), "--", *argv]


def camera_path_argv(camera: str, frames: str, *, with_cycles: bool) -> list[str]:
    """The generator's flags writing ``camera``'s path over ``frames`` (``S:E:STEP``) into the
    dataset (given by ``--out``, an option), and with ``with_cycles`` its Cycles frames."""
    argv = [GeneratorFlag.CAMERA_PATH, camera, GeneratorFlag.FRAMES, frames]
    return argv + ([GeneratorFlag.WITH_CYCLES] if with_cycles else [])
