"""The camera-inputs benchmark (benchmarks/camera_inputs.py) measures what it says."""


import numpy as np
import pytest
from benchmark_script import load_benchmark

ci = load_benchmark("camera_inputs")


def test_the_radius_of_a_gaussian_footprint_is_its_second_moment():
    k, sigmas = 41, (1.0, 2.0, 3.5)
    d = np.arange(k) - k // 2
    r2 = d[:, None] ** 2 + d[None, :] ** 2
    f = np.stack([np.exp(-r2 / (2 * s * s)) for s in sigmas], axis=-1)[None]  # (1, K, K, 3)
    np.testing.assert_allclose(ci.radius(f)[0], np.sqrt(2) * np.array(sigmas), rtol=1e-3)
    assert ci.radius(-f)[0].tolist() == [0.0, 0.0, 0.0]  # no positive light: no width, no NaN


def test_frames_through_the_mosaic_keep_a_flat_colour_and_change_a_fringe():
    flat = np.broadcast_to(np.array([0.6, 0.3, 0.1], np.float32), (8, 20, 22, 3))
    np.testing.assert_allclose(ci.bayer_frames(flat), flat, atol=1e-6)
    x = np.arange(22)
    fringe = (0.5 + 0.4 * np.cos(2 * np.pi * x / 5))[None, None, :, None] * np.array([1.0, 0.5, 0.2])
    fringe = np.broadcast_to(fringe, (8, 20, 22, 3)).astype(np.float32)
    assert np.abs(ci.bayer_frames(fringe) - fringe).max() > 0.01
    assert ci.as_array(np.zeros((2, 3, 3, 3), np.float32)).dtype == np.float64


@pytest.mark.parametrize("mix", [np.array([0.5, 0.6, 0.7])])
def test_a_row_reports_an_exact_footprint_as_exact(mix):
    rng = np.random.default_rng(0)
    f = rng.random((5, 9, 9, 3))
    top = f"{-10 * np.log10(ci.MSE_FLOOR):.1f}"
    line = ci.row("same", f, f, mix)
    assert line == f"| same | 1.00 / 1.00 / 1.00 | {top} / {top} / {top} | 0.00 / 0.00 / 0.00 | 0.50 / 0.60 / 0.70 |"
    worse = ci.row("wide", f + 0.01, f, mix)
    assert float(worse.split("|")[3].split("/")[0]) == pytest.approx(40.0, abs=0.01)  # MSE 1e-4


def test_detail_of_a_delta_footprint():
    f = np.zeros((4, 9, 9, 3))
    f[:, 4, 4] = 1.0
    cells = [c.strip() for c in ci.detail("delta", f, f).strip("|").split("|")]
    assert cells[0] == "delta"
    assert cells[1] == "1.000 / 1.000 / 1.000" and all(c == "0.000 / 0.000 / 0.000" for c in cells[2:7])  # all at r < 0.5
    assert cells[7:10] == ["1.000 / 1.000 / 1.000"] * 3  # a delta passes every period
    assert cells[10] == "0.000 / 0.000 / 0.000"
    moved = np.roll(f, 1, axis=2)
    assert ci.detail("moved", moved, f).strip(" |").endswith("1.000 / 1.000 / 1.000")
