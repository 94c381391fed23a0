"""Every writer on a disk that fills: a real, small tmpfs (mounted in a private mount namespace, so no
root is needed where user namespaces are allowed). The old file stays whole, the new one never appears
half-written under its name, no temporary is left, and the writer raises."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

HELPER = Path(__file__).with_name("full_disk_writers.py")


def _tmpfs_runner(folder: Path) -> list[str]:
    """The command prefix that runs a command with a 1 MiB tmpfs mounted on ``folder``, or skip."""
    prefix = ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=1m tmpfs "$0" && exec "$@"', str(folder)]
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1): the tmpfs cannot be mounted (the RLIMIT_FSIZE tests still cover the writers)")
    probe = subprocess.run([*prefix, "true"], capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"a private tmpfs cannot be mounted here ({probe.stderr.strip()[:120]}); "
                    "the RLIMIT_FSIZE tests still cover the writers")
    return prefix


@pytest.mark.slow
def test_every_writer_on_a_full_tmpfs_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    prefix = _tmpfs_runner(tmp_path)
    res = subprocess.run([*prefix, sys.executable, str(HELPER), str(tmp_path)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    results = json.loads(res.stdout.strip().splitlines()[-1])
    assert len(results) == 9
    for writer, r in results.items():
        assert r["raised"], f"{writer}: wrote past a full disk without an error"
        assert r["old_kept"], f"{writer}: the old file was damaged ({r['raised']})"
        assert r["left"] == [], f"{writer}: left {r['left']}"
    # each says what went wrong (no space), in its own words
    assert "disk full while writing psp" in results["sessions"]["raised"]
    assert "could not write" in results["relit.exr"]["raised"]
    assert "cannot write" in results["manifest.json"]["raised"]
    assert "could not write the checkpoint" in results["best.pt"]["raised"] and "disk is full" in results["best.pt"]["raised"]
