import sys

try:
    import torch  # noqa: F401  (checked first: without it the error would be a traceback)
except ModuleNotFoundError:
    raise SystemExit(f"python -m nerf_backend: error: this Python ({sys.executable}) has no torch; use the "
                     "project's Python, .venv/bin/python (`make setup` creates it)") from None

from .cli import main

raise SystemExit(main())
