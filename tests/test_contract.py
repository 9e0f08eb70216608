"""The contract between the add-on and the backends (nerf_contract): every command line the
add-on builds parses with the backends' real parsers into what was asked, the flag names the
contract defines are the ones the parsers define, and the events round-trip."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from datasets_gen.cli import build_parser as generator_parser
from datasets_gen.core.options import options_from_keywords, options_to_argv
from nerf_backend.cli import build_parser as backend_parser
from nerf_backend.cli import parse_arguments
from nerf_backend.commands import COMMANDS, command_module
from nerf_contract import commands, training_events
from nerf_contract.commands import BackendFlag, GeneratorFlag


def _backend(argv):
    return parse_arguments(argv)  # as python -m nerf_backend reads it: the command's own parser


def test_each_command_is_the_module_it_names_and_a_process_imports_only_its_own():
    """A process builds only its command's parser and imports only that command's module (the
    others' imports cost a ``train`` about 0.3 s), and not scipy.ndimage or scikit-image's
    metrics (another 0.3 s) which training never calls; ``--help`` alone names them all."""
    assert [command_module(name).NAME for name in COMMANDS] == list(COMMANDS)
    probe = ("import sys; from nerf_backend.cli import parse_arguments; "
             "parse_arguments(['train', 'ds', '--out', 'run']); "
             "print(*sorted(m for m in sys.modules if m.startswith('nerf_backend.commands.') or m in "
             "('nerf_backend.bench', 'skimage.measure', 'skimage.metrics', 'scipy.ndimage')))")
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert loaded.split() == ["nerf_backend.commands.arguments", "nerf_backend.commands.train"], loaded
    with pytest.raises(SystemExit):
        parse_arguments(["--help"])


def test_training_command_lines_parse_as_asked():
    args = _backend(commands.train_argv("ds", "run", device="cpu", preset="auto", max_seconds=600.0, cpu_threads=1,
                                        overwrite=True))
    assert (args.command, str(args.dataset), str(args.out), args.device, args.preset) == ("train", "ds", "run", "cpu", "auto")
    assert (args.max_seconds, args.iters, args.cpu_threads, args.overwrite, args.no_progress) == (600.0, None, 1, True, True)
    resumed = _backend(commands.train_argv("ds", "run", device="auto", resume=True, iterations=500))
    assert (resumed.resume, resumed.preset, resumed.iters) == (True, None, 500)


def test_render_compare_mesh_and_report_command_lines_parse_as_asked():
    split = _backend(commands.render_split_argv("run", "test"))
    assert (split.command, str(split.run), split.split, split.no_progress) == ("render", "run", "test", True)
    cameras = _backend(commands.render_cameras_argv("run", "cams.json", "out"))
    assert (str(cameras.cameras), str(cameras.out)) == ("cams.json", "out")
    path = _backend(commands.render_camera_path_argv("run", "path.json", "out", device="cpu", cycles=True))
    assert (str(path.camera_path), str(path.out), path.device, path.cycles) == ("path.json", "out", "cpu", True)
    compare = _backend(commands.compare_argv("cycles.png", "nerf.png", "out"))
    assert (compare.command, str(compare.reference), str(compare.render), str(compare.out)) == \
        ("compare", "cycles.png", "nerf.png", "out")
    mesh = _backend(commands.mesh_argv("run", "m.ply", resolution=64, device="cpu", overwrite=True))
    assert (mesh.command, mesh.resolution, mesh.device, mesh.overwrite) == ("mesh", 64, "cpu", True)
    asset = _backend(commands.export_argv("run", "a.glb", triangles=20000, texture_size=1024, device="cpu",
                                          cpu_threads=1))
    assert (asset.command, str(asset.out), asset.triangles, asset.texture_size, asset.device, asset.cpu_threads) == \
        ("export", "a.glb", 20000, 1024, "cpu", 1)
    assert asset.overwrite and asset.no_progress
    report = _backend(commands.report_argv("run"))
    assert (report.command, [str(r) for r in report.results]) == ("report", ["run"])
    serve = _backend(commands.serve_argv("run", "frames", device="cpu", idle_seconds=30.0))
    assert (serve.command, str(serve.run), str(serve.frames), serve.device, serve.idle_seconds) == \
        ("serve", "run", "frames", "cpu", 30.0)


def test_a_flag_the_backend_does_not_define_fails_to_parse():
    """What the test above relies on: the real parser refuses an unknown flag."""
    with pytest.raises(SystemExit):
        _backend([*commands.report_argv("run"), "--no-such-flag"])


def test_the_generators_camera_path_command_line_parses_as_asked():
    options = options_from_keywords(out_dir="ds", open_scene=True, device="CUDA", overwrite=True)
    argv = [*options_to_argv(options), *commands.camera_path_argv("Camera.001", "1:48:2", with_cycles=True),
            GeneratorFlag.NO_PROGRESS]
    args = generator_parser().parse_args(argv)
    assert (args.out_dir, args.device, args.overwrite) == ("ds", "CUDA", True)
    assert (args.camera_path, args.frames, args.cycles, args.no_progress) == ("Camera.001", "1:48:2", True, True)


def _option_strings(parser) -> set[str]:
    found = set()
    for action in parser._actions:  # argparse keeps no public list of a parser's flags
        found.update(action.option_strings)
        for sub in getattr(action, "choices", None).values() if isinstance(action.choices, dict) else ():
            found |= _option_strings(sub)
    return found


@pytest.mark.parametrize("flags, parser", [(BackendFlag, backend_parser), (GeneratorFlag, generator_parser)])
def test_every_contract_flag_is_one_the_parser_defines(flags, parser):
    names = {value for key, value in vars(flags).items() if not key.startswith("_")}
    assert names - _option_strings(parser()) == set()


def test_events_round_trip_through_a_line():
    events = [training_events.Start(iteration=0, preset="auto", target_iterations=None, max_seconds=60.0),
              training_events.Train(iteration=10, loss=0.01, psnr=20.0, image_size=[100, 100], elapsed_s=1.5),
              training_events.Collapse(iteration=20, views=[0, 1], action="restarted", reason="near blank"),
              training_events.Done(iteration=30, reason="time", val_psnr=31.0)]
    text = "\n".join(training_events.to_line(event) for event in events)
    assert training_events.parse_lines(text) == events
    assert [json.loads(line)["event"] for line in text.splitlines()] == ["start", "train", "collapse", "done"]


def test_an_older_log_still_reads():
    """A field this version added is missing, one it dropped is present: both are fine."""
    line = json.dumps({"event": "val", "iteration": 5, "psnr": 12.0, "retired_field": 1})
    (event,) = training_events.parse_lines(line)
    assert event == training_events.Val(iteration=5, psnr=12.0)
    assert dataclasses.asdict(event)["blank_psnr"] is None
