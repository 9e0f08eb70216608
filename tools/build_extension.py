"""Build the installable Blender extension: ``python tools/build_extension.py [--out DIR]``
(what ``make extension`` runs). Standard library only.

The zip's root is the add-on package: ``blender_manifest.toml``, the ``addon/`` modules, and
the ``datasets_gen`` and ``nerf_backend`` sources as sub-folders (the add-on finds them
there; see addon/sources.py). Nothing else goes in: no caches, no tests, no data.
"""

from __future__ import annotations

import argparse
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUNDLED_PACKAGES = ("datasets_gen", "nerf_backend")
BACKEND_DATA = ("nerf_backend/requirements.txt", "nerf_backend/configs/presets.json")


def extension_files() -> list[tuple[Path, str]]:
    """(source file, path inside the zip) for everything the extension ships."""
    files = [(REPO / "blender_manifest.toml", "blender_manifest.toml")]
    files += [(path, path.name) for path in sorted((REPO / "addon").glob("*.py"))]
    for package in BUNDLED_PACKAGES:
        files += [(path, path.relative_to(REPO).as_posix()) for path in sorted((REPO / package).rglob("*.py"))
                  if "__pycache__" not in path.parts]
    files += [(REPO / name, name) for name in BACKEND_DATA]
    return files


def build(out_dir: Path) -> Path:
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    partial = target.with_suffix(".zip.partial")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
        for source, name in extension_files():
            archive.write(source, name)
    partial.replace(target)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="build_extension", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "dist")
    args = parser.parse_args(argv)
    path = build(args.out)
    print(f"built {path} ({path.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
