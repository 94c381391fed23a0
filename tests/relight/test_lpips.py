"""LPIPS from weights on this machine: computed when both files are there, skipped with a precise
message when not; nothing is downloaded."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.learning import lpips


@pytest.fixture
def no_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("SSS_LPIPS_DIR", raising=False)
    monkeypatch.setattr(lpips, "_MODEL", None)
    monkeypatch.setattr(lpips.importlib.util, "find_spec", lambda name: None)  # as if `lpips` were not installed


@pytest.fixture
def local_weights(tmp_path, monkeypatch):
    """Weight files of the right layout (random values: the real ones cannot be fetched here)."""
    g = torch.Generator().manual_seed(0)
    shapes = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}
    alexnet = {}
    for i, shape in shapes.items():
        alexnet[f"features.{i}.weight"] = torch.randn(shape, generator=g) * 0.05
        alexnet[f"features.{i}.bias"] = torch.zeros(shape[0])
    alexnet["classifier.1.weight"] = torch.zeros(2, 2)  # the classifier is ignored
    linear = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(lpips.CHANNELS)}
    folder = tmp_path / "lpips"
    folder.mkdir()
    torch.save(alexnet, folder / lpips.ALEXNET_FILE)
    torch.save(linear, folder / lpips.LINEAR_FILE)
    monkeypatch.setenv("SSS_LPIPS_DIR", str(folder))
    monkeypatch.setattr(lpips, "_MODEL", None)
    return folder


def test_without_weights_lpips_is_skipped_naming_each_missing_file(no_weights, tmp_path):
    from sssphase_core.relight.evaluation import lpips_note, relight_metrics

    ok, why = lpips.available()
    assert not ok and lpips.ALEXNET_FILE in why and lpips.LINEAR_FILE in why and str(tmp_path / "torch") in why
    assert lpips_note().startswith("LPIPS skipped: ") and "SSS_LPIPS_DIR" in lpips_note()
    img = np.random.default_rng(0).random((40, 48, 3)).astype(np.float32)
    assert "lpips" not in relight_metrics(img, img, np.ones((40, 48), bool))
    with pytest.raises(InputError, match="not on this machine"):
        lpips.load()


def test_with_local_weights_lpips_is_a_distance(local_weights):
    from sssphase_core.learning.evaluation import footprint_metrics
    from sssphase_core.relight.evaluation import lpips_note, relight_metrics

    rng = np.random.default_rng(1)
    a = rng.random((64, 80, 3)).astype(np.float32) * 0.5
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, None).astype(np.float32)
    mask = np.ones((64, 80), bool)
    assert lpips_note().startswith("LPIPS: AlexNet")
    same, diff = relight_metrics(a, a, mask)["lpips"], relight_metrics(b, a, mask)["lpips"]
    assert same == pytest.approx(0.0, abs=1e-7) and diff > 1e-4
    worse = relight_metrics(np.clip(a + rng.normal(0, 0.2, a.shape), 0, None).astype(np.float32), a, mask)["lpips"]
    assert worse > diff
    fps = rng.random((5, 32, 32, 3)).astype(np.float32) * 0.04
    fm = footprint_metrics(fps, fps)
    assert fm["lpips"].shape == (5,) and np.allclose(fm["lpips"], 0, atol=1e-7)


def test_a_weight_file_of_another_kind_is_one_clear_error(local_weights):
    torch.save({"something": torch.zeros(3)}, local_weights / lpips.LINEAR_FILE)
    with pytest.raises(InputError, match="not the expected files"):
        lpips.load()


def test_weight_files_that_are_not_torch_files_skip_lpips_saying_why(local_weights):
    """Text in place of the weights (torch's unpickler fails before any key is read): LPIPS is skipped with the
    reason, before any image is scored, instead of failing the evaluation after the relighting."""
    from sssphase_core.relight.evaluation import lpips_note, relight_metrics

    (local_weights / lpips.ALEXNET_FILE).write_text("garbage\n")
    with pytest.raises(InputError, match="not the expected files") as info:
        lpips.load()
    assert "\n" not in str(info.value)
    ok, why = lpips.available()
    assert not ok and "not the expected files" in why and lpips.ALEXNET_FILE in why
    assert lpips_note().startswith("LPIPS skipped: ")
    img = np.random.default_rng(0).random((40, 48, 3)).astype(np.float32)
    assert "lpips" not in relight_metrics(img, img, np.ones((40, 48), bool))
