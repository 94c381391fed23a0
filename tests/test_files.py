"""Atomic file replacement: the old file or the new one, never half, and no temporary left behind."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.store.files import atomic_path


def test_the_new_file_replaces_the_old_only_when_the_block_succeeds(tmp_path):
    path = tmp_path / "sub" / "state.json"
    with atomic_path(path) as tmp:
        tmp.write_text("first")
    assert path.read_text() == "first"
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_text("half writ")
        raise RuntimeError("disk full")
    assert path.read_text() == "first"
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.json"]


def test_an_error_writing_the_temporary_names_the_file_asked_for():
    """`sss eval knn --out /proc/x.json` said "/proc/.x.json.30213-78fb61.tmp: No such file or directory"."""
    from pathlib import Path

    if not Path("/proc/self").exists():
        pytest.skip("needs /proc, a folder no file can be created in whoever runs this")
    path = Path("/proc") / "sssphase-result.json"
    with pytest.raises(OSError) as err, atomic_path(path) as tmp:
        tmp.write_text("x")
    assert err.value.filename == str(path), err.value


def test_a_suffix_keeps_numpy_from_renaming_the_temporary(tmp_path):
    path = tmp_path / "cache.npz"
    with atomic_path(path, ".npz") as tmp:
        np.savez(tmp, a=np.arange(3))
    np.testing.assert_array_equal(np.load(path)["a"], np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["cache.npz"]


def test_reports_figures_and_rig_files_are_never_left_half_written(tmp_path):
    """Every report, figure and rewritten rig file goes through the one atomic writer: under a full disk (a
    file-size limit on the writing process) the old file stays whole, or there is none."""
    import subprocess
    import sys

    (tmp_path / "old.json").write_text('{"kept": true}\n')
    code = """
import resource, signal, sys
from pathlib import Path
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from sssphase_core.store.files import save_figure, write_text
from sssphase_core.store.results import write_report
out = Path(sys.argv[1])
for name, write in (("old.json", lambda p: write_text(p, "x" * 100000)),
                    ("report.json", lambda p: write_report({"rows": list(range(30000))}, [], p, md=p.with_suffix(".md"))),
                    ("figure.png", lambda p: save_figure(plt.figure(figsize=(20, 20)).add_subplot().imshow(
                        np.random.default_rng(0).random((800, 800))).figure, p))):
    try:
        write(out / name)
    except OSError as exc:
        print("refused", name, exc.errno)
"""
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert res.stdout.count("refused") == 3, res.stdout + res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]  # no report, no figure, no temporaries
    assert (tmp_path / "old.json").read_text() == '{"kept": true}\n'


def test_a_checkpoint_past_the_file_size_limit_says_so_not_to_free_disk_space(tmp_path):
    """Under `ulimit -f` a checkpoint write said torch's "unexpected pos 5085824 vs 5085716" and "free some space"
    with 54 GB free. It says the previous checkpoint is kept only where there was one."""
    import subprocess
    import sys

    code = """
import resource, sys
from pathlib import Path
import torch
from sssphase_core.errors import DataError
from sssphase_core.learning.training import save_checkpoint
out = Path(sys.argv[1])
save_checkpoint(out / "kept.pt", {"weights": torch.zeros(10)})
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
for name in ("last.pt", "kept.pt"):
    try:
        save_checkpoint(out / name, {"weights": torch.zeros(100000)})
    except DataError as exc:
        print(exc)
"""
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=120)
    why = "it outgrew the largest file this process may write (20,000 bytes: ulimit -f)"
    assert (f"could not write the checkpoint {tmp_path / 'last.pt'}: {why}; no checkpoint was written: raise the "
            "limit and run it again") in res.stdout, res.stdout + res.stderr
    assert (f"could not write the checkpoint {tmp_path / 'kept.pt'}: {why}; the previous checkpoint is kept: raise "
            "the limit and resume") in res.stdout, res.stdout + res.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["kept.pt"]
    import torch

    assert torch.load(tmp_path / "kept.pt")["weights"].shape == (10,)


def test_a_json_write_that_fails_says_a_previous_version_is_kept_only_where_there_was_one(tmp_path, monkeypatch):
    import errno
    import json

    from sssphase_core.errors import DataError
    from sssphase_core.store.session import write_json_atomic

    (tmp_path / "manifest.json").write_text('{"kept": true}')
    with monkeypatch.context() as m:
        m.setattr(json, "dump", lambda *a, **k: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device")))
        with pytest.raises(DataError, match=r"manifest.json: No space left on device \(the previous version is kept\)$"):
            write_json_atomic(tmp_path / "manifest.json", {})
    assert (tmp_path / "manifest.json").read_text() == '{"kept": true}'
    (tmp_path / "file").write_text("")
    with pytest.raises(DataError) as caught:
        write_json_atomic(tmp_path / "file" / "new.json", {})  # (its folder is a file)
    assert "cannot write" in str(caught.value) and "kept" not in str(caught.value)
