import gc
import os
import sys

# No garbage collection while the modules load, and what they made kept out of later ones: the
# collector walked torch's import three times (0.2 s of `eval`'s start) and the whole heap once
# more at exit (0.1 s), for objects that live as long as the process.
gc.disable()

# OpenMP's threads spin for a while after each of PyTorch's operations, waiting for the next;
# the compiled kernels (kernels/) run on threads of their own in between, and the spinning took
# their cores. Sleeping threads instead, measured on lego at 800×800 on 2 cores: a rendered view
# 0.86-0.96 → 0.64-0.65 s, `eval` 13.3 → 12.2 s, two minutes of training 1 892 and 1 812 steps →
# 2 102 and 2 201 (docs/benchmarks_lego.md). Set before torch loads OpenMP; the user's own
# setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Large freed blocks kept for reuse, not handed back to the kernel and faulted in again
# (core/allocator.py: a rendered view of lego 0.55 s against 0.61-0.69).
from .core.allocator import keep_freed_memory  # noqa: E402  (before torch's first allocations)

keep_freed_memory()

try:
    import torch  # noqa: F401  (checked first: without it the error would be a traceback)
except ModuleNotFoundError:
    raise SystemExit(f"python -m nerf_backend: error: this Python ({sys.executable}) has no torch; use the "
                     "project's Python, .venv/bin/python (`make setup` creates it)") from None

from .cli import main  # noqa: E402  (after the settings above)

gc.freeze()
gc.enable()

raise SystemExit(main())
