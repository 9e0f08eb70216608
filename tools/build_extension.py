"""Build the installable Blender extension and its repository: ``python
tools/build_extension.py [--out DIR]`` (what ``make extension`` runs). Standard library only.

The zip's root is the add-on package: ``blender_manifest.toml``, the ``addon/`` modules, and
the ``datasets_gen`` and ``nerf_backend`` sources as sub-folders (the add-on finds them
there; see addon/sources.py). Nothing else goes in: no caches, no tests, no data.

Beside the zips, ``index.json`` lists every extension zip in DIR as Blender's own
``blender --command extension server-generate --repo-dir DIR`` would (tests/test_gui.py checks
that they are the same, in a real Blender): served over HTTP, or as a folder, DIR is a
repository a user adds once (Preferences › Get Extensions › Repositories › + › Add Remote
Repository, its index.json's URL) and Blender then installs and updates the add-on from it.
Written here, not by Blender, so that ``make extension`` needs no Blender.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUNDLED_PACKAGES = ("datasets_gen", "nerf_backend")
BACKEND_DATA = ("nerf_backend/requirements.txt", "nerf_backend/requirements-no-deps.txt", "nerf_backend/configs/presets.json")


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


def _listing_entry(archive: Path) -> dict | None:
    """A repository listing's entry for one extension zip: its manifest's fields, and where the
    archive is, its size and SHA-256; None for a zip that is not an extension."""
    with zipfile.ZipFile(archive) as package:
        if "blender_manifest.toml" not in package.namelist():
            return None
        manifest = tomllib.loads(package.read("blender_manifest.toml").decode("utf-8"))
    data = archive.read_bytes()
    return {**manifest, "archive_url": f"./{archive.name}", "archive_size": len(data),
            "archive_hash": f"sha256:{hashlib.sha256(data).hexdigest()}"}


def write_repository_index(folder: Path) -> Path:
    """``folder/index.json``: the repository listing (format v1) of the extension zips in it."""
    entries = [entry for archive in sorted(folder.glob("*.zip")) if (entry := _listing_entry(archive)) is not None]
    index = folder / "index.json"
    partial = index.with_suffix(".json.partial")
    partial.write_text(json.dumps({"version": "v1", "blocklist": [], "data": entries}, indent=2) + "\n")
    partial.replace(index)
    return index


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="build_extension", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "dist")
    args = parser.parse_args(argv)
    path = build(args.out)
    index = write_repository_index(args.out)
    print(f"built {path} ({path.stat().st_size // 1024} KiB); repository listing {index}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
