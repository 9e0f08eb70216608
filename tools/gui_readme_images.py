"""The README's two pictures of the add-on, cut from the GUI test's screenshots
(``make test-gui`` leaves them in out/gui-screenshots/SUITE/; sid's, the newest Blender, by
default): the sidebar while training and when
done, and the comparison in the Image Editor.

    .venv/bin/python tools/gui_readme_images.py [SCREENSHOTS] [--out docs]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from PIL import Image

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("screenshots", type=Path, nargs="?", default=REPO / "out" / "gui-screenshots" / "sid")
    parser.add_argument("--out", type=Path, default=REPO / "docs")
    args = parser.parse_args()
    report = json.loads((args.screenshots / "gui_report.json").read_text())

    def crop(name: str) -> Image.Image:
        image = Image.open(args.screenshots / f"{name}.png").convert("RGB")
        x0, y0, x1, y1 = report["shots"][name]["panel_box"]  # rows bottom-up
        return image.crop((x0, image.height - y1, x1, image.height - y0))

    panels = [crop("06_training"), crop("08_trained")]
    sidebar = Image.new("RGB", (sum(p.width for p in panels) + 8, max(p.height for p in panels)), (40, 40, 40))
    for number, panel in enumerate(panels):
        sidebar.paste(panel, (number * (panels[0].width + 8), 0))
    sidebar.save(args.out / "gui_sidebar.png", optimize=True)
    crop("10_compared").save(args.out / "gui_compare.png", optimize=True)
    print(f"wrote {args.out / 'gui_sidebar.png'} and {args.out / 'gui_compare.png'}")


if __name__ == "__main__":
    main()
