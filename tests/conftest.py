"""Shared test fixtures."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

# pytest-xdist runs a worker per core (and one more, below): each worker's torch (and the `sss` processes it
# starts) gets its share of the cores instead of all of them, so that parallel tests do not oversubscribe the
# machine.
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1:
    _share = str(max(1, (os.cpu_count() or 1) // _workers))
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_var, _share)


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker more than the cores. A third of the suite's CPU time is in the workers and the
    rest in the `sss` processes and daemons they start; while a worker waits on one (or on a timeout a test
    provokes), the extra worker keeps the cores busy (2 cores: 86% busy with 2 workers, 99% with 3; fresh-clone
    runs 838 s and 822 s)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 1


def pytest_configure(config: pytest.Config) -> None:
    """Byte-compile our packages once, before the workers start, where the environment forbids Python to write
    bytecode (``PYTHONDONTWRITEBYTECODE``, as on the build machine): otherwise each of the ~400 `sss` processes and
    daemons the suite starts compiles our modules from source again (0.2 s of CPU each, measured on
    `sss relight` refusing a missing session: 1.0 -> 0.8 s). Python reads the files it finds either way."""
    if hasattr(config, "workerinput") or not sys.dont_write_bytecode:
        return
    import compileall
    import importlib.util

    for package in ("sssphase_core", "sssphase_cli", "sssphase_daemon", "sssphase_plugins", "sssphase_view"):
        spec = importlib.util.find_spec(package)
        if spec is not None and spec.origin is not None:
            compileall.compile_dir(Path(spec.origin).parent, quiet=1)


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


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups into the node ids
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Order and group the tests for pytest-xdist.

    * Tests that use a module- or class-scoped fixture of their own module (a capture, a trained demo)
      share one worker (``xdist_group``), so the fixture is built once instead of once per worker.
    * Tests marked ``slow`` run first, then the groups (each one unit of work, its fixture and all its tests),
      then the rest, so that the long units do not start last on one worker while the others idle
      (``--no-loadscope-reorder`` in pyproject.toml keeps this order: xdist's own put every group first).
    """
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        for name in info.names_closure:
            defs = info.name2fixturedefs.get(name)
            if defs and defs[-1].scope in ("module", "class") and defs[-1].baseid not in ("", "tests"):
                item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
                break
    items.sort(key=lambda item: (item.get_closest_marker("slow") is None,  # stable: file order kept otherwise
                                 item.get_closest_marker("xdist_group") is None))



@pytest.hookimpl(trylast=True)  # after pytest-xdist's worker hook, which appends each item's group to its node id
def pytest_collection_finish(session: pytest.Session) -> None:
    """Refuse to run when ``--dist loadgroup`` cannot group (a pytest that xdist's renaming no longer reaches,
    pytest-dev/pytest-xdist#1386): every module fixture would be built on every worker, the suite running
    minutes longer in silence. constraints.txt pins a pair that groups."""
    if not (os.environ.get("PYTEST_XDIST_WORKER") and getattr(session.config.option, "loadgroup", False)):
        return
    lost = [item.nodeid for item in session.items if item.get_closest_marker("xdist_group") and "@" not in item.nodeid]
    if lost:
        raise pytest.UsageError(f"pytest {pytest.__version__} with this pytest-xdist does not group tests "
                                f"(e.g. {lost[0]} has no @group): install with -c constraints.txt")
