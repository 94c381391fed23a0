"""Usage errors of the `sss` command: a short message and exit code 2, never a traceback.

Run as a user runs it (a separate process through the installed entry module), so that the error
path itself is exercised with exactly the packages the install declares.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _sss(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "SSS_DEBUG"}
    env["COLUMNS"] = "200"
    return subprocess.run([sys.executable, "-m", "sssphase_cli.main", *args], capture_output=True, text=True,
                          timeout=120, env=env)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["capture", "--object", "apple", "--view", "2"], "No such option"),
        (["relight", "some_session"], "--pattern"),
        (["capture", "--object", "apple", "--views", "two"], "--views"),
        (["--version"], "No such option"),
        (["sim", "--object", "apple", "--views", "-"], "--views"),
    ],
)
def test_usage_errors_are_one_message_not_a_traceback(args: list[str], expected: str) -> None:
    res = _sss(*args)
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out and "ModuleNotFoundError" not in out, out
    assert expected in out
    assert len(out.strip().splitlines()) <= 12, out


def test_bare_group_prints_help_and_exits_cleanly() -> None:
    res = _sss("train")
    out = res.stdout + res.stderr
    assert "Traceback" not in out, out
    assert "pretrain" in out and "decoder" in out
    assert res.returncode in (0, 2)


def test_user_errors_keep_square_brackets() -> None:
    """Rich markup must not eat text such as ``pip install sssphase[depthai]`` from an error message."""
    res = _sss("relight", "no/such/session[depthai]", "--pattern", "checker.png")
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out
    assert "no/such/session[depthai]" in out, out
