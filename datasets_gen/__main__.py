"""`python -m datasets_gen ...` (needs the bpy module); see datasets_gen.cli."""

import sys

from .cli import main

sys.exit(main())
