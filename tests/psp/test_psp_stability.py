"""Numerical stability of PSP decoding: property-based tests and named extreme cases (issue §6)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sssphase_core.processing.patterns import PSPConfig, period_ladder, psp_key
from sssphase_core.processing.psp import Reason, decode, wrapped_phase

CFG = PSPConfig(period=10, n_shifts=4, unwrap_periods=(180, 50))
PROJ = (160, 120)


def check_invariants(corr) -> None:
    """No NaN/inf outside masked pixels; every masked pixel has a reason; invalid maps are NaN."""
    assert corr.mask.dtype == bool and corr.reason.dtype == np.uint8
    np.testing.assert_array_equal(corr.mask, corr.reason == Reason.VALID)
    assert np.isfinite(corr.xp[corr.mask]).all() and np.isfinite(corr.yp[corr.mask]).all()
    assert np.isnan(corr.xp[~corr.mask]).all() and np.isnan(corr.yp[~corr.mask]).all()
    assert (corr.reason[~corr.mask] > 0).all() and corr.reason.max() <= max(Reason)
    for extra in (corr.modulation, corr.offset, corr.modulation_ratio):
        assert np.isfinite(extra).all()


def frames_at(positions_x, positions_y, config, *, A=0.3, B=0.2, noise=0.0, rng=None):
    """Fringe frames of a (1, M) camera whose pixels see the given projector coordinates."""
    rng = rng or np.random.default_rng(0)
    out = {}
    for o, u in (("x", np.atleast_2d(positions_x)), ("y", np.atleast_2d(positions_y))):
        for p in config.periods:
            for n in range(config.n_shifts):
                img = A + B * np.cos(2 * np.pi * u / p - 2 * np.pi * n / config.n_shifts)
                out[psp_key(o, p, n)] = (img + noise * rng.standard_normal(img.shape)).astype(np.float32)
    return out


# ---------------------------------------------------------------- property-based


@settings(max_examples=150, deadline=None)
@given(
    phase=st.floats(-np.pi, np.pi),
    offset=st.floats(0.0, 10.0),
    amp_frac=st.floats(1e-3, 1.0),
    n=st.integers(3, 12),
)
def test_wrapped_phase_recovers_any_phase(phase, offset, amp_frac, n):
    amplitude = amp_frac * max(offset, 1e-2)
    stack = np.array(
        [[[offset + amplitude * np.cos(phase - 2 * np.pi * k / n)]] for k in range(n)], dtype=np.float64
    ).astype(np.float32)
    p, a, b = wrapped_phase(stack)
    assert np.isfinite(p).all() and -np.pi <= p[0, 0] <= np.pi
    tol = 1e-3 + 4e-7 * (offset + amplitude) / amplitude
    assert abs(np.angle(np.exp(1j * (p[0, 0] - phase)))) < tol
    assert abs(b[0, 0] - amplitude) < 1e-5 * (1 + offset)
    assert abs(a[0, 0] - offset) < 1e-5 * (1 + offset)


@settings(max_examples=40, deadline=None)
@given(
    period=st.integers(4, 30),
    extent=st.integers(40, 2500),
    n=st.integers(3, 8),
    data=st.data(),
)
def test_unwrapping_recovers_any_position(period, extent, n, data):
    ladder = period_ladder(period, extent)
    config = PSPConfig(period=period, n_shifts=n, unwrap_periods=ladder)
    xs = np.array(data.draw(st.lists(st.floats(-0.49, extent - 0.51), min_size=1, max_size=20)))
    ys = np.array(data.draw(st.lists(st.floats(-0.49, extent - 0.51), min_size=len(xs), max_size=len(xs))))
    corr = decode(frames_at(xs, ys, config), config, (extent, extent))
    check_invariants(corr)
    assert corr.mask.all()
    assert np.abs(corr.xp[0] - xs).max() < 2e-3 * period and np.abs(corr.yp[0] - ys).max() < 2e-3 * period


@settings(max_examples=40, deadline=None)
@given(A=st.floats(0.0, 2.0), B=st.floats(0.0, 1.0), noise=st.floats(0.0, 0.3), seed=st.integers(0, 2**16))
def test_invariants_hold_for_any_signal(A, B, noise, seed):
    rng = np.random.default_rng(seed)
    xs, ys = rng.uniform(-20, 180, 50), rng.uniform(-20, 140, 50)
    corr = decode(frames_at(xs, ys, CFG, A=A, B=B, noise=noise, rng=rng), CFG, PROJ)
    check_invariants(corr)


# ---------------------------------------------------------------- named extreme cases


def test_vanishing_modulation_is_low_modulation():
    xs = np.linspace(1, 150, 40)
    for B in (0.0, 1e-9, 1e-4, 0.004):
        corr = decode(frames_at(xs, xs / 2, CFG, A=0.5, B=B), CFG, PROJ)
        check_invariants(corr)
        assert (corr.reason == Reason.LOW_MODULATION).all()


def test_saturated_pixels_flagged_uint8_and_float():
    xs = np.linspace(1, 150, 40)
    frames = frames_at(xs, xs / 2, CFG, A=0.6, B=0.5)  # peaks at 1.1 -> clipped
    u8 = {k: np.round(np.clip(v, 0, 1) * 255).astype(np.uint8) for k, v in frames.items()}
    corr = decode(u8, CFG, PROJ)
    check_invariants(corr)
    assert (corr.reason == Reason.SATURATED).any()
    clipped = {k: np.clip(v, 0, 1) for k, v in frames.items()}
    corr = decode(clipped, CFG, PROJ, saturation=1.0)
    check_invariants(corr)
    assert (corr.reason == Reason.SATURATED).all()  # every pixel peaks above 1 in some fringe set


def test_black_and_all_zero_frames_are_shadow():
    xs = np.linspace(1, 150, 40)
    zeros = {k: np.zeros_like(v) for k, v in frames_at(xs, xs, CFG).items()}
    corr = decode(zeros, CFG, PROJ)
    check_invariants(corr)
    assert (corr.reason == Reason.SHADOW).all()
    zeros_u8 = {k: v.astype(np.uint8) for k, v in zeros.items()}
    assert (decode(zeros_u8, CFG, PROJ).reason == Reason.SHADOW).all()


def test_phase_exactly_at_plus_minus_pi():
    # positions at half periods of every level: the wrapped phase sits exactly on the branch cut
    xs = np.array([5.0, 15.0, 25.0, 95.0, 105.0, 125.0, 155.0])
    corr = decode(frames_at(xs, xs / 2, CFG, A=0.5, B=0.5), CFG, PROJ)
    check_invariants(corr)
    assert corr.mask.all()
    np.testing.assert_allclose(corr.xp[0], xs, atol=1e-3)
    np.testing.assert_allclose(corr.yp[0], xs / 2, atol=1e-3)


def test_noise_at_the_unwrapping_limit_never_gives_a_wrong_fringe_order():
    """With the phase noise of the coarse level near the tolerance, pixels are either right or flagged."""
    rng = np.random.default_rng(1)
    xs = rng.uniform(0, 159, 20000)
    # phase std ~ noise * sqrt(2/N) / B = 0.09 rad: coarse error 50 * 0.09 / 2π ≈ 0.07 fine period
    corr = decode(frames_at(xs, np.full_like(xs, 60.0), CFG, A=0.5, B=0.2, noise=0.025, rng=rng), CFG, PROJ)
    check_invariants(corr)
    assert (corr.reason == Reason.UNWRAP_INCONSISTENT).any(), "noise should reach the unwrapping limit"
    assert corr.mask.mean() > 0.9
    err = np.abs(corr.xp[0] - xs)[corr.mask[0]]
    assert err.max() < CFG.period / 2, "a wrong fringe order slipped through"


def test_float16_matches_float32():
    rng = np.random.default_rng(2)
    xs, ys = rng.uniform(0, 159, 300), rng.uniform(0, 119, 300)
    f32 = frames_at(xs, ys, CFG, A=0.4, B=0.3)
    c32 = decode(f32, CFG, PROJ)
    c16 = decode({k: v.astype(np.float16) for k, v in f32.items()}, CFG, PROJ)
    check_invariants(c16)
    np.testing.assert_array_equal(c16.mask, c32.mask)
    assert np.abs(c16.xp - c32.xp).max() < 0.05 and np.abs(c16.yp - c32.yp).max() < 0.05


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_pixels_are_flagged_not_spread(bad):
    xs = np.linspace(1, 150, 30)
    frames = frames_at(xs, xs / 2, CFG)
    frames["psp/y/p50/s1"][0, 7] = bad
    corr = decode(frames, CFG, PROJ)
    check_invariants(corr)
    assert corr.reason[0, 7] == Reason.BAD_INPUT
    assert corr.mask.sum() == 29
    p, a, b = wrapped_phase([frames[psp_key("y", 50, n)] for n in range(4)])
    assert np.isnan(p[0, 7]) and np.isfinite(np.delete(p[0], 7)).all()


def test_non_finite_rgb_channel_flags_the_pixel():
    xs = np.linspace(1, 150, 10)
    frames = {k: np.repeat(v[..., None], 3, -1) for k, v in frames_at(xs, xs / 2, CFG).items()}
    frames["psp/x/p10/s0"][0, 3, 1] = np.nan
    corr = decode(frames, CFG, PROJ)
    check_invariants(corr)
    assert corr.reason[0, 3] == Reason.BAD_INPUT and corr.mask.sum() == 9


def test_outside_projector_flagged():
    xs = np.array([-3.0, 10.0, 161.0])
    corr = decode(frames_at(xs, np.full(3, 20.0), CFG), CFG, PROJ)
    check_invariants(corr)
    np.testing.assert_array_equal(corr.reason[0], [Reason.OUTSIDE, Reason.VALID, Reason.OUTSIDE])
