"""Real Blender programs and Python 3.13 for tests, from Debian's archive, each in a chroot of its
own (this machine's Debian 12 has only Blender 3.4 and Python 3.11), drawn by Xvfb with Mesa's
software OpenGL. Facts checked in ../shared/BLENDER_GUI.md.

- ``trixie`` (Debian 13): Blender 4.3.2, and Python 3.13, which the ``bpy`` 5.1 and 5.2 wheels
  need (``tests/blender_versions.py`` makes their venvs inside it);
- ``sid`` (Debian unstable): the newest Blender Debian packages (5.2.2 on 2026-11-25; its
  Python is 3.14, so no ``bpy`` wheel runs there).

``python tests/blender_gui.py [SUITE ...]`` builds the chroots once (about 2-3 minutes and
1.5 GB each; root, with Debian's mirror reachable) and caches them in
``~/.cache/nerf-from-blender/blender-gui-SUITE`` (``$NERF_BLENDER_GUI_CHROOT`` for trixie's);
the tests call it too.

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
import time
from collections.abc import Iterator
from pathlib import Path

SUITES = ("trixie", "sid")
CACHE = Path.home() / ".cache" / "nerf-from-blender"
# python3-numpy: Debian's blender only recommends it, and the add-on (the voxeliser) needs it.
# python3-venv, python3-pip and ca-certificates: the bpy venvs made inside (trixie's Python 3.13).
# libegl1, libegl-mesa0 and libgl1-mesa-dri: EEVEE in those bpy wheels draws through EGL ("Couldn't
# open libEGL.so.1" without them), here on Mesa's software renderer.
PACKAGES = ("blender", "python3-numpy", "xvfb", "xauth", "x11-apps", "imagemagick", "python3-venv", "python3-pip",
            "ca-certificates", "libegl1", "libegl-mesa0", "libgl1-mesa-dri")
# sid's blender 5.2.2 package does not depend on the modules its Extensions add-on imports
# (cattrs, requests): without them that add-on fails to register ("No module named 'cattrs'")
# and `blender --command extension` cannot run. A user of that package needs them too.
SUITE_PACKAGES = {"trixie": (), "sid": ("python3-cattr", "python3-requests")}
READY = ".nerf-ready"  # written last: a chroot without it is incomplete
# Where the host's pip finds its certificate authorities: a chroot's pip needs the same ones.
HOST_CERTIFICATES = Path("/usr/local/share/ca-certificates")


def chroot_path(suite: str = "trixie") -> Path:
    if suite == "trixie" and os.environ.get("NERF_BLENDER_GUI_CHROOT"):
        return Path(os.environ["NERF_BLENDER_GUI_CHROOT"])
    return CACHE / f"blender-gui-{suite}"



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
    # A run killed before its cleanup (Ctrl+C twice, a timeout) leaves its mounts: lift them
    # first, deepest first, or every mount below fails with "already mounted".
    for stale in sorted(mount_points_under(root), key=lambda p: len(p.parts), reverse=True):
        if stale != root.resolve():
            subprocess.run(["umount", "-l", str(stale)], capture_output=True)

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


def _trust_host_certificates(root: Path) -> None:
    """The host's extra certificate authorities, trusted inside too (pip fails without them)."""
    if HOST_CERTIFICATES.is_dir() and any(HOST_CERTIFICATES.glob("*.crt")):
        target = root / HOST_CERTIFICATES.relative_to("/")
        target.mkdir(parents=True, exist_ok=True)
        for certificate in HOST_CERTIFICATES.glob("*.crt"):
            shutil.copy(certificate, target / certificate.name)
        _run("chroot", root, "update-ca-certificates")


def _apt_install(root: Path, packages: tuple[str, ...] | list[str]) -> None:
    # Check-Valid-Until off: the mirror reachable here serves a snapshot whose sid Release file
    # has expired (apt refuses it otherwise); its packages are still signed and checked.
    _run("chroot", root, "apt-get", "-o", "Acquire::Check-Valid-Until=false", "update", "-qq")
    _run("chroot", root, "apt-get", "install", "-y", "-qq", "--no-install-recommends", *packages,
         env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    _run("chroot", root, "apt-get", "clean")


def ensure_chroot(suite: str = "trixie", log=print) -> Path:
    """The cached chroot of ``suite``, built first if missing; raises with the reason when it
    cannot be."""
    if suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}: choose one of {', '.join(SUITES)}")
    root = chroot_path(suite)
    packages = PACKAGES + SUITE_PACKAGES[suite]
    if (root / READY).is_file():
        missing = [p for p in packages if not (root / "var" / "lib" / "dpkg" / "info" / f"{p}.list").is_file()
                   and not any((root / "var" / "lib" / "dpkg" / "info").glob(f"{p}:*.list"))]
        if missing:  # a chroot cached before a package was added to PACKAGES
            log(f"apt-get install {' '.join(missing)}")
            with mounted(root):
                _apt_install(root, missing)
                _trust_host_certificates(root)
        return root
    if os.geteuid() != 0:
        raise RuntimeError(f"building {root} needs root (debootstrap, mount, chroot)")
    if shutil.which("debootstrap") is None:
        log("installing debootstrap")
        _run("apt-get", "install", "-y", "-qq", "debootstrap",
             env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    partial = root.with_name(root.name + ".partial")
    if partial.exists():
        _remove_unmounted(partial)
    partial.parent.mkdir(parents=True, exist_ok=True)
    log(f"debootstrap {suite} into {partial}")
    _run("debootstrap", "--variant=minbase", suite, partial, _mirror())
    shutil.copy("/etc/resolv.conf", partial / "etc" / "resolv.conf")
    (partial / "etc" / "mtab").unlink(missing_ok=True)
    (partial / "etc" / "mtab").symlink_to("../proc/self/mounts")
    with mounted(partial):
        log(f"apt-get install {' '.join(packages)}")
        _apt_install(partial, packages)
        _trust_host_certificates(partial)
    (partial / READY).write_text(_run("chroot", partial, "blender", "--version").stdout.splitlines()[0] + "\n")
    if root.exists():
        _remove_unmounted(root)
    partial.rename(root)
    return root


SCREEN = "1600x1000x24"
DISPLAY = ":99"


def in_chroot(chroot: Path, work: Path, *command: str, **kwargs) -> subprocess.Popen:
    """``command`` started in the chroot with a clean environment, in ``work``, on the Xvfb display."""
    environment = {"HOME": str(work / "home"), "PATH": "/usr/bin:/bin", "DISPLAY": DISPLAY,
                   "LIBGL_ALWAYS_SOFTWARE": "1", "BROWSER": str(work / "browser")}
    return subprocess.Popen(["chroot", str(chroot), "/usr/bin/env", "-i", *(f"{k}={v}" for k, v in environment.items()),
                             "/usr/bin/env", "-C", str(work), *command], **kwargs)


def kill_processes_using(folder: Path) -> None:
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if int(cmdline.parent.name) != os.getpid() and str(folder) in cmdline.read_bytes().decode(errors="replace"):
                os.kill(int(cmdline.parent.name), 9)
        except (OSError, ValueError):
            continue


def run_session(chroot: Path, work: Path, script: Path, *arguments: str, blend: Path | None = None,
                timeout: float = 1500) -> str:
    """The add-on's extension built and installed in the chroot's Blender, then ``script`` run in
    its GUI under Xvfb (``--enable-event-simulate``; ``blend`` opened first) with ``WORK
    BACKEND_PYTHON ARGUMENTS`` after ``--``; returns Blender's console. The backend's Python is
    this one (the project's .venv on the host), reached through ``chroot /host``; ``$BROWSER``
    records URLs in WORK/browser_urls.txt."""
    from conftest import REPO_ROOT, run_python

    (work / "home").mkdir(exist_ok=True)
    run_python(str(REPO_ROOT / "tools" / "build_extension.py"), "--out", str(work))
    extension = next(work.glob("nerf_from_blender-*.zip"))
    # A session imports the driver of another, and the checks the headless session shares.
    for helper in [*script.parent.glob("*_session.py"), *script.parent.glob("*_check.py")]:
        shutil.copy(helper, work)
    backend = work / "backend-python"
    backend.write_text(f'#!/bin/sh\nexec /usr/sbin/chroot /host /usr/bin/env -C "$PWD" "{sys.executable}" "$@"\n')
    browser = work / "browser"  # records the URL instead of opening it
    browser.write_text(f'#!/bin/sh\necho "$1" >> "{work / "browser_urls.txt"}"\n')
    for stub in (backend, browser):
        stub.chmod(0o755)
    with mounted(chroot, (work,), host=True):
        install = in_chroot(chroot, work, "blender", "--command", "extension", "install-file", "-r", "user_default",
                            "-e", str(extension), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        output = install.communicate(timeout=300)[0]
        if install.returncode != 0:
            raise RuntimeError(f"installing {extension.name} failed:\n{output}")
        xvfb = in_chroot(chroot, work, "Xvfb", DISPLAY, "-screen", "0", SCREEN, "-nolisten", "tcp",
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 30
            while not (chroot / "tmp" / ".X11-unix" / f"X{DISPLAY[1:]}").exists():
                if time.monotonic() > deadline or xvfb.poll() is not None:
                    raise RuntimeError("Xvfb did not start")
                time.sleep(0.2)
            blender = in_chroot(chroot, work, "blender", "--factory-startup", "--enable-event-simulate",
                                "--python-exit-code", "1", *([str(blend)] if blend else []),
                                "--python", str(work / script.name), "--", str(work), str(backend), *arguments,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            try:
                console = blender.communicate(timeout=timeout)[0]
            except subprocess.TimeoutExpired:
                blender.kill()
                console = blender.communicate()[0]
        finally:
            xvfb.terminate()
            xvfb.wait(timeout=30)
            kill_processes_using(work)  # a job the session could not stop (it was killed, or timed out)
    return console


def blender_version(suite: str = "trixie") -> str:
    """'Blender 4.3.2': the first line of the chroot's ``blender --version``."""
    return (chroot_path(suite) / READY).read_text().strip()


if __name__ == "__main__":
    try:
        for name in sys.argv[1:] or SUITES:
            print(f"ready: {ensure_chroot(name)} ({blender_version(name)})")
    except RuntimeError as error:
        sys.exit(f"blender_gui: {error}")
