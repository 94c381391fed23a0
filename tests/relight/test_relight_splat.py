"""Relighting by splatting: exactness against the simulator and against a brute-force loop."""

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.relight import Projection, emitted_light, relight, sample_projector


def test_splat_matches_brute_force_loop(make_projection):
    rng = np.random.default_rng(0)
    proj, k = make_projection(), 9
    h, w = proj.shape
    fps = rng.random((h, w, k, k, 3)).astype(np.float32)
    pats = (rng.random((2, 50, 60)) > 0.5).astype(np.float32)
    out = relight(lambda px: fps[px[:, 0], px[:, 1]], proj, pats, k, chunk=37)

    light = emitted_light(pats, proj.gamma)
    ref = np.zeros((2, h + k, w + k, 3), np.float32)
    for y, x in zip(*np.nonzero(proj.mask), strict=True):
        c = sample_projector(light, proj.xp[y : y + 1, x], proj.yp[y : y + 1, x])[0]
        ref[:, y : y + k, x : x + k] += fps[y, x][None] * c[:, None, None, :]
    ref = ref[:, k // 2 : k // 2 + h, k // 2 : k // 2 + w]
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


def test_unlit_pixels_never_reach_the_footprint_source(make_projection):
    proj, k = make_projection(), 5
    pats = np.zeros((1, 50, 60), np.float32)
    pats[:, :, :30] = 1.0  # left half of the projector only
    seen = []

    def source(px):
        seen.append(px.copy())
        return np.ones((len(px), k, k, 3), np.float32)

    relight(source, proj, pats, k)
    px = np.concatenate(seen)
    assert len(px) < proj.mask.sum()
    assert np.all(proj.xp[px[:, 0], px[:, 1]] < 30)  # bilinear support ends at x < 30


def test_pattern_size_mismatch_is_a_clear_error(make_projection):
    proj = make_projection()
    with pytest.raises(InputError, match="does not match the projector"):
        relight(lambda px: np.zeros((len(px), 3, 3, 3)), proj, np.ones((1, 10, 10), np.float32), 3)


def test_relight_with_exact_footprints_reproduces_the_simulator():
    from sssphase_core.sim import SimScene

    scene = SimScene("pear")
    hp, wp = scene.shape_projector
    yy, xx = np.mgrid[0:hp, 0:wp]
    rng = np.random.default_rng(3)
    pats = np.stack([((yy // 16 + xx // 16) % 2).astype(np.float32), rng.random((hp, wp), dtype=np.float32)])
    ref = scene.render(pats)
    white = scene.render(np.ones((1, hp, wp), np.float32))[0]
    proj = Projection(scene.proj_xy[..., 0], scene.proj_xy[..., 1], scene.mask, (wp, hp),
                      scene.rig.projector.gamma, scene.rig.projector.black)
    out = relight(scene.footprints, proj, pats, scene.rig.patch, white=white, chunk=2048)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, atol=1e-5 * float(ref.max()))
