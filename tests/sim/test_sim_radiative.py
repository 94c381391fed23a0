"""The radiative transport: the random walk against closed forms it must meet (single scattering, a medium that
absorbs nothing), the shipped table against a fresh walk, and its footprints against the Burley transport's."""

from __future__ import annotations

import numpy as np
import pytest
from sim_scenes import centre_pixel, slab_scene

from sssphase_core.errors import InputError
from sssphase_core.sim import RigConfig, radiative, rig_from_options, rig_preset
from sssphase_core.sim.materials import MATERIALS, Material


def test_low_albedo_media_reflect_the_single_scattering_closed_form():
    """Isotropic, index-matched, alpha' = 0.02: the light that scattered once, alpha / 2 (1 - ln 2), and little more
    (twice-scattered light is of order alpha^2)."""
    alpha = 0.02
    cdf, lost = radiative.simulate(alpha, 0.0, 1.0, np.array([radiative.WALK_RADIUS]), photons=40_000, seed=3)
    assert cdf[-1] == pytest.approx(alpha / 2 * (1 - np.log(2)), rel=0.06)
    assert lost < 1e-3 * alpha


def test_a_medium_that_absorbs_nothing_returns_all_its_light():
    """No absorption and no boundary: every photon leaves through the surface or wanders past the walk's bounds."""
    cdf, lost = radiative.simulate(1.0, 0.0, 1.0, np.array([radiative.WALK_RADIUS]), photons=4000, seed=1)
    assert cdf[-1] + lost == pytest.approx(1.0, abs=0.02)
    assert cdf[-1] > 0.8


def test_forward_scattering_moves_the_first_exits_away_from_the_entry_point():
    """Same reduced coefficients (so the same diffusion far away), g = 0.8 against isotropic: less light leaves within
    a reduced mean free path, about as much in all."""
    radii = np.array([0.3, 1.0, radiative.MC_RADIUS])
    iso, _ = radiative.simulate(0.99, 0.0, 1.3, radii, photons=20_000, seed=2)
    fwd, _ = radiative.simulate(0.99, 0.8, 1.3, radii, photons=20_000, seed=2)
    assert fwd[0] < 0.6 * iso[0] and fwd[1] < 0.85 * iso[1]
    assert fwd[-1] == pytest.approx(iso[-1], rel=0.08)


def test_the_shipped_table_is_what_the_walk_gives():
    data = np.load(radiative.TABLE_FILE)
    cdf = data["cdf"]
    assert cdf.shape == (len(radiative.TABLE_G), len(radiative.TABLE_ABSORPTION), len(radiative.TABLE_RADII))
    assert np.all(np.diff(cdf, axis=-1) >= 0) and np.all(cdf[..., -1] <= 1)
    assert np.all(np.diff(cdf[..., -1], axis=1) < 0)  # more absorption, less light back
    i, j = radiative.TABLE_G.index(0.6), 4
    fresh = radiative.full_cdf(1 - radiative.TABLE_ABSORPTION[j], 0.6, float(data["eta"]), photons=6000, seed=11)
    at = np.searchsorted(radiative.TABLE_RADII, [0.3, 1.0, 3.0, radiative.MC_RADIUS])
    np.testing.assert_allclose(fresh[at], cdf[i, j, at], rtol=0.06)


def test_the_table_interpolates_between_its_media():
    lo, hi = radiative.ProfileTable.at(0.3), radiative.ProfileTable.at(0.6)
    mid = radiative.ProfileTable.at(0.45)
    np.testing.assert_allclose(mid.total, (lo.total + hi.total) / 2, rtol=1e-6)
    assert np.all(mid.table >= np.minimum(lo.table, hi.table) - 1e-6)
    assert np.all(mid.table <= np.maximum(lo.table, hi.table) + 1e-6)
    row = mid.index(np.array([0.999, 0.9, 0.5]))
    r = np.array([[0.1, 1.0, 10.0]] * 3, np.float32)
    c = mid.cdf(row, r)
    assert np.all(np.diff(c, axis=1) > 0) and np.all((c > 0) & (c <= 1))
    assert c[0, 0] < c[2, 0]  # the more absorbing medium keeps its light closer to the entry point
    grid = np.exp(radiative.LOOKUP_START + radiative.LOOKUP_STEP * np.array([100, 400, 700])) - radiative.LOOKUP_EPS
    on_grid = mid.cdf(np.array([2.0, 7.0, 11.0]), np.tile(grid.astype(np.float32), (3, 1)))  # rows and radii exact
    np.testing.assert_allclose(on_grid, mid.table[[2, 7, 11]][:, [100, 400, 700]], rtol=1e-4)
    halfway = mid.cdf(np.array([7.5]), grid[None, :1].astype(np.float32))[0, 0]
    assert halfway == pytest.approx((mid.table[7, 100] + mid.table[8, 100]) / 2, rel=1e-4)


def test_footprints_carry_the_albedo_and_lean_out_with_forward_scattering():
    """On a slab whose reduced mean free path is about a pixel: Burley's energy, and with g = 0.8 less light leaves
    through the entry pixel itself than with isotropic scattering (the first exits move outward)."""
    long = Material("long", (0.5, 0.7, 0.9), (2.0, 3.0, 4.0), 0.03, measured=False)
    fps = {}
    for transport, g in (("burley", 0.0), ("radiative", 0.0), ("radiative", 0.8)):
        scene = slab_scene(long, transport=transport, anisotropy=g)
        y, x = centre_pixel(scene)
        fps[transport, g] = scene.footprints(np.array([[y, x]]))[0] / scene.irradiance[y, x]
        assert np.isfinite(fps[transport, g]).all() and fps[transport, g].min() >= 0
    for g in (0.0, 0.8):  # (both lose the same few % to the ring quadrature and the patch)
        np.testing.assert_allclose(fps["radiative", g].sum((0, 1)), fps["burley", 0.0].sum((0, 1)), rtol=0.02)
    c = fps["burley", 0.0].shape[0] // 2
    assert np.all(fps["radiative", 0.8][c, c, :2] < 0.8 * fps["radiative", 0.0][c, c, :2])
    np.testing.assert_allclose(fps["radiative", 0.0][c, c], fps["burley", 0.0][c, c], rtol=0.1)  # Burley fits g = 0


def test_an_opaque_material_is_a_delta_and_wide_ones_stay_finite():
    opaque = Material("opaque", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.5, measured=False)
    wide = Material("wide", (0.9, 0.9, 0.9), (40.0, 20.0, 10.0), 0.02, measured=False)
    for m in (opaque, wide, MATERIALS["wholemilk"]):
        scene = slab_scene(m, transport="radiative", anisotropy=0.85)
        y, x = centre_pixel(scene)
        fp = scene.footprints(np.array([[y, x]]))[0] / scene.irradiance[y, x]
        assert np.isfinite(fp).all() and fp.min() >= 0 and fp.sum() <= 3 * (m.rho_s + max(m.albedo)) + 1e-6
    assert fp[16, 16].sum() > 0
    scene = slab_scene(opaque, transport="radiative")
    y, x = centre_pixel(scene)
    fp = scene.footprints(np.array([[y, x]]))[0]
    assert fp[16, 16] == pytest.approx(0.5 * scene.irradiance[y, x], rel=1e-4)
    fp[16, 16] = 0
    assert not fp.any()


def test_anisotropy_is_a_rig_option_and_checked():
    rig = rig_from_options({"transport": "radiative", "anisotropy": 0.5})
    assert rig.transport == "radiative" and rig.anisotropy == 0.5
    for bad in (0.95, -0.1, float("nan"), "0.5"):
        with pytest.raises(InputError, match="anisotropy"):
            rig_from_options({"transport": "radiative", "anisotropy": bad})
    with pytest.raises(InputError, match="anisotropy"):
        RigConfig(**{**rig_preset("cpu").__dict__, "anisotropy": 1.0})
