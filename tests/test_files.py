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


def test_a_suffix_keeps_numpy_from_renaming_the_temporary(tmp_path):
    path = tmp_path / "cache.npz"
    with atomic_path(path, ".npz") as tmp:
        np.savez(tmp, a=np.arange(3))
    np.testing.assert_array_equal(np.load(path)["a"], np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["cache.npz"]
