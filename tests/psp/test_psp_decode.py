"""PSP decoding: wrapped phase, unwrapping and correspondences on synthetic fringes."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import PSPConfig, capture_plan, psp_config_for
from sssphase_core.processing.psp import Reason, decode, modulation_ratio, wrapped_phase

CFG = PSPConfig(period=10, n_shifts=4, unwrap_periods=(180, 50))
PHASE_TOL = 3e-4  # documented arctangent accuracy (cv2.phase: 1.7e-4 rad) plus float32 rounding
PROJ = (160, 120)


def _angle_diff(a, b):
    return np.angle(np.exp(1j * (a - b)))


@pytest.mark.parametrize("n", [3, 4, 5, 7])
def test_wrapped_phase_offset_and_modulation_exact(n):
    rng = np.random.default_rng(n)
    phi = rng.uniform(-np.pi, np.pi, (20, 30))
    A, B = rng.uniform(0.2, 0.6, phi.shape), rng.uniform(0.01, 0.2, phi.shape)
    stack = np.stack([A + B * np.cos(phi - 2 * np.pi * k / n) for k in range(n)]).astype(np.float32)
    p, a, b = wrapped_phase(stack)
    assert p.dtype == np.float32 and p.shape == phi.shape
    assert np.abs(_angle_diff(p, phi)).max() < PHASE_TOL
    np.testing.assert_allclose(a, A, atol=1e-6)
    np.testing.assert_allclose(b, B, atol=1e-6)
    assert np.all((p >= -np.pi) & (p <= np.pi))


def test_wrapped_phase_rgb_is_per_channel():
    phi = np.linspace(-3, 3, 12).reshape(3, 4)
    gains = np.array([1.0, 0.5, 0.2])
    stack = np.stack([(0.4 + 0.3 * np.cos(phi - np.pi * k / 2))[..., None] * gains for k in range(4)])
    p, a, b = wrapped_phase(stack.astype(np.float32))
    assert p.shape == (3, 4, 3)
    for c in range(3):
        assert np.abs(_angle_diff(p[..., c], phi)).max() < PHASE_TOL
    np.testing.assert_allclose(b / a, np.full((3, 4, 3), 0.75), rtol=1e-5)
    np.testing.assert_allclose(modulation_ratio(a, b), b / a, rtol=1e-6)


def test_decode_recovers_affine_correspondence(fringes, camera_map):
    xp, yp = camera_map((90, 130))
    frames = fringes(CFG, xp, yp, blur=1.5, noise=0.002)
    corr = decode(frames, CFG, PROJ)
    inside = (xp >= -0.5) & (xp < PROJ[0] - 0.5) & (yp >= -0.5) & (yp < PROJ[1] - 0.5)
    interior = inside.copy()
    interior[:4], interior[-4:], interior[:, :4], interior[:, -4:] = False, False, False, False
    assert corr.mask[interior].all()
    err = np.hypot(corr.xp - xp, corr.yp - yp)
    assert np.median(err[corr.mask]) < 0.05 and err[interior].max() < 0.2  # the blur biases the image border
    assert (corr.reason[~inside] == Reason.OUTSIDE).all()
    assert corr.modulation_ratio.shape == (90, 130, 1)


def test_decode_rgb_returns_per_channel_contrast(fringes, camera_map):
    xp, yp = camera_map((40, 50))
    gains = (0.9, 0.6, 0.3)
    frames = fringes(CFG, xp, yp, offset=0.4, amplitude=0.2, channels=gains)
    corr = decode(frames, CFG, PROJ)
    assert corr.mask.all()
    np.testing.assert_allclose(corr.modulation_ratio, 0.5, atol=1e-4)
    np.testing.assert_allclose(corr.offset, 0.4 * np.mean(gains), rtol=1e-4)
    np.testing.assert_allclose(corr.modulation, 0.2 * np.mean(gains), rtol=1e-3)


def test_decode_round_trip_through_rendered_patterns_with_gamma():
    """Camera = projector, emitted light = pattern**gamma: decode must give each pixel its own coordinate."""
    w, h, gamma = 96, 64, 2.2
    cfg = psp_config_for(w, h)
    plan = capture_plan(w, h, psp=cfg, gamma=gamma)
    frames = {f.key: (0.05 + 0.9 * f.pattern() ** gamma).astype(np.float32) for f in plan}
    corr = decode(frames, cfg, (w, h))
    yy, xx = np.mgrid[:h, :w]
    assert corr.mask.all()
    assert np.abs(corr.xp - xx).max() < 1e-3 and np.abs(corr.yp - yy).max() < 1e-3


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float16, np.float32])
def test_decode_accepts_integer_and_half_inputs(fringes, camera_map, dtype):
    xp, yp = camera_map((30, 40))
    frames = fringes(CFG, xp, yp, offset=0.45, amplitude=0.4)
    if np.issubdtype(dtype, np.integer):
        top = np.iinfo(dtype).max
        frames = {k: np.round(v * top).astype(dtype) for k, v in frames.items()}
    else:
        frames = {k: v.astype(dtype) for k, v in frames.items()}
    corr = decode(frames, CFG, PROJ)
    assert corr.mask.all()
    tol = 0.1 if dtype == np.uint8 else 0.02
    assert np.abs(corr.xp - xp).max() < tol and np.abs(corr.yp - yp).max() < tol
    np.testing.assert_allclose(corr.offset, 0.45, atol=0.01)


def test_decode_independent_of_block_size(fringes, camera_map):
    xp, yp = camera_map((37, 41))
    frames = fringes(CFG, xp, yp, noise=0.01)
    a = decode(frames, CFG, PROJ, block_rows=5)
    b = decode(frames, CFG, PROJ)
    np.testing.assert_array_equal(a.reason, b.reason)
    np.testing.assert_allclose(a.xp, b.xp, atol=1e-5)


def test_decode_reports_missing_frames_and_short_ladder(fringes, camera_map):
    xp, yp = camera_map((10, 10))
    frames = fringes(CFG, xp, yp)
    del frames["psp/y/p50/s2"]
    with pytest.raises(InputError, match="psp/y/p50/s2"):
        decode(frames, CFG, PROJ)
    short = PSPConfig(period=10, unwrap_periods=(50,))
    with pytest.raises(InputError, match="coarsest period"):
        decode(fringes(short, xp, yp), short, PROJ)


def test_coverage_counts_every_pixel(fringes, camera_map):
    xp, yp = camera_map((20, 20))
    corr = decode(fringes(CFG, xp, yp), CFG, PROJ)
    assert sum(corr.coverage().values()) == 400


@pytest.mark.parametrize("demosaic", ["malvar", "opencv"])
def test_demosaic_bleed_finds_background_pixels_that_only_borrowed_fringes(demosaic):
    """A bright disk's fringes on black, through a Bayer camera: background pixels beside the disk show the
    fringes in the colours demosaicing filled in, while their own sample stays dark. Those, and no disk
    pixel, are flagged; a colour an object lacks is not bleed in its interior."""
    from sssphase_core.processing.isp import through_camera
    from sssphase_core.processing.psp import demosaic_bleed

    h, w = 64, 80
    yy, xx = np.mgrid[:h, :w]
    disk = np.hypot(yy - 31.3, xx - 40.6) < 18
    colour = np.array([0.8, 0.45, 0.3], np.float32)
    sets = []
    for coord in (xx, yy):
        shifts = [0.5 + 0.45 * np.cos(2 * np.pi * coord / 9.0 - np.pi * k / 2) for k in range(4)]
        scene = np.stack([np.where(disk, s, 0.0)[..., None] * colour for s in shifts]).astype(np.float32)
        sets.append(through_camera(scene, demosaic=demosaic))
    seen = np.abs(sets[0][0] - sets[0][2]).max(axis=-1) > 0.01  # what a decoder would take as surface
    assert (seen & ~disk).sum() > 20  # demosaicing spread the fringes beyond the disk
    flagged = demosaic_bleed(seen, sets)
    assert not (flagged & disk).any()
    assert flagged.sum() >= 0.9 * (seen & ~disk).sum()
    # an object without blue: its interior blue sites show no fringes of their own and are kept
    red = [np.where(disk[None, ..., None], s * np.array([1.0, 0.5, 0.0], np.float32) / colour, 0) for s in sets]
    assert not demosaic_bleed(disk, red)[np.hypot(yy - 31.3, xx - 40.6) < 16].any()
