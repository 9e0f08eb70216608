"""A warm interpreter for the tests' ``python -m nerf_backend ...`` processes.

A backend command started cold spends 1.3-1.9 s of a 2-core machine importing torch before it does
anything, and the default suite starts about 140 of them. Here one server process per pytest
worker imports torch and numpy once (no code of this project: each command imports that itself,
as a cold process would), then forks: each command is still its own process, with its own pid,
exit status, stdout and stderr pipes, working folder and environment, run by ``runpy`` exactly as
``python -m`` runs it, and it ends through Python's normal exit (threads joined, atexit run).

The server never runs a torch operation, so the fork copies no OpenMP thread pool: each child
starts its own. What a fork cannot change is read here: a command whose environment differs from
the server's in a variable read at start-up (``READ_AT_START_PREFIXES``) runs cold.
In conftest's ``run_python``, ``NERF_TESTS_COLD=1`` runs every command cold (to compare), and
``NERF_TESTS_PROCESS_LOG=FILE`` appends a line a command saying how it ran.

The protocol, one Unix-socket connection a command: the client sends a JSON request (module,
arguments, folder, environment) with its stdin, stdout and stderr as passed file descriptors; the
server answers the child's pid, then its exit status (``subprocess``'s convention: -N for a
signal)."""

from __future__ import annotations

import json
import locale
import os
import runpy
import selectors
import signal
import socket
import subprocess
import sys
import time
import types
from pathlib import Path

# What each command would otherwise import cold, and nothing of this project.
PRELOADED = ("torch", "numpy")
# Modules run warm; anything else (``-c``, scripts, datasets_gen with bpy's own threads) runs cold.
WARM_MODULES = ("nerf_backend",)
# Environment variables read when the interpreter or a library starts (Python's own, the dynamic
# loader's, the locale, OpenMP's and the math libraries', torch's): a fork cannot change them.
# TORCH_HOME is read when a download is asked for. Any other variable (NERF_*, PYTEST_CURRENT_TEST,
# the MaterialX paths that importing bpy in a test's own process sets) is read while it runs.
READ_AT_START_PREFIXES = ("PYTHON", "LD_", "LC_", "LANG", "OMP_", "GOMP_", "KMP_", "MKL_", "OPENBLAS_", "MALLOC_",
                          "ATEN_", "ONEDNN_", "DNNL_", "TORCH_", "CUDA_", "NPY_")
READ_WHILE_RUNNING = frozenset({"TORCH_HOME"})
START_TIMEOUT_S = 120


def _variables_read_at_start(env: dict[str, str]) -> dict[str, str]:
    return {key: value for key, value in env.items()
            if key.startswith(READ_AT_START_PREFIXES) and key not in READ_WHILE_RUNNING}


def _send_message(connection: socket.socket, message: dict, fds: list[int] | None = None) -> None:
    payload = json.dumps(message).encode() + b"\n"
    if fds:
        socket.send_fds(connection, [payload], fds)
    else:
        connection.sendall(payload)


def _receive_line(connection: socket.socket, buffer: bytearray) -> dict:
    while b"\n" not in buffer:
        chunk = connection.recv(65536)
        if not chunk:
            raise ConnectionError("the warm interpreter closed the connection")
        buffer += chunk
    line, _, rest = bytes(buffer).partition(b"\n")
    buffer[:] = rest
    return json.loads(line)


# ---------------------------------------------------------------------------------------------
# The server (run as ``python tests/warm_python.py SOCKET_PATH``)
# ---------------------------------------------------------------------------------------------

def _receive_request(connection: socket.socket) -> tuple[dict, list[int]]:
    buffer = bytearray()
    fds: list[int] = []
    while b"\n" not in buffer:
        chunk, received_fds, _, _ = socket.recv_fds(connection, 1 << 20, 3)
        if not chunk:
            raise ConnectionError("the client closed the connection")
        buffer += chunk
        fds += received_fds
    return json.loads(bytes(buffer).partition(b"\n")[0]), fds


def serve(socket_path: str) -> dict:
    """Answer requests until the parent (the pytest worker) is gone; returns only in a forked
    child, with the request that child is to run."""
    parent = os.getppid()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(socket_path)
    listener.listen(8)
    listener.settimeout(1.0)
    print("ready", flush=True)
    while os.getppid() == parent:
        try:
            connection, _ = listener.accept()
        except TimeoutError:
            continue
        connection.settimeout(None)
        with connection:
            try:
                request, fds = _receive_request(connection)
            except (ConnectionError, ValueError):
                continue
            pid = os.fork()
            if pid == 0:
                listener.close()
                connection.close()
                for target, fd in enumerate(fds):
                    os.dup2(fd, target)
                    os.close(fd)
                return request
            for fd in fds:
                os.close(fd)
            try:
                _send_message(connection, {"pid": pid})
            except OSError:
                pass
            _, status = os.waitpid(pid, 0)
            try:
                _send_message(connection, {"returncode": os.waitstatus_to_exitcode(status)})
            except OSError:
                pass
    listener.close()
    sys.exit(0)


def run_request(request: dict) -> None:
    """In the forked child: become ``python -m MODULE ARGS`` in the request's folder and
    environment, by runpy's own ``-m`` entry. Descriptors 0-2 are already the client's, so the
    inherited sys.stdin/stdout/stderr (flushed, empty) write to them; SystemExit and uncaught
    exceptions reach the interpreter as in a cold process."""
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    # `python -m` puts the working folder first on the path, and runs the module in a fresh __main__.
    sys.path[0] = os.getcwd()
    sys.modules["__main__"] = types.ModuleType("__main__")
    sys.argv = [request["module"], *request["args"]]
    runpy._run_module_as_main(request["module"], alter_argv=True)


# ---------------------------------------------------------------------------------------------
# The client
# ---------------------------------------------------------------------------------------------

class WarmInterpreter:
    """One server for this process, started on first use and stopped with the process."""

    def __init__(self, root: Path, python: str = sys.executable, modules: tuple[str, ...] = WARM_MODULES):
        self.root = root
        self.python = python
        self.modules = modules
        self.process: subprocess.Popen | None = None
        self.socket_path = ""
        # The environment the server starts in: this process's when it was made (before any test
        # changed it), so a test's monkeypatching does not make every later command run cold.
        self.start_environment = dict(os.environ)

    def _start(self) -> None:
        self.socket_path = f"/tmp/nerf-warm-{os.getpid()}-{time.monotonic_ns()}.sock"
        self.process = subprocess.Popen([self.python, str(Path(__file__).resolve()), self.socket_path],
                                        cwd=self.root, env=self.start_environment, stdin=subprocess.DEVNULL,
                                        stdout=subprocess.PIPE, text=True)
        if self.process.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the warm interpreter did not start (exit {self.process.wait(START_TIMEOUT_S)})")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        if self.socket_path:
            Path(self.socket_path).unlink(missing_ok=True)
        self.process = None

    def can_run(self, args: tuple[str, ...], env: dict[str, str]) -> bool:
        if len(args) < 2 or args[0] != "-m" or args[1] not in self.modules:
            return False
        return _variables_read_at_start(env) == _variables_read_at_start(self.start_environment)

    def run(self, args: tuple[str, ...], cwd: Path, env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
        """``subprocess.run([python, *args], capture_output=True, text=True)``, forked warm."""
        if self.process is None or self.process.poll() is not None:
            self._start()
        out_read, out_write = os.pipe()
        err_read, err_write = os.pipe()
        connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            connection.connect(self.socket_path)
            request = {"module": args[1], "args": list(args[2:]), "cwd": str(cwd), "env": env}
            _send_message(connection, request, [0, out_write, err_write])
        finally:
            os.close(out_write)
            os.close(err_write)
        buffer = bytearray()
        pid = _receive_line(connection, buffer)["pid"]
        deadline = time.monotonic() + timeout
        captured = {out_read: bytearray(), err_read: bytearray()}
        with selectors.DefaultSelector() as selector:
            for fd in captured:
                selector.register(fd, selectors.EVENT_READ)
            while selector.get_map():
                left = deadline - time.monotonic()
                if left <= 0:
                    os.kill(pid, signal.SIGKILL)
                    _receive_line(connection, buffer)
                    for fd in captured:
                        os.close(fd)
                    connection.close()
                    raise subprocess.TimeoutExpired([self.python, *args], timeout,
                                                    bytes(captured[out_read]), bytes(captured[err_read]))
                for key, _ in selector.select(min(left, 1.0)):
                    chunk = os.read(key.fd, 65536)
                    if chunk:
                        captured[key.fd] += chunk
                    else:
                        selector.unregister(key.fd)
                        os.close(key.fd)
        returncode = _receive_line(connection, buffer)["returncode"]
        connection.close()
        return subprocess.CompletedProcess([self.python, *args], returncode, _as_text(captured[out_read]),
                                           _as_text(captured[err_read]))


def _as_text(data: bytes) -> str:
    """What ``subprocess.run(text=True)`` makes of a stream: the locale's encoding, strict, and
    universal newlines (a progress bar's carriage returns become line ends)."""
    return data.decode(locale.getpreferredencoding(False)).replace("\r\n", "\n").replace("\r", "\n")


if __name__ == "__main__":
    for name in PRELOADED:
        __import__(name)
    # This file's folder (tests/) is not a folder a cold `python -m` would search.
    sys.path[0] = ""
    run_request(serve(sys.argv[1]))
