"""Shared test fixtures."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def _private_log_dir():
    """Daemons started by tests (and their subprocesses) log into a temporary folder, not the user's state dir."""
    logs = Path(tempfile.mkdtemp(prefix="sss-logs-"))
    old = os.environ.get("SSS_LOG_DIR")
    os.environ["SSS_LOG_DIR"] = str(logs)
    yield logs
    if old is None:
        os.environ.pop("SSS_LOG_DIR", None)
    else:
        os.environ["SSS_LOG_DIR"] = old
    shutil.rmtree(logs, ignore_errors=True)


@pytest.fixture(scope="session")
def sim_daemon():
    """A client of a sim-rig daemon of our own (private runtime folder), as `sss capture` and `sss demo`
    start one when none runs; stopped at the end of the session."""
    from sssphase_daemon.client import local_client

    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))  # ipc paths must stay short
    old = os.environ.get("SSS_RUNTIME_DIR")
    os.environ["SSS_RUNTIME_DIR"] = str(runtime)
    try:
        with local_client() as client:
            yield client
    finally:
        if old is None:
            os.environ.pop("SSS_RUNTIME_DIR", None)
        else:
            os.environ["SSS_RUNTIME_DIR"] = old
        shutil.rmtree(runtime, ignore_errors=True)
