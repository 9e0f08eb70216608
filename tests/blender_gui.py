"""The real Blender program with its GUI, for tests: Debian trixie's Blender 4.3.2 in a chroot
of its own (this machine's Debian 12 has only Blender 3.4), drawn by Xvfb with Mesa's
software OpenGL. Facts checked in ../shared/BLENDER_GUI.md.

``python tests/blender_gui.py`` builds the chroot once (about 2 minutes, 1.4 GB; root, with
Debian's mirror reachable) and caches it in ``$NERF_BLENDER_GUI_CHROOT`` (default
``~/.cache/nerf-from-blender/blender-gui-trixie``); the GUI test calls it too.

Inside, a test sees its work folder at the same path as outside (a bind mount), and the
host's root at ``/host``: the add-on's backend runs the project's ``.venv`` through
``chroot /host``, as a user's Blender would run a Python set up beside it.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

CHROOT = Path(os.environ.get("NERF_BLENDER_GUI_CHROOT",
                             Path.home() / ".cache" / "nerf-from-blender" / "blender-gui-trixie"))
# python3-numpy: Debian's blender only recommends it, and the add-on (the voxeliser) needs it.
PACKAGES = ("blender", "python3-numpy", "xvfb", "xauth", "x11-apps", "imagemagick")
READY = ".nerf-ready"  # written last: a chroot without it is incomplete


def _run(*command: str | os.PathLike, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run([str(c) for c in command], capture_output=True, text=True, **kwargs)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, command))} exited {result.returncode}:\n"
                           f"{result.stdout[-2000:]}{result.stderr[-2000:]}")
    return result


def _mirror() -> str:
    """The Debian mirror apt already uses here (the only one reachable)."""
    sources = Path("/etc/apt/sources.list.d/debian.sources")
    if sources.is_file():
        for line in sources.read_text().splitlines():
            if line.startswith("URIs:"):
                return line.split()[1]
    return "http://deb.debian.org/debian"


def mount_points_under(root: Path) -> list[Path]:
    root = root.resolve()
    points = [Path(line.split()[1].replace("\\040", " ")) for line in Path("/proc/self/mounts").read_text().splitlines()]
    return [p for p in points if p == root or root in p.parents]


def _remove_unmounted(folder: Path) -> None:
    """rm -rf, but never across a mount (a bind-mounted /dev would take the host's devices)."""
    if mount_points_under(folder):
        raise RuntimeError(f"{folder}: something is still mounted under it; not removing it")
    shutil.rmtree(folder)


@contextlib.contextmanager
def mounted(root: Path, same_paths: tuple[Path, ...] = (), host: bool = False) -> Iterator[None]:
    """The chroot's /proc, /sys and /dev; each of ``same_paths`` at its own path inside; with
    ``host``, the host's root at /host (with its own /proc and /dev). Unmounted on exit."""
    points: list[Path] = []

    def mount(target: Path, *options: str) -> None:
        target.mkdir(parents=True, exist_ok=True)
        _run("mount", *options, target)
        points.append(target)

    try:
        mount(root / "proc", "-t", "proc", "proc")
        mount(root / "sys", "-t", "sysfs", "sys")
        for device in ("/dev", "/dev/pts", "/dev/shm"):
            mount(root / device.lstrip("/"), "--bind", device)
        if host:
            mount(root / "host", "--bind", "/")
            mount(root / "host" / "proc", "-t", "proc", "proc")
            for device in ("/dev", "/dev/pts", "/dev/shm"):
                mount(root / "host" / device.lstrip("/"), "--bind", device)
        for path in same_paths:
            mount(root / str(path.resolve()).lstrip("/"), "--bind", str(path.resolve()))
        yield
    finally:
        for point in reversed(points):
            if subprocess.run(["umount", str(point)], capture_output=True).returncode != 0:
                subprocess.run(["umount", "-l", str(point)], capture_output=True)


def ensure_chroot(log=print) -> Path:
    """The cached chroot, built first if missing; raises with the reason when it cannot be."""
    if (CHROOT / READY).is_file():
        missing = [p for p in PACKAGES if not (CHROOT / "var" / "lib" / "dpkg" / "info" / f"{p}.list").is_file()]
        if missing:  # a chroot cached before a package was added to PACKAGES
            log(f"apt-get install {' '.join(missing)}")
            with mounted(CHROOT):
                _run("chroot", CHROOT, "apt-get", "update", "-qq")
                _run("chroot", CHROOT, "apt-get", "install", "-y", "-qq", "--no-install-recommends", *missing,
                     env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
                _run("chroot", CHROOT, "apt-get", "clean")
        return CHROOT
    if os.geteuid() != 0:
        raise RuntimeError(f"building {CHROOT} needs root (debootstrap, mount, chroot)")
    if shutil.which("debootstrap") is None:
        log("installing debootstrap")
        _run("apt-get", "install", "-y", "-qq", "debootstrap",
             env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    partial = CHROOT.with_name(CHROOT.name + ".partial")
    if partial.exists():
        _remove_unmounted(partial)
    partial.parent.mkdir(parents=True, exist_ok=True)
    log(f"debootstrap trixie into {partial}")
    _run("debootstrap", "--variant=minbase", "trixie", partial, _mirror())
    shutil.copy("/etc/resolv.conf", partial / "etc" / "resolv.conf")
    (partial / "etc" / "mtab").unlink(missing_ok=True)
    (partial / "etc" / "mtab").symlink_to("../proc/self/mounts")
    with mounted(partial):
        log(f"apt-get install {' '.join(PACKAGES)}")
        _run("chroot", partial, "apt-get", "update", "-qq")
        _run("chroot", partial, "apt-get", "install", "-y", "-qq", "--no-install-recommends", *PACKAGES,
             env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
        _run("chroot", partial, "apt-get", "clean")
    (partial / READY).write_text(_run("chroot", partial, "blender", "--version").stdout.splitlines()[0] + "\n")
    if CHROOT.exists():
        _remove_unmounted(CHROOT)
    partial.rename(CHROOT)
    return CHROOT


def blender_version() -> str:
    return (CHROOT / READY).read_text().strip()


if __name__ == "__main__":
    try:
        print(f"ready: {ensure_chroot()} ({blender_version()})")
    except RuntimeError as error:
        sys.exit(f"blender_gui: {error}")
