"""Shared test fixtures."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def _private_log_dir():
    """Daemons started by tests (and their subprocesses) log into a temporary folder, not the user's state dir."""
    logs = Path(tempfile.mkdtemp(prefix="sss-logs-"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SSS_LOG_DIR", str(logs))
        yield logs
    shutil.rmtree(logs, ignore_errors=True)


@pytest.fixture(scope="session")
def sim_daemon():
    """A client of a sim-rig daemon of our own (private runtime folder), as `sss capture` and `sss demo`
    start one when none runs; stopped at the end of the session."""
    from sssphase_daemon.client import local_client

    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))  # ipc paths must stay short
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("SSS_RUNTIME_DIR", str(runtime))
            with local_client() as client:
                yield client
    finally:
        shutil.rmtree(runtime, ignore_errors=True)
