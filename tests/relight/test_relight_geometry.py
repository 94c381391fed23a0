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


def decoded_centred(entry_x: float):
    """A learned model's footprints: centred where a dot crop is cut (the decoded point), the light entering
    ``entry_x`` camera px from the centre (densest there) and running on to the right."""
    yy, xx = np.mgrid[:K, :K].astype(np.float64) - K // 2
    d = xx - entry_x
    profile = np.exp(-0.5 * (d ** 2 + yy ** 2) / 0.8 ** 2) + 0.3 * np.where(d > 0, np.exp(-d / 1.5), 0) * np.exp(-0.5 * yy ** 2)

    def source(pixels: np.ndarray) -> np.ndarray:
        return np.broadcast_to(profile[None, :, :, None].astype(np.float32), (len(pixels), K, K, 3)).copy()
    return source


def test_a_learned_models_footprints_give_the_shift_by_where_light_enters_them():
    """Footprints centred on the decoded point, relit under the fringes, predict their tail's pull, not the
    shift (with a trained decoder `sss geometry` moved points the wrong way, tripling the bias); the shift
    is the entry point inside them through the decoded map's slope: light entering 1.5 camera px to the left
    of the centre means the pixel's decoded point is that of the pixel 1.5 px to its left: 1.5 x 0.8 projector px
    behind the point that lit it."""
    from sssphase_core.relight.geometry import entry_shift

    decoded = projection(offset=1.5)
    inner = (slice(K, H - K), slice(K, W - K))
    relit_x, _ = scattering_shift(decoded_centred(-1.5), decoded, K, period=PERIOD)
    assert np.nanmedian(relit_x[inner]) > 0  # the wrong tool: the wrong way (+0.96 px against the -1.2 px shift)
    bx, by = entry_shift(decoded_centred(-1.5), decoded)
    # the maximum sits a little the way light travels (the tail adds to it): 1.28 of the 1.5 px, an under-correction
    assert -1.5 * SLOPE < np.nanmedian(bx[inner]) < -1.1 * SLOPE and np.abs(by[inner]).max() < 1e-6
    geometric = geometric_correspondence(decoded_centred(-1.5), decoded, K, period=PERIOD, centred_on="decoded")
    truth = projection(offset=0.0)
    np.testing.assert_allclose(geometric.xp[inner], truth.xp[inner], atol=0.25)  # the decoded points were 1.2 px off
    np.testing.assert_allclose(geometric.yp[inner], truth.yp[inner], atol=1e-5)
