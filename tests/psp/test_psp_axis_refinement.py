"""The turntable's axis refined from the views' own overlaps (`sss geometry --refine-axis`), on synthetic turntable
views: organised clouds of a shape seen from the camera at each recorded angle, back faces left out."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.processing.axis_refinement import MIN_PAIRS, refine_axis, surface_normals
from sssphase_core.processing.triangulation import turned

AXIS, POINT = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 400.0])


def _views(angles: list[float], radii=(40.0, 25.0, 30.0), bumps: float = 0.08, centre=(3.0, -5.0, 402.0),
           grid=(60, 120)) -> dict[int, np.ndarray]:
    """Per view (H, W, 3): a bumpy ellipsoid about ``centre`` on a turntable turned by the view's angle about the
    true axis, seen by a camera at the origin looking along +z (points whose normal faces away are NaN)."""
    v, u = np.meshgrid(np.linspace(0.05, np.pi - 0.05, grid[0]), np.linspace(0, 2 * np.pi, grid[1], endpoint=False),
                       indexing="ij")
    r = 1 + bumps * np.sin(3 * u) * np.cos(2 * v) + bumps * np.cos(5 * u + 1) * np.sin(v) ** 2
    shape = np.stack([radii[0] * np.sin(v) * np.cos(u), radii[1] * np.cos(v), radii[2] * np.sin(v) * np.sin(u)], -1)
    surface = r[..., None] * shape + np.asarray(centre)
    views = {}
    for i, angle in enumerate(angles):
        p = turned(surface, AXIS, POINT, angle)
        n = np.nan_to_num(surface_normals(p))
        middle = turned(np.asarray(centre), AXIS, POINT, angle)
        outward = np.where((np.einsum("hwc,hwc->hw", n, p - middle) < 0)[..., None], -n, n)
        seen = np.einsum("hwc,hwc->hw", outward, p) < 0  # facing the camera at the origin
        views[i] = np.where(seen[..., None], p, np.nan)
    return views


def _apart(axis: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    offset = point - POINT
    return (float(np.degrees(np.arccos(min(1.0, abs(axis @ AXIS))))),
            float(np.linalg.norm(offset - (offset @ AXIS) * AXIS)))


@pytest.mark.parametrize("tilt, move", [(3.0, 8.0), (-2.0, -5.0)])
def test_an_axis_that_is_off_is_refined_back_onto_the_turntables(tilt, move):
    views = _views([0, 60, 120, 180, 240, 300])
    angles = {i: 60.0 * i for i in views}
    start = turned(AXIS, np.array([0.0, 0.0, 1.0]), np.zeros(3), tilt)
    r = refine_axis(views, angles, start, POINT + np.array([move, 0.0, move / 2]), sample=1500)
    assert r.refused is None and r.pinned and r.pairs >= MIN_PAIRS
    off_tilt, off_shift = _apart(r.axis, r.point)
    assert off_tilt < 0.05 and off_shift < 0.1, (off_tilt, off_shift)  # (the grid spacing is ~2 mm)
    assert r.tilt == pytest.approx(abs(tilt), abs=0.05) and r.rms_after < 0.2 < r.rms_before
    assert r.slide_tilt < 0.05 and r.slide_shift < 0.05


def test_a_shape_symmetric_about_the_axis_does_not_pin_it_down():
    """A sphere centred on the axis turns into itself about any axis through its centre: the refinement keeps the
    views agreeing but cannot tell where the axis is, and says so (not pinned)."""
    views = _views([0, 45, 90, 135], radii=(30.0, 30.0, 30.0), bumps=0.0, centre=(0.0, 0.0, 400.0))
    start = turned(AXIS, np.array([0.0, 0.0, 1.0]), np.zeros(3), 2.0)
    r = refine_axis(views, {i: 45.0 * i for i in views}, start, POINT, sample=1500)
    assert r.refused is None and not r.pinned and r.slide_tilt > 0.2


def test_views_that_do_not_overlap_keep_the_given_axis():
    views = _views([0, 180], grid=(30, 60))
    rows = np.arange(30)[:, None, None]
    views = {0: np.where(rows < 10, views[0], np.nan), 1: np.where(rows >= 20, views[1], np.nan)}  # top, bottom
    r = refine_axis(views, {0: 0.0, 1: 180.0}, AXIS, POINT)
    assert r.refused is not None and "overlap in only" in r.refused and (r.axis == AXIS).all()
    empty = refine_axis({0: np.full((4, 4, 3), np.nan)}, {0: 0.0}, AXIS, POINT)
    assert empty.refused is not None and "too few points" in empty.refused


def test_normals_of_an_organised_plane_are_its_normal_and_nan_at_its_edges():
    y, x = np.mgrid[0:5, 0:6].astype(float)
    plane = np.stack([x, y, 2 * x + 3.0], -1)
    n = surface_normals(plane)
    expected = np.array([-2.0, 0.0, 1.0]) / np.sqrt(5)
    assert np.allclose(np.abs(n[1:-1, 1:-1] @ expected), 1) and np.isnan(n[0]).all() and np.isnan(n[:, -1]).all()
