"""Entry point for Blender's own Python: `blender -b [SCENE.blend] --python datasets_gen/generate.py -- ARGS`.

Blender runs this file as a script, not as part of a package, so it puts the repository root on
sys.path itself (whatever the current directory) and passes the arguments after `--` to the
same CLI as `python -m datasets_gen`.  Without SCENE.blend or --demo after `--`, it renders the
file Blender opened (`blender -b SCENE.blend ...`), exactly as `python -m datasets_gen
SCENE.blend` would.  It always ends with sys.exit(status) because Blender otherwise returns 0
even when a --python script fails.
"""

import os
import sys


def _arguments_after_double_dash(argv: list) -> list:
    return argv[argv.index("--") + 1:] if "--" in argv else []


def _main() -> None:
    repo_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if repo_root not in sys.path:
        sys.path.insert(0, repo_root)
    import bpy

    from datasets_gen.cli import main

    try:
        status = main(_arguments_after_double_dash(sys.argv), blender_file=bpy.data.filepath)
    except SystemExit as exit_request:  # argparse errors and --help
        code = exit_request.code
        status = code if isinstance(code, int) else (0 if code is None else 1)
    except BaseException:
        import traceback

        traceback.print_exc()
        status = 1
    sys.stdout.flush()
    sys.stderr.flush()
    # Blender exits with this status (and cleans up its session) on SystemExit from a --python script.
    sys.exit(status)


if __name__ == "__main__":
    _main()
