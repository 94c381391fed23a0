"""Correspondences for geometry: the predicted scattering shift of decoded points, and its removal."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.relight.engine import Projection
from sssphase_core.relight.geometry import geometric_correspondence, scattering_shift

K, H, W = 9, 24, 40
SLOPE = 0.8  # projector px per camera px along x
#: Fringe period of the tests (projector px): bilinear sampling of the fringe raster shifts phases by
#: up to ~0.016 px at the rig's 11 px, ~0.002 px at 32 px.
PERIOD = 32.0


def shifted_delta(dx: int):
    """Footprints that send all of a pixel's light ``dx`` camera pixels to the right."""
    def source(pixels: np.ndarray) -> np.ndarray:
        fp = np.zeros((len(pixels), K, K, 3), np.float32)
        fp[:, K // 2, K // 2 + dx] = 1.0
        return fp
    return source


def symmetric(pixels: np.ndarray) -> np.ndarray:
    g = np.exp(-0.5 * (np.arange(K) - K // 2) ** 2)
    return np.broadcast_to((np.outer(g, g) / np.outer(g, g).sum())[None, :, :, None], (len(pixels), K, K, 3)).copy()


def projection(offset: float) -> Projection:
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return Projection((SLOPE * (cols - offset) + 3.0).astype(np.float32), (rows + 2.0).astype(np.float32),
                      np.ones((H, W), bool), (48, 32), gamma=2.2, black=0.0)


def test_light_that_travels_shifts_the_decoded_point_and_the_shift_is_removed():
    decoded = projection(offset=2.0)  # what PSP decodes: the light of the point lighting col - 2 shows at col
    geometric = geometric_correspondence(shifted_delta(2), decoded, K, period=PERIOD)
    truth = projection(offset=0.0)
    inner = (slice(K, H - K), slice(K, W - K))
    np.testing.assert_allclose(geometric.xp[inner], truth.xp[inner], atol=5e-3)
    np.testing.assert_allclose(geometric.yp[inner], truth.yp[inner], atol=5e-3)
    bx, _ = scattering_shift(shifted_delta(2), truth, K, period=PERIOD)
    assert np.nanmedian(bx[inner]) == pytest.approx(-2 * SLOPE, abs=1e-3)


def test_symmetric_footprints_predict_no_shift():
    bx, by = scattering_shift(symmetric, projection(0.0), K, period=PERIOD)
    inner = (slice(K, H - K), slice(K, W - K))
    assert np.abs(bx[inner]).max() < 1e-3 and np.abs(by[inner]).max() < 1e-3
