"""The volumetric Monte Carlo stand-in renderer (benchmarks/standin_volumetric.py) obeys the physics it claims."""


import numpy as np
import pytest
from benchmark_script import load_benchmark

mc = load_benchmark("standin_volumetric")

XS = np.arange(-mc.RADIUS, mc.RADIUS + 1)


def _centroid(k: np.ndarray) -> tuple[float, float]:
    return float((k.sum(0) * XS).sum() / k.sum()), float((k.sum(1) * XS).sum() / k.sum())


def test_fresnel_at_normal_incidence_and_total_internal_reflection():
    assert mc.fresnel(np.array(1.0), 1.3) == pytest.approx(((1.3 - 1) / 2.3) ** 2)
    critical = np.sqrt(1 - (1 / 1.3) ** 2)  # cosine of the critical angle, from inside
    assert mc.fresnel(np.array(critical * 0.99), 1 / 1.3) == 1.0 and mc.fresnel(np.array(critical * 1.01), 1 / 1.3) < 1.0


def test_footprints_conserve_energy_and_skew_toward_where_oblique_light_travels():
    """Skin (Jensen 2001, red): the normal-incidence footprint holds the diffuse reflectance of the classical
    dipole within 5 % and is centred; at 50 degrees it leans forward along +x, not across."""
    from sssphase_core.sim.materials import jensen_diffuse_reflectance

    (sp, *_), (sa, *_) = mc.MEASURED["skin1"]
    rng = np.random.default_rng(0)
    normal = mc.mc_kernel(sp, sa, 0.0, 0.0, 1.0, 4000, rng)
    oblique = mc.mc_kernel(sp, sa, 0.0, 50.0, 1.0, 4000, rng)
    assert normal.sum() == pytest.approx(float(jensen_diffuse_reflectance(sp, sa)), rel=0.05)
    assert max(map(abs, _centroid(normal))) < 0.1
    cx, cy = _centroid(oblique)
    assert cx > 0.3 and abs(cy) < 0.1
    assert oblique.sum() < normal.sum() * np.cos(np.radians(50)) * 1.1  # less light enters obliquely
