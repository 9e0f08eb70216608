"""Build the installable Blender extension and its repository: ``python
tools/build_extension.py [--out DIR]`` (what ``make extension`` runs). Standard library only.

The zip's root is the add-on package: ``blender_manifest.toml``, ``addon/``'s contents (its
``__init__.py``, ``core/`` and ``blender/``), the
wheel the manifest names (``wheels/``: ``datasets_gen`` and ``nerf_contract``, which the add-on
imports; Blender installs it beside its own modules, its recommended way to bundle Python
modules), and the ``nerf_backend`` and ``nerf_contract`` sources as sub-folders, for the
backend's own Python (see addon/core/sources.py). Nothing else goes in: no caches, no tests, no data.
The wheel is written here with the standard library (a pure-Python wheel is a zip with three
metadata files), with fixed timestamps so that the same sources give the same bytes.

Beside the zips, ``index.json`` lists every extension zip in DIR as Blender's own
``blender --command extension server-generate --repo-dir DIR`` would (tests/test_gui.py checks
that they are the same, in a real Blender): served over HTTP, or as a folder, DIR is a
repository a user adds once (Preferences › Get Extensions › Repositories › + › Add Remote
Repository, its index.json's URL) and Blender then installs and updates the add-on from it.
Written here, not by Blender, so that ``make extension`` needs no Blender.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import json
import re
import sys
import zipfile
from pathlib import Path

import tomllib

REPO = Path(__file__).resolve().parents[1]
BACKEND_PACKAGES = ("nerf_backend", "nerf_contract")  # folders: the backend's PYTHONPATH
WHEEL_PACKAGES = ("datasets_gen", "nerf_contract")  # the wheel: what the add-on imports
WHEEL_NAME = re.compile(r"\./wheels/(?P<name>[A-Za-z0-9_]+)-(?P<version>[0-9.]+)-py3-none-any\.whl")
FIXED_TIME = (1980, 1, 1, 0, 0, 0)
BACKEND_DATA = ("nerf_backend/requirements.txt", "nerf_backend/requirements-no-deps.txt", "nerf_backend/configs/presets.json")
# The compiled kernels' C sources, every one: the backend builds them on first use (a kernel left
# out would only be noticed when training or rendering reached it).
KERNEL_SOURCES = ("nerf_backend/kernels", ("*.c", "*.h"))  # a kernel includes the headers beside it


def _sources(package: str) -> list[Path]:
    return [path for path in sorted((REPO / package).rglob("*.py")) if "__pycache__" not in path.parts]


def extension_files() -> list[tuple[Path, str]]:
    """(source file, path inside the zip) for everything the extension ships, but its wheel."""
    files = [(REPO / "blender_manifest.toml", "blender_manifest.toml")]
    # The add-on package at the root: its __init__.py (the entry Blender registers), core/, blender/.
    files += [(path, path.relative_to(REPO / "addon").as_posix()) for path in _sources("addon")]
    for package in BACKEND_PACKAGES:
        files += [(path, path.relative_to(REPO).as_posix()) for path in _sources(package)]
    files += [(REPO / name, name) for name in BACKEND_DATA]
    folder, patterns = KERNEL_SOURCES
    for pattern in patterns:
        files += [(path, path.relative_to(REPO).as_posix()) for path in sorted((REPO / folder).glob(pattern))]
    return files


def wheel_entry(manifest: dict) -> tuple[str, str, str]:
    """The manifest's one wheel: (its path in the zip, distribution name, version); ValueError
    naming the manifest when it lists another or none, or a version other than the extension's."""
    wheels = manifest.get("wheels", [])
    match = WHEEL_NAME.fullmatch(wheels[0]) if len(wheels) == 1 else None
    if match is None or match["version"] != manifest["version"]:
        raise ValueError(f"{REPO / 'blender_manifest.toml'}: 'wheels' must list one ./wheels/NAME-"
                         f"{manifest['version']}-py3-none-any.whl (the extension's version), got {wheels}")
    return wheels[0].removeprefix("./"), match["name"], match["version"]


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def wheel_bytes(name: str, version: str, packages: tuple[str, ...] = WHEEL_PACKAGES) -> bytes:
    """A pure-Python wheel of ``packages``' sources (METADATA, WHEEL and RECORD as the wheel
    format asks), with fixed timestamps."""
    files = {path.relative_to(REPO).as_posix(): path.read_bytes() for package in packages for path in _sources(package)}
    info = f"{name}-{version}.dist-info"
    files[f"{info}/METADATA"] = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n".encode()
    files[f"{info}/WHEEL"] = (b"Wheel-Version: 1.0\nGenerator: tools/build_extension.py\nRoot-Is-Purelib: true\n"
                              b"Tag: py3-none-any\n")
    record = "".join(f"{path},{_record_hash(data)},{len(data)}\n" for path, data in files.items())
    files[f"{info}/RECORD"] = (record + f"{info}/RECORD,,\n").encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path, data in files.items():
            archive.writestr(zipfile.ZipInfo(path, FIXED_TIME), data, zipfile.ZIP_DEFLATED)
    return buffer.getvalue()


def build(out_dir: Path) -> Path:
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    wheel_path, wheel_name, wheel_version = wheel_entry(manifest)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    partial = target.with_suffix(".zip.partial")
    with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
        for source, name in extension_files():
            archive.write(source, name)
        archive.writestr(wheel_path, wheel_bytes(wheel_name, wheel_version))
    partial.replace(target)
    return target


def python_versions(wheels: list[str]) -> list[str]:
    """The Python versions a listing names for an extension's wheels, as Blender derives them
    from each wheel's Python tag (``py3`` is "3", ``cp311`` is "3.11").

    >>> python_versions(["./wheels/a-1.0-py3-none-any.whl", "./wheels/b-2-cp311-cp311-win_amd64.whl"])
    ['3', '3.11']
    """
    versions = set()
    for wheel in wheels:
        for tag in Path(wheel).name.split("-")[-3].split("."):
            digits = tag.lstrip("cpy")
            versions.add(digits[0] + ("." + digits[1:] if len(digits) > 1 else ""))
    return sorted(versions)


def _listing_entry(archive: Path) -> dict | None:
    """A repository listing's entry for one extension zip: its manifest's fields, and where the
    archive is, its size and SHA-256; None for a zip that is not an extension. As Blender's
    listing does, the wheels are not listed but the Python versions they need are."""
    with zipfile.ZipFile(archive) as package:
        if "blender_manifest.toml" not in package.namelist():
            return None
        manifest = tomllib.loads(package.read("blender_manifest.toml").decode("utf-8"))
    wheels = manifest.pop("wheels", [])
    if wheels:
        manifest["python_versions"] = python_versions(wheels)
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
