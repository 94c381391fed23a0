"""Catalogue, materials (Jensen -> Burley), rig presets and views."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError, UnknownObjectError
from sssphase_core.sim import (
    CALIBRATION_OBJECTS,
    CATALOGUE,
    EXTRA_OBJECTS,
    MATERIALS,
    TRAIN_OBJECTS,
    UNSEEN_OBJECTS,
    SimScene,
    get_object,
    rig_preset,
)
from sssphase_core.sim.materials import (
    JENSEN_2001,
    burley_cdf,
    burley_scale,
    diffuse_mean_free_path,
    jensen_diffuse_reflectance,
)


def test_catalogue_has_the_papers_objects():
    assert TRAIN_OBJECTS == ("apple", "pear", "orange", "star", "shovel")
    assert UNSEEN_OBJECTS == ("crab", "hand", "tangerine", "sand_rake", "soap", "leaf", "lego")
    assert set(CATALOGUE) == set(TRAIN_OBJECTS + UNSEEN_OBJECTS + EXTRA_OBJECTS + CALIBRATION_OBJECTS)
    with pytest.raises(UnknownObjectError) as err:
        get_object("banana")
    assert all(name in str(err.value) for name in CATALOGUE)


@pytest.mark.parametrize("name", TRAIN_OBJECTS + UNSEEN_OBJECTS + EXTRA_OBJECTS + CALIBRATION_OBJECTS)
def test_every_object_fits_the_view_and_is_lit(name):
    scene = SimScene(name)
    mask = scene.mask
    assert mask.sum() > 2000
    assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())  # fits the view
    assert scene.lit.sum() > 0.8 * mask.sum()
    labels = np.unique(scene.material[mask])
    assert (labels >= 0).all() and (scene.material[~mask] == -1).all()
    assert np.isfinite(scene.albedo[mask]).all() and (scene.mfp[mask] > 0).all()


def _labels(name: str) -> set[str]:
    scene = SimScene(name)
    from sssphase_core.sim import MATERIAL_NAMES

    return {MATERIAL_NAMES[i] for i in np.unique(scene.material[scene.mask])}


def test_spatially_varying_materials():
    assert {"apple_flesh", "apple_red"} <= _labels("apple")
    assert {"marble", "soap_vein"} <= _labels("soap")
    assert {"leaf", "leaf_vein"} <= _labels("leaf")
    assert _labels("hand") & {"skin", "skin_palm"}
    assert _labels("star") == {"plastic_star"}
    assert _labels("chicken") == {"chicken", "chicken_fat"}


def test_extra_objects_are_made_of_measured_materials_only():
    """The objects outside the paper's splits carry Jensen et al.'s measured coefficients, flagged so."""
    for name in EXTRA_OBJECTS:
        assert CATALOGUE[name].split == "extra"
        assert all(MATERIALS[m].measured for m in _labels(name)), name
    sp, sa = JENSEN_2001["chicken1"]
    assert MATERIALS["chicken"].mfp[0] == pytest.approx(float(diffuse_mean_free_path(sp[0], sa[0])))


def _spread(scene: SimScene) -> float:
    """Mean radius (pixels) of the green footprint energy of lit pixels around the object centre."""
    ys, xs = np.nonzero(scene.lit)
    pick = np.linspace(0, len(ys) - 1, 40).astype(int)
    fp = scene.footprints(np.stack([ys[pick], xs[pick]], 1))[..., 1]
    k = fp.shape[1]
    yy, xx = np.mgrid[0:k, 0:k] - k // 2
    return float((fp * np.hypot(yy, xx)).sum() / fp.sum())


def test_apple_scatters_more_than_pear_more_than_star():
    apple, pear, star = (_spread(SimScene(n)) for n in ("apple", "pear", "star"))
    assert apple > 1.5 * pear and pear > 3 * star
    assert star < 0.3  # near-opaque plastic: almost a delta


def test_jensen_conversion():
    sp, sa = JENSEN_2001["apple"]
    rd = jensen_diffuse_reflectance(sp, sa)
    assert np.all((rd > 0.4) & (rd < 0.95)) and rd[2] < rd[0]  # blue is absorbed most
    np.testing.assert_allclose(diffuse_mean_free_path(sp, sa), 1 / np.sqrt(3 * np.array(sa) * (np.array(sa) + sp)))
    # more absorption -> darker and shorter
    assert jensen_diffuse_reflectance(1.0, 0.1) < jensen_diffuse_reflectance(1.0, 0.01)
    assert MATERIALS["apple_flesh"].measured and MATERIALS["skin"].measured and not MATERIALS["pear"].measured
    assert not MATERIALS["apple_red"].measured  # Jensen's apple with an invented pigment


def test_burley_profile_cdf_matches_its_density():
    s = 1.7
    r = np.linspace(0.05, 6, 400)
    density = s * (np.exp(-s * r) + np.exp(-s * r / 3)) / (8 * np.pi * r)
    dcdf = np.gradient(burley_cdf(r, s), r)
    np.testing.assert_allclose(dcdf[2:-2], (2 * np.pi * r * density)[2:-2], rtol=1e-3)
    assert burley_cdf(0.0, s) == 0 and burley_cdf(1e3, s) == pytest.approx(1.0)
    assert burley_scale(0.33) == pytest.approx(3.5)


def test_presets_and_views():
    cpu, paper = rig_preset("cpu"), rig_preset("paper")
    assert (cpu.camera.width, cpu.camera.height, cpu.patch) == (256, 192, 32)
    assert (paper.camera.width, paper.camera.height, paper.patch) == (1920, 1080, 90)
    assert (paper.projector.width, paper.projector.height) == (1920, 1080)
    assert 100 <= np.linalg.norm(cpu.projector.centre) <= 200  # stereo baseline
    # the projector is verged on the turntable centre: it projects near its image centre
    xy = cpu.projector.project(cpu.projector.to_projector(np.array([cpu.turntable_centre])))[0]
    np.testing.assert_allclose(xy, [(cpu.projector.width - 1) / 2, (cpu.projector.height - 1) / 2], atol=1e-6)
    assert cpu.view_angle(1, 4) == 90.0
    with pytest.raises(InputError):
        cpu.view_angle(4, 4)
    with pytest.raises(InputError):
        rig_preset("huge")


def test_dropped_energy_shrinks_with_the_patch_and_fits_the_presets():
    from sssphase_core.bench.sim_bench import dropped_energy
    from sssphase_core.sim.materials import dropped_fraction

    rate = np.array([0.2, 0.5, 2.0])  # mm^-1
    small, large = dropped_fraction(rate, 0.65, 16), dropped_fraction(rate, 0.65, 64)
    assert np.all(small >= large) and small[0] > 0.1 and large[2] < 1e-6
    extra = {"chicken", "chicken_fat", "potato", "skimmilk"}  # measured, left as measured: they reach further
    for preset in ("cpu", "paper"):
        dropped = dropped_energy(preset)
        assert max(max(v) for k, v in dropped.items() if k not in extra) < 0.05  # the paper splits' materials fit
        assert max(dropped["chicken"]) > 0.1  # chicken's red light travels beyond the patch
