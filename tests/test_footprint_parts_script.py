"""The footprint-parts diagnostic (benchmarks/footprint_parts.py): energy, ring profile and angular detail swapped
between footprints keep what they say they keep."""

import numpy as np
from benchmark_script import load_benchmark

script = load_benchmark("footprint_parts")


def footprints(seed: int, n: int = 5, k: int = 9) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, (n, k, k, 3)).astype(np.float64)


def ring_index(k: int) -> np.ndarray:
    off = np.arange(k) - k // 2
    return np.rint(np.hypot(off[:, None], off[None, :])).astype(np.int64)


def ring_sums(fp: np.ndarray) -> np.ndarray:
    rings = ring_index(fp.shape[1])
    return np.stack([fp[:, rings == r].sum(axis=1) for r in range(int(rings.max()) + 1)], axis=1)


def test_ring_average_keeps_each_rings_light_and_drops_the_angle():
    fp = footprints(0)
    flat = script.ring_average(fp)
    np.testing.assert_allclose(ring_sums(flat), ring_sums(fp), rtol=1e-5)
    rings = ring_index(fp.shape[1])
    for r in range(int(rings.max()) + 1):
        assert np.ptp(flat[:, rings == r], axis=1).max() < 1e-5


def test_energy_and_profile_swaps_take_exactly_the_part_they_name():
    a, b = footprints(1), footprints(2)
    scaled = script.with_energy(a, b)
    np.testing.assert_allclose(scaled.sum(axis=(1, 2)), b.sum(axis=(1, 2)), rtol=1e-12)  # b's energy ...
    np.testing.assert_allclose(scaled / scaled.sum(axis=(1, 2), keepdims=True), a / a.sum(axis=(1, 2), keepdims=True))
    profiled = script.with_profile(a, b)
    np.testing.assert_allclose(ring_sums(profiled), ring_sums(b), rtol=1e-5)  # b's ring profile ...
    rings = ring_index(a.shape[1])
    for r in range(1, int(rings.max()) + 1):  # ... a's angular detail: each ring's light in a's proportions
        np.testing.assert_allclose(profiled[:, rings == r] / profiled[:, rings == r].sum(axis=1, keepdims=True),
                                   a[:, rings == r] / a[:, rings == r].sum(axis=1, keepdims=True), rtol=1e-5)
    np.testing.assert_allclose(script.with_profile(a, a), a, rtol=1e-5)
    dark = np.zeros_like(a)
    assert np.isfinite(script.with_energy(dark, b)).all() and not script.with_energy(dark, b).any()
    assert np.isfinite(script.with_profile(dark, b)).all()


def test_a_model_equal_to_the_truth_gives_the_truth_in_every_hybrid():
    exact = footprints(3)
    parts = script.hybrids(["analytic", "torch"])
    assert "torch angular detail, analytic ring profile" in parts and len(parts) == 12
    for name, part in parts.items():
        np.testing.assert_allclose(part({"exact": exact, "analytic": exact, "torch": exact}), exact, rtol=1e-5,
                                   err_msg=name)
