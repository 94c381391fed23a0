"""Repairing clipped fringes (`psp.declip`) and taking a footprint's energy from the white capture
where they cannot be repaired (`relight.energy_from_white`), on fringes written by hand."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.processing.psp import declip
from sssphase_core.relight import energy_from_white, white_usable
from sssphase_core.store.session import clip_levels

SHIFTS = np.arange(4) * np.pi / 2


def fringes(a: np.ndarray, b: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(8, H, W, 3) paper inputs: x shifts then y shifts, I_n = A + B cos(phi - n pi / 2) (phi shifted by
    0.7 rad for y)."""
    x = a[None] + b[None] * np.cos(phi[None] - SHIFTS[:, None, None, None])
    y = a[None] + b[None] * np.cos(phi[None] + 0.7 - SHIFTS[:, None, None, None])
    return np.concatenate([x, y]).astype(np.float32)


@pytest.fixture
def scene():
    rng = np.random.default_rng(3)
    shape = (24, 32, 3)
    a = rng.uniform(0.05, 0.6, shape)
    b = a * rng.uniform(0.1, 0.95, shape)
    phi = rng.uniform(-np.pi, np.pi, shape)
    return a, b, phi


def test_clipped_samples_come_back_exactly_where_the_physics_allows(scene):
    a, b, phi = scene
    true = fringes(a, b, phi)
    level = 0.5
    clipped = np.minimum(true, level)
    fixed, lost = declip(clipped, level / 0.95, white=2 * a, margin=0.95)  # black 0: A = white / 2
    any_clip = (true >= level).any(axis=(0, -1))
    assert any_clip.mean() > 0.3 and lost.any() and (~lost & any_clip).any()
    # A pair clipped on both samples means A >= level: its modulation is gone, and the pixel is reported.
    both = np.zeros(lost.shape, bool)
    for o in (0, 4):
        c = true[o:o + 4] >= level
        both |= ((c[0] & c[2]) | (c[1] & c[3])).any(axis=-1)
    np.testing.assert_array_equal(lost, both)
    np.testing.assert_allclose(fixed[:, ~lost], true[:, ~lost], atol=1e-5)
    assert np.abs(fixed[:, lost] - true[:, lost]).max() > 0.01  # not silently "repaired"


def test_without_a_white_capture_the_unclipped_pair_gives_the_offset(scene):
    a, b, phi = scene
    true = fringes(a, b, phi)
    level = 0.5
    fixed, lost = declip(np.minimum(true, level), level / 0.95, margin=0.95)
    one_pair = np.ones(lost.shape, bool)  # every orientation and colour has an unclipped pair and no pair clipped twice
    for o in (0, 4):
        c = true[o:o + 4] >= level
        n = c[:2].astype(int) + c[2:]
        one_pair &= ((n == 0).any(axis=0) & (n < 2).all(axis=0)).all(axis=-1)
    assert one_pair.any() and lost[one_pair].sum() == 0
    np.testing.assert_allclose(fixed[:, one_pair], true[:, one_pair], atol=1e-5)
    assert lost[~one_pair & (true >= level).any(axis=(0, -1))].all()  # one clipped in each pair, no white


def test_a_clipped_white_is_not_used_and_unclipped_frames_are_untouched(scene):
    a, b, phi = scene
    true = fringes(a, b, phi)
    fixed, lost = declip(true, 10.0)
    np.testing.assert_array_equal(fixed, true)
    assert not lost.any()
    level = 0.5
    _, with_white = declip(np.minimum(true, level), level / 0.95, white=2 * a, margin=0.95)
    _, clipped_white = declip(np.minimum(true, level), level / 0.95, white=2 * a, white_saturation=0.3, margin=0.95)
    assert with_white.sum() < clipped_white.sum()
    np.testing.assert_array_equal(white_usable(2 * a, 0.3), (2 * a < 0.95 * 0.3).all(axis=-1))


def test_bad_stacks_are_refused_in_one_line():
    with pytest.raises(InputError, match=r"\(8, H, W, 3\)"):
        declip(np.zeros((4, 5, 5, 3), np.float32), 1.0)
    with pytest.raises(InputError, match="saturation"):
        declip(np.zeros((8, 5, 5, 3), np.float32), 0.0)


@pytest.mark.parametrize("as_tensor", [False, True])
def test_energy_from_white_rescales_only_the_chosen_pixels(as_tensor):
    """NumPy footprints, or a model's tensors (which stay tensors: on a GPU they stay on it)."""
    import torch

    white = np.full((6, 6, 3), 0.4, np.float32)
    white[..., 2] = 0.1
    fp = np.zeros((1, 5, 5, 3), np.float32)
    fp[0, 1:4, 1:4] = 0.01  # energy 0.09 per colour

    def source(px):
        out = np.repeat(fp, len(px), axis=0)
        return torch.from_numpy(out) if as_tensor else out

    where = np.zeros((6, 6), bool)
    where[2, 3] = True
    out = energy_from_white(source, where, white)(np.array([[2, 3], [1, 1]]))
    assert torch.is_tensor(out) == as_tensor
    out = np.asarray(out)
    np.testing.assert_allclose(out[0].sum(axis=(0, 1)), [0.4, 0.4, 0.1], rtol=1e-5)
    np.testing.assert_allclose(out[0] / out[0].max(axis=(0, 1)), fp[0] / fp[0].max(axis=(0, 1)), rtol=1e-5)  # same shape
    np.testing.assert_array_equal(out[1], fp[0])


@pytest.mark.parametrize("as_tensor", [False, True])
def test_a_model_mixed_with_no_scattering_is_the_weighted_sum_per_colour(as_tensor):
    """``mix * model + (1 - mix) * delta * white``, for NumPy footprints and for a model's tensors alike."""
    import torch

    from sssphase_core.relight.calibration import mixed_with_no_scattering

    white = np.random.default_rng(0).uniform(0.1, 0.9, (6, 6, 3)).astype(np.float32)
    white[0, 0, 1] = np.nan  # a lost white value adds no light
    fp = np.random.default_rng(1).uniform(0, 0.01, (2, 5, 5, 3)).astype(np.float32)
    px = np.array([[2, 3], [0, 0]])
    mix = np.array([1.0, 0.25, 0.0], np.float32)
    kept = fp.copy()
    out = mixed_with_no_scattering(lambda p: torch.from_numpy(fp.copy()) if as_tensor else fp, mix, white)(px)
    assert torch.is_tensor(out) == as_tensor
    want = fp * mix
    want[:, 2, 2] += (1 - mix) * np.nan_to_num(white[px[:, 0], px[:, 1]])
    np.testing.assert_allclose(np.asarray(out), want, rtol=1e-6)
    np.testing.assert_array_equal(fp, kept)  # a source's own array (a cache's) is not changed


def test_clip_levels_follow_the_exposures_of_the_plan():
    frames = [{"kind": "psp", "exposure": 1.0}, {"kind": "psp", "exposure": 4.0}, {"kind": "white", "exposure": 2.0}]
    assert clip_levels(frames, 1.6) == (1.6, 0.8)  # HDR brackets clip where the shortest exposure did
    assert clip_levels(frames, None) == (None, None)
    assert clip_levels([{"kind": "psp"}], 1.0) == (1.0, None)


def test_training_reads_the_same_repaired_fringes_as_relighting(scene):
    from sssphase_core.learning.data import repaired_psp

    a, b, phi = scene
    true = fringes(a, b, phi)

    class ClippedSession:  # what session_views reads: arrays by name and where the session clips
        def __init__(self, level, black=0.0):
            self.level, self.black = level, black

        def load(self, view, name):
            return {"psp": np.minimum(true, 0.5), "white": 2 * a}[name]

        def clip_levels(self):
            return self.level, None

        def projector_black(self, view, white=None, mask=None):
            return self.black

    fixed, lost = declip(np.minimum(true, 0.5), 0.5 / 0.95, white=2 * a, margin=0.95)
    np.testing.assert_array_equal(repaired_psp(ClippedSession(0.5 / 0.95), 0), fixed)
    np.testing.assert_array_equal(repaired_psp(ClippedSession(None), 0), np.minimum(true, 0.5))  # level unknown: as stored
    # the view's projector black level enters the repair as it does for relighting (A from the white)
    dark, _ = declip(np.minimum(true, 0.5), 0.5 / 0.95, white=2 * a, margin=0.95, black=0.1)
    np.testing.assert_array_equal(repaired_psp(ClippedSession(0.5 / 0.95, black=0.1), 0), dark)
