"""Fixtures for the learning tests: a tiny preset (same code as lite/paper) and synthetic views."""

from __future__ import annotations

import pytest
import torch
from learn_sessions import synthetic_sessions

from sssphase_core.bench.synthetic import synthetic_views
from sssphase_core.learning.data import PatchDataset
from sssphase_core.learning.models.presets import ModelPreset

TINY = ModelPreset(name="tiny", patch=16, in_channels=24, stem=8, stages=(8, 12, 16), bottleneck=32, dropout=0.2,
                   proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4,
                   scale_invariant=True)


@pytest.fixture(scope="session", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def tiny() -> ModelPreset:
    return TINY


@pytest.fixture(scope="session")
def synthetic():
    """(views, kernels): 2 objects x 2 views, 64 pixels each, 16 px patches."""
    return synthetic_views(("a", "b"), (0, 1), size=(48, 48), patch=16, pixels_per_view=64)


@pytest.fixture(scope="session")
def dataset(synthetic) -> PatchDataset:
    return PatchDataset(synthetic[0], 16, ["a", "b"], with_targets=True)


@pytest.fixture(scope="session")
def pretrained(dataset, tiny, tmp_path_factory):
    """A tiny SimSiam run (2 epochs) on the synthetic dataset."""
    from sssphase_core.learning.training import PretrainConfig, pretrain

    out = tmp_path_factory.mktemp("pre") / "run"
    pretrain(PretrainConfig(epochs=2, batch_size=16, ckpt_every=3, warmup_epochs=1), dataset, out, preset=tiny, progress=False)
    return out


@pytest.fixture
def one_and_three_sessions(synthetic):
    """``make(root, footprints=False, views_of=None)``: sessions 'one' (view 0) and 'three' (views 0, 2, 5) (or
    ``views_of``: {name: views}) made of a synthetic view (with its footprint crops when asked), under ``root``."""
    return lambda root, footprints=False, views_of=None: synthetic_sessions(root, synthetic, footprints, views_of)
