"""Test-only stand-in for torchvision, so the ``lpips`` package's own code can run as the
reference for this project's LPIPS: PyPI's torchvision does not import beside the CPU
build of torch pinned here. It supplies only what ``lpips`` builds for ``net="alex"``:
torchvision's AlexNet trunk (the same layer list and parameter names), with the weights
the test wrote to ``$LPIPS_TEST_BACKBONE``. Nothing outside tests/reference_lpips.py uses it.
"""

from . import models  # noqa: F401
