"""The view calibration leaves a model out where the fringes show none of its scattering: a model whose only
difference from no scattering is the captures' own noise (its energy read from them) gets weight 0, while a
model whose blur the captures do show keeps its fitted weight."""

from __future__ import annotations

import numpy as np

from sssphase_core.relight import calibration
from sssphase_core.relight.calibration import fringe_ac, fringe_noise_variance, scattering_evidence


def _fringes(h: int = 40, w: int = 50, contrast: float = 1.0) -> np.ndarray:
    """(8, H, W, 3) four-step fringes of both orientations with the given contrast, offset 0.5."""
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    out = []
    for coord in (xx, yy):
        for k in range(4):
            out.append(0.5 + 0.5 * contrast * np.cos(2 * np.pi * coord / 8 + k * np.pi / 2))
    return np.repeat(np.stack(out)[..., None], 3, axis=-1)


def test_the_fringes_own_noise_variance_is_read_from_the_four_shifts():
    clean = _fringes()
    assert np.abs(fringe_noise_variance(clean)).max() < 1e-12  # a sinusoid has none
    rng = np.random.default_rng(0)
    sigma = np.array([0.01, 0.02, 0.04])
    noisy = clean + rng.normal(size=clean.shape) * sigma
    assert np.allclose(fringe_noise_variance(noisy).mean(axis=(0, 1)), sigma**2, rtol=0.05)
    # the modulation keeps the fringes and drops each orientation's mean
    assert np.allclose(fringe_ac(clean + 0.3), clean - 0.5, atol=1e-12)


def test_a_model_that_only_repeats_the_captures_noise_shows_no_scattering_and_a_blur_does():
    rng = np.random.default_rng(1)
    none = _fringes()
    captured = none + rng.normal(size=none.shape) * 0.01
    noise = fringe_noise_variance(captured)
    # energy read from the captures themselves: none scaled by each pixel's noisy offset
    offset = captured.reshape(2, 4, *captured.shape[1:]).mean(axis=(0, 1))
    leaking = none * (offset / 0.5)[None]
    d, e = [leaking - none], captured - none
    gram, cross = float((d[0] * d[0])[..., 0].sum()), float((d[0] * e)[..., 0].sum())
    full = calibration.mixture_weights(np.array([[gram]]), np.array([cross]))
    assert full[0] > 0.3  # fitted on everything (the mean too), the noise it repeats wins it a large weight
    assert not scattering_evidence(d, e, noise).any()
    # a blur that the captures do show: fringes at 70 % contrast, and a model predicting 60 %
    blurred = _fringes(contrast=0.7) + rng.normal(size=none.shape) * 0.01
    assert scattering_evidence([_fringes(contrast=0.6) - none], blurred - none, fringe_noise_variance(blurred)).all()


def test_only_the_colours_without_evidence_are_left_out():
    rng = np.random.default_rng(2)
    none = _fringes()
    captured = none.copy()
    for c, k in enumerate((1.0, 1.0, 0.7)):  # blue scatters (its fringes lose 30 % of their contrast)
        captured[..., c] = _fringes(contrast=k)[..., c]
    captured += rng.normal(size=none.shape) * 0.01
    model = _fringes(contrast=0.75)
    assert scattering_evidence([model - none], captured - none, fringe_noise_variance(captured)).tolist() == [False, False, True]
