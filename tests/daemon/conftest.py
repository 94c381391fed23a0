"""Fixtures for the acquisition tests: a real daemon process in a private runtime dir."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from sss_process import run_sss as run_sss_process

from sssphase_daemon import security
from sssphase_daemon.client import DaemonClient, spawn_daemon

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def runtime_dir():
    """A short private runtime dir (ipc paths are limited to ~100 characters)."""
    path = Path(tempfile.mkdtemp(prefix="sssd", dir="/tmp"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SSS_RUNTIME_DIR", str(path))
        yield path
    shutil.rmtree(path, ignore_errors=True)


def start_daemon(*args: str) -> tuple[subprocess.Popen, DaemonClient]:
    proc = spawn_daemon(extra_args=("--client-timeout", "4", "--max-message-bytes", str(2**20), *args))
    state = security.read_state()
    return proc, DaemonClient(state.endpoint, state.token, timeout_s=5.0, heartbeat_s=0.3)


def stop_daemon(proc: subprocess.Popen, client: DaemonClient) -> None:
    if proc.poll() is None:
        try:
            client.call("shutdown", timeout_s=2.0)
        except Exception:
            proc.kill()
        proc.wait(10)
    client.close()


@pytest.fixture(scope="module")
def daemon(runtime_dir):
    """A daemon process (client timeout 4 s, 1 MiB message limit) and a client for it, in a runtime dir of
    its own that the module's `sss` commands find (SSS_RUNTIME_DIR while the module runs): another
    session fixture's daemon (``sim_daemon``) or one a capture started must not be serving there."""
    path = Path(tempfile.mkdtemp(prefix="sssm", dir="/tmp"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SSS_RUNTIME_DIR", str(path))
        proc, client = start_daemon()
        try:
            yield proc, client
        finally:
            stop_daemon(proc, client)
            shutil.rmtree(path, ignore_errors=True)


def run_sss(*args: str, env: dict[str, str] | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run the `sss` CLI in a process of its own (``tests/sss_process.py``), capturing its output."""
    return run_sss_process(args, env={**os.environ, **(env or {})}, cwd=REPO, timeout=timeout)


def _own_runtime_daemon(*args: str) -> tuple[subprocess.Popen, DaemonClient, Path]:
    """A daemon in a runtime dir of its own (two daemons must not share one)."""
    path = Path(tempfile.mkdtemp(prefix="sssf", dir="/tmp"))
    old = os.environ["SSS_RUNTIME_DIR"]
    os.environ["SSS_RUNTIME_DIR"] = str(path)
    try:
        proc, client = start_daemon(*(a.replace("{runtime}", str(path)) for a in args))
    finally:
        os.environ["SSS_RUNTIME_DIR"] = old
    return proc, client, path


@pytest.fixture
def fresh_daemon(runtime_dir):
    """A daemon of its own for tests that kill or stop it: (process, client, its runtime dir)."""
    proc, client, path = _own_runtime_daemon()
    yield proc, client, path
    stop_daemon(proc, client)
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def sss():
    return run_sss


@pytest.fixture
def daemon_factory(runtime_dir):
    """Start daemons on demand (each stopped at teardown)."""
    started: list[tuple[subprocess.Popen, DaemonClient, Path]] = []

    def start(*args: str) -> tuple[subprocess.Popen, DaemonClient, Path]:
        """Extra daemon arguments may use ``{runtime}`` for the daemon's runtime dir."""
        started.append(_own_runtime_daemon(*args))
        return started[-1]

    yield start
    for proc, client, path in started:
        stop_daemon(proc, client)
        shutil.rmtree(path, ignore_errors=True)
