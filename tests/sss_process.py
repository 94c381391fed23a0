"""Run the `sss` command as a process of its own, the way the suite runs it (:func:`run_sss`).

Each call is a new process running the installed entry module (``python -m sssphase_cli.main``) with the
given arguments, environment and folder; its exit code, stdout and stderr come back as a
:class:`subprocess.CompletedProcess`. The process is forked from a server (this file run as a script, one
per test process) that has already imported the *third-party* packages `sss` processes import (``PRELOAD``): a
fresh interpreter spends ~0.5 s of CPU on numpy, scipy, OpenCV, typer, zmq and the rest, and 2.3 s more where
torch is imported, ~300 times a run of the suite. Our own packages are imported by each process from scratch, as a
user's `sss` does. The child's ``sys.path`` is a fresh ``python -m``'s, its environment is exactly ``env``,
it exits as the interpreter does (threads joined, ``atexit`` run, streams flushed) and a signal ends it as it
ends any process.

Tests of what a fresh interpreter imports (``tests/test_cli_startup.py``) and of signals a user sends start
theirs with :mod:`subprocess`. ``SSS_TEST_FRESH_PROCESS=1`` makes every call a fresh interpreter.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

#: imported once by the server: third-party packages only (the threads numpy's, scipy's and OpenCV's libraries
#: start on import are fork-safe; matplotlib's backend is chosen later, in the child)
PRELOAD = ("numpy", "scipy.ndimage", "torch", "torch.utils.tensorboard", "cv2", "PIL.Image", "zarr", "matplotlib",
           "matplotlib.pyplot", "typer", "rich.console", "pydantic", "zmq", "pluggy")
ENTRY = "sssphase_cli.main"


# --- the server (a fresh interpreter running this file) -------------------------------------------------

#: the server's ``sys.path`` after this file's folder: a fresh ``python -m``'s after the current folder
_INTERPRETER_PATH = sys.path[1:]

def _child(request: dict) -> None:
    """In the forked child: become ``python -m sssphase_cli.main ARGS``; never returns."""
    import runpy
    import threading
    import traceback

    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    signal.set_wakeup_fd(-1)
    os.environ.clear()
    os.environ.update(request["env"])
    os.chdir(request["cwd"])
    for fd, name, flags in ((0, "stdin", os.O_RDONLY), (1, "stdout", os.O_WRONLY), (2, "stderr", os.O_WRONLY)):
        f = os.open(request[name], flags)
        os.dup2(f, fd)
        os.close(f)
    extra = [p for p in request["env"].get("PYTHONPATH", "").split(os.pathsep) if p]
    sys.path[:] = [request["cwd"], *extra, *_INTERPRETER_PATH]
    sys.argv = [ENTRY, *request["argv"]]
    code: object = 0
    try:
        runpy.run_module(ENTRY, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code
    except BaseException:  # noqa: BLE001 - reported as the interpreter reports an uncaught exception
        traceback.print_exc()
        code = 1
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    try:  # the interpreter's shutdown: non-daemon threads, then atexit, then the streams
        threading._shutdown()  # type: ignore[attr-defined]
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code & 0xFF)


def serve(path: str) -> None:
    """Preload, listen on ``path`` and fork a child per request until stdin closes (the test process ended).

    A request is one JSON line; the answer is the child's pid and, once it has exited, its return code
    (``-N`` for signal N), one JSON line each."""
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(16)
    print("ready", flush=True)
    waiting: dict[int, socket.socket] = {}
    while True:
        ready, _, _ = select.select([listener, wake_r, sys.stdin], [], [])
        if sys.stdin in ready and not os.read(sys.stdin.fileno(), 1):
            return
        if wake_r in ready:
            os.read(wake_r, 512)
            while waiting:
                pid, status = os.waitpid(-1, os.WNOHANG)
                if pid == 0:
                    break
                conn = waiting.pop(pid, None)
                if conn is not None:
                    with contextlib.suppress(OSError):  # the test process may have gone
                        conn.sendall(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}).encode() + b"\n")
                    conn.close()
        if listener in ready:
            conn, _ = listener.accept()
            request = json.loads(conn.makefile("rb").readline())
            pid = os.fork()
            if pid == 0:
                listener.close()
                conn.close()
                _child(request)
            waiting[pid] = conn
            with contextlib.suppress(OSError):
                conn.sendall(json.dumps({"pid": pid}).encode() + b"\n")


# --- the client (the test process) ----------------------------------------------------------------------

_server: tuple[subprocess.Popen, str] | None = None


def _stop_server(proc: subprocess.Popen, folder: str) -> None:
    """End the server (its stdin closes) and remove its socket's folder."""
    with contextlib.suppress(OSError, subprocess.TimeoutExpired):
        proc.stdin.close()
        proc.wait(10)
    shutil.rmtree(folder, ignore_errors=True)


def _server_path() -> str:
    """The socket of this test process's server, started on first use (without PYTHONPATH: its ``sys.path``
    after this file's folder is a fresh interpreter's, which each child is given)."""
    global _server
    if _server is None or _server[0].poll() is not None:
        path = os.path.join(tempfile.mkdtemp(prefix="sssz", dir="/tmp"), "s")  # an AF_UNIX path is short
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        proc = subprocess.Popen([sys.executable, __file__, path], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True, env=env)
        if "ready\n" not in iter(proc.stdout.readline, ""):  # (lines a preloaded package may print come first)
            raise RuntimeError(f"the sss fork server did not start (exit code {proc.wait()})")
        _server = (proc, path)
        atexit.register(_stop_server, proc, os.path.dirname(path))
    return _server[1]


class _Lines:
    """The lines a socket receives; a timeout raises and the next call goes on where it stopped."""

    def __init__(self, conn: socket.socket):
        self.conn, self.buf = conn, b""

    def next(self) -> bytes:
        while b"\n" not in self.buf:
            chunk = self.conn.recv(4096)
            if not chunk:
                raise RuntimeError("the sss fork server closed the connection")
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line


def run_sss(args: Sequence[str | os.PathLike[str]], *, env: Mapping[str, str] | None = None,
            cwd: str | os.PathLike[str] | None = None, timeout: float = 120,
            input: str | None = None) -> subprocess.CompletedProcess[str]:
    """``sss ARGS`` in a process of its own, as ``subprocess.run([python, "-m", "sssphase_cli.main", *args],
    capture_output=True, text=True, ...)`` runs it, forked from the preloaded server (module docstring)."""
    argv = [os.fspath(a) for a in args]
    env = dict(os.environ if env is None else env)
    cwd = os.path.abspath(os.fspath(cwd) if cwd is not None else os.getcwd())
    cmd = [sys.executable, "-m", ENTRY, *argv]
    if os.environ.get("SSS_TEST_FRESH_PROCESS") == "1":
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=cwd, input=input)
    with tempfile.TemporaryDirectory(prefix="sss-run-") as tmp:
        files = {name: Path(tmp) / name for name in ("stdin", "stdout", "stderr")}
        for name, path in files.items():
            path.write_text(input if name == "stdin" and input else "")
        request = {"argv": argv, "env": env, "cwd": cwd, **{n: str(p) for n, p in files.items()}}
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.connect(_server_path())
            conn.sendall(json.dumps(request).encode() + b"\n")
            answers = _Lines(conn)
            pid = json.loads(answers.next())["pid"]
            conn.settimeout(timeout)
            try:
                line = answers.next()
            except TimeoutError:
                os.kill(pid, signal.SIGKILL)
                conn.settimeout(None)
                answers.next()
                raise subprocess.TimeoutExpired(cmd, timeout, files["stdout"].read_text(),
                                                files["stderr"].read_text()) from None
        return subprocess.CompletedProcess(cmd, json.loads(line)["returncode"], files["stdout"].read_text(),
                                           files["stderr"].read_text())


if __name__ == "__main__":
    serve(sys.argv[1])
