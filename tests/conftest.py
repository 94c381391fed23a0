"""Shared test fixtures."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest


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
