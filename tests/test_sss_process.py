"""The suite's way of running `sss` (``tests/sss_process.py``) answers as a fresh interpreter does."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from sss_process import run_sss


def _fresh(args: list[str], **kw) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "sssphase_cli.main", *args], capture_output=True, text=True,
                          timeout=120, **kw)


@pytest.mark.parametrize("args", [
    ["--version"],
    ["capture", "--object", "apple", "--view", "2"],  # a usage error: exit 2, its message on stderr
    ["daemon", "status"],  # reads SSS_RUNTIME_DIR from the environment it is given
    ["patterns", "--projector", "64x48", "--out", "p"],  # a relative path: the folder it is given
])
def test_forked_sss_answers_as_a_fresh_interpreter(args, tmp_path):
    env = {**os.environ, "COLUMNS": "200", "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    forked = run_sss(args, env=env, cwd=tmp_path / "a")
    fresh = _fresh(args, env=env, cwd=tmp_path / "b")
    assert (forked.returncode, forked.stdout, forked.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr)
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == sorted(p.name for p in (tmp_path / "b").iterdir())


def test_a_forked_sss_past_its_timeout_is_killed(tmp_path):
    before = time.monotonic()
    with pytest.raises(subprocess.TimeoutExpired):
        run_sss(["sim", "--object", "apple", "--views", "4", "--out", str(tmp_path / "s")], timeout=1)
    assert time.monotonic() - before < 30

