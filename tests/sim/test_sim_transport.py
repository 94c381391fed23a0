"""Light transport: footprints reproduce renders, linearity, opaque/wide/grazing/shadow extremes."""

from __future__ import annotations

import numpy as np
import pytest
from sim_scenes import centre_pixel, custom_object, slab_scene

from sssphase_core.errors import InputError
from sssphase_core.sim import SimScene
from sssphase_core.sim import geometry as g
from sssphase_core.sim.materials import MATERIALS, Material, burley_cdf


def lookup(scene: SimScene, pattern: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Independent bilinear lookup of (1 - black) * L**gamma at the pixels' projector points (N, 3)."""
    proj = scene.rig.projector
    light = (1 - proj.black) * np.clip(pattern, 0, 1) ** proj.gamma
    if light.ndim == 2:
        light = np.repeat(light[..., None], 3, axis=-1)
    padded = np.pad(light, ((1, 1), (1, 1), (0, 0)))  # zero outside the projector image
    xp, yp = scene.proj_xy[ys, xs, 0] + 1, scene.proj_xy[ys, xs, 1] + 1
    x0, y0 = np.floor(xp).astype(int), np.floor(yp).astype(int)
    fx, fy = (xp - x0)[:, None], (yp - y0)[:, None]
    return ((1 - fy) * (1 - fx) * padded[y0, x0] + (1 - fy) * fx * padded[y0, x0 + 1]
            + fy * (1 - fx) * padded[y0 + 1, x0] + fy * fx * padded[y0 + 1, x0 + 1])


def splat(fp: np.ndarray, ys: np.ndarray, xs: np.ndarray, c: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """sum_p F_p(q - p) c_p with np.bincount (independent of the simulator's sparse product)."""
    n, k = fp.shape[:2]
    h, w = shape
    wp = w + k
    oy, ox = np.mgrid[0:k, 0:k]
    idx = ((ys * wp + xs)[:, None] + (oy * wp + ox).ravel()[None]).ravel()
    out = np.stack([np.bincount(idx, (fp[..., ch].reshape(n, -1) * c[:, ch, None]).ravel(), (h + k) * wp)
                    for ch in range(3)], -1)
    return out.reshape(h + k, wp, 3)[k // 2 : k // 2 + h, k // 2 : k // 2 + w]


@pytest.fixture(scope="module")
def apple_footprints(apple):
    ys, xs = np.nonzero(apple.lit)
    return ys, xs, apple.footprints(np.stack([ys, xs], 1))


@pytest.mark.parametrize("kind", ["checkerboard", "random_rgb"])
def test_footprints_splatted_reproduce_render(apple, apple_footprints, kind):
    ys, xs, fp = apple_footprints
    hp, wp = apple.shape_projector
    if kind == "checkerboard":
        pattern = ((np.arange(hp)[:, None] // 9 + np.arange(wp)[None] // 9) % 2).astype(np.float32)
    else:
        pattern = np.random.default_rng(1).random((hp, wp, 3), dtype=np.float32)
    rendered = apple.render(pattern[None])[0]
    ones = np.ones((hp, wp), np.float32)
    black_image = splat(fp, ys, xs, lookup(apple, ones, ys, xs) / (1 - apple.rig.projector.black), apple.shape)
    expected = splat(fp, ys, xs, lookup(apple, pattern, ys, xs), apple.shape) + apple.rig.projector.black * black_image
    assert rendered.shape == apple.shape + (3,)
    np.testing.assert_allclose(rendered, expected, rtol=1e-4, atol=1e-6)
    assert rendered[apple.mask].mean() > 0.05  # the pattern actually lit the object


def test_sum_of_dot_grids_equals_white(apple):
    hp, wp = apple.shape_projector
    s = 4
    dots = np.zeros((s * s, hp, wp), np.float32)
    for i, (sy, sx) in enumerate(np.ndindex(s, s)):
        dots[i, sy::s, sx::s] = 1.0
    black, white = apple.render(np.stack([np.zeros((hp, wp), np.float32), np.ones((hp, wp), np.float32)]))
    total = (apple.render(dots) - black).sum(axis=0)
    np.testing.assert_allclose(total, white - black, rtol=1e-4, atol=1e-5)
    assert (black[apple.mask] > 0).any() and black.max() < 0.01 * white.max()  # the projector's black level


def test_opaque_material_gives_delta_footprint():
    opaque = Material("opaque", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.5, measured=False)
    scene = slab_scene(opaque)
    y, x = centre_pixel(scene)
    fp = scene.footprints(np.array([[y, x]]))[0]
    k = scene.rig.patch
    expected = np.zeros_like(fp)
    expected[k // 2, k // 2] = 0.5 * scene.irradiance[y, x]
    np.testing.assert_allclose(fp, expected, rtol=1e-6, atol=0)


def test_energy_is_conserved_up_to_the_patch():
    short = Material("short", (0.6, 0.7, 0.8), (0.5, 0.6, 0.7), 0.03, measured=False)
    scene = slab_scene(short)
    y, x = centre_pixel(scene)
    e = scene.irradiance[y, x]
    fp = scene.footprints(np.array([[y, x]]))[0]
    np.testing.assert_allclose(fp.sum((0, 1)), e * (0.03 + np.array(short.albedo)), rtol=0.05)  # quadrature


def test_footprint_wider_than_the_patch_drops_the_tail():
    m = Material("wide", (0.9, 0.9, 0.9), (40.0, 20.0, 10.0), 0.02, measured=False)
    scene = slab_scene(m)
    y, x = centre_pixel(scene)
    fp = scene.footprints(np.array([[y, x]]))[0]
    e = scene.irradiance[y, x]
    kept = (fp.sum((0, 1)) / e - m.rho_s) / np.array(m.albedo)
    k, pitch = scene.rig.patch, np.sqrt(scene.area[y, x])
    rate = m.rate(scene.rig.sss_scale)
    lower = burley_cdf((k / 2 - 0.5) * pitch, rate)  # disc inside the window
    upper = burley_cdf((k / 2 + 0.5) * np.sqrt(2) * pitch, rate)  # disc around it
    assert kept[0] < 0.9 and kept[0] < kept[1] < kept[2]  # the widest channel loses the most
    assert np.all(kept > lower - 0.05) and np.all(kept < upper + 0.05)
    assert np.isfinite(fp).all() and fp.min() >= 0


@pytest.mark.parametrize("tilt", [0.0, 84.0])
def test_grazing_views_stay_finite(tilt):
    """A ball's rim (tilt 0) and a slab seen almost edge-on: clamped cell areas, finite footprints."""
    scene = slab_scene(MATERIALS["apple_flesh"], tilt_deg=tilt) if tilt else SimScene(
        custom_object(lambda p: g.sphere(p, (0, 0, 0), 25.0), MATERIALS["skin"]))
    view_dirs = scene.points / np.linalg.norm(scene.points, axis=-1, keepdims=True)
    cos_view = np.abs(np.einsum("hwc,hwc->hw", np.nan_to_num(scene.normals), np.nan_to_num(view_dirs)))
    grazing = scene.mask & (cos_view < 0.3)
    assert grazing.sum() > 50
    ys, xs = np.nonzero(grazing)
    fp = scene.footprints(np.stack([ys, xs], 1))
    img = scene.render(np.ones((1,) + scene.shape_projector, np.float32))
    assert np.isfinite(fp).all() and np.isfinite(img).all()
    assert np.isfinite(scene.area[scene.mask]).all() and (scene.area[scene.mask] > 0).all()
    assert not img[0][~scene.mask].any()  # light never leaves the surface
    # albedo <= 1, so a footprint never holds more than E (plus the quadrature's 8 % at grazing)
    assert (fp.sum(axis=(1, 2)) <= scene.irradiance[ys, xs, None] * 1.08 + 1e-6).all()


def test_shadowed_pixels_receive_no_light():
    # A small ball between the big ball and the projector casts a shadow the camera can see.
    toward_projector = np.array([0.351, 0.0, -0.936])
    blocker = 42 * toward_projector
    obj = custom_object(lambda p: np.minimum(g.sphere(p, (0, 0, 0), 25.0), g.sphere(p, blocker, 6.0)),
                        MATERIALS["plastic_star"], radius=52.0)
    scene = SimScene(obj)
    proj = scene.rig.projector
    to_light = proj.centre - scene.points
    facing = np.einsum("hwc,hwc->hw", np.nan_to_num(scene.normals), to_light) > 0
    shadow = scene.mask & facing & ~scene.lit
    assert shadow.sum() > 20
    ys, xs = np.nonzero(shadow)
    assert not scene.footprints(np.stack([ys, xs], 1)).any()
    assert np.isnan(scene.proj_xy[shadow]).all() and (scene.irradiance[shadow] == 0).all()
    white = scene.render(np.ones((1,) + scene.shape_projector, np.float32))[0]
    lit_level = np.median(white[scene.lit & facing], axis=0)
    assert (np.median(white[shadow], axis=0) < 0.1 * lit_level).all()


def test_proj_xy_reprojects_and_points_lie_on_the_surface(apple):
    lit = apple.lit
    pts = apple.points[lit].astype(np.float64)
    cam, proj = apple.rig.camera, apple.rig.projector
    ys, xs = np.nonzero(lit)
    np.testing.assert_allclose(cam.project(pts), np.stack([xs, ys], 1), atol=2e-3)
    np.testing.assert_allclose(proj.project(proj.to_projector(pts)), apple.proj_xy[lit], atol=2e-3)
    assert np.isnan(apple.proj_xy[~apple.mask]).all()
    for view in (0, 1):
        scene = apple if view == 0 else SimScene("apple", view=1, n_views=4)
        turn = g.rotation_y(np.deg2rad(scene.angle))
        obj_pts = (scene.points[scene.mask] - np.array(scene.rig.turntable_centre)) @ turn
        assert np.abs(scene.obj.sdf(obj_pts)).max() < 0.05


def test_footprint_requests_are_checked(apple):
    with pytest.raises(InputError):
        apple.footprints(np.array([[0, 10_000]]))
    assert not apple.footprints(np.array([[0, 0]])).any()  # background pixel: no footprint
    with pytest.raises(InputError):
        apple.render(np.ones((1, 10, 10), np.float32))


def test_irradiance_follows_incidence_and_distance(apple):
    lit = apple.lit
    proj = apple.rig.projector
    to_light = proj.centre - apple.points[lit].astype(np.float64)
    dist = np.linalg.norm(to_light, axis=1)
    cos_in = np.einsum("nc,nc->n", apple.normals[lit], to_light / dist[:, None])
    expected = cos_in * (apple.rig.reference_distance / dist) ** 2
    np.testing.assert_allclose(apple.irradiance[lit], expected, rtol=1e-4)
    assert (apple.irradiance[apple.mask & ~lit] == 0).all() and (apple.irradiance[lit] > 0).all()


def test_backdrop_is_an_opaque_wall_the_object_shadows(apple):
    from dataclasses import replace

    scene = SimScene("apple", rig=replace(apple.rig, backdrop=80.0))
    wall = scene.mask & ~scene.object_mask
    assert (scene.object_mask == apple.mask).all() and wall.sum() > apple.mask.sum()
    assert np.allclose(scene.points[wall][:, 2], apple.rig.turntable_centre[2] + 80.0)
    white = scene.render(np.ones((1,) + scene.shape_projector, np.float32))[0]
    alone = apple.render(np.ones((1,) + apple.shape_projector, np.float32))[0]
    assert np.allclose(white[apple.mask], alone[apple.mask], rtol=1e-5, atol=1e-7)  # no light crosses the gap
    # the wall's light leaves where it enters: its footprints are deltas of albedo times irradiance
    ys, xs = np.nonzero(wall & scene.lit)
    pick = np.linspace(0, len(ys) - 1, 40).astype(int)
    fp = scene.footprints(np.stack([ys[pick], xs[pick]], 1))
    k = fp.shape[1] // 2
    expected = np.asarray(MATERIALS["backdrop"].albedo)[None] * scene.irradiance[ys[pick], xs[pick], None]
    assert np.allclose(fp[:, k, k], expected, rtol=1e-4) and np.allclose(fp.sum(axis=(1, 2)), fp[:, k, k])
    # the object shadows the wall: wall points inside the projector's image that get no light, and stay dark
    proj = scene.rig.projector
    xy = proj.project(proj.to_projector(scene.points[wall]))
    framed = (xy[:, 0] > 0) & (xy[:, 0] < proj.width - 1) & (xy[:, 1] > 0) & (xy[:, 1] < proj.height - 1)
    shadow = np.zeros_like(wall)
    shadow[wall] = framed & ~scene.lit[wall]
    assert shadow.sum() > 100
    assert np.median(white[shadow]) < 0.05 * np.median(white[wall & scene.lit])


def test_backdrop_distance_is_checked():
    from dataclasses import replace

    from sssphase_core.sim import rig_from_options, rig_preset

    assert rig_from_options({"backdrop": 120}).backdrop == 120.0
    for bad in (10.0, float("nan"), 5000.0):
        with pytest.raises(InputError, match="backdrop"):
            replace(rig_preset("cpu"), backdrop=bad)
        with pytest.raises(InputError, match="sim option backdrop must be a number in"):
            rig_from_options({"backdrop": bad})


def test_mfp_skew_stretches_red_and_shrinks_blue_scattering(apple):
    from dataclasses import replace

    from sssphase_core.sim import rig_from_options

    skewed = SimScene("apple", rig=replace(apple.rig, mfp_skew=2.0))
    m = apple.mask
    assert np.allclose(skewed.mfp[m], apple.mfp[m] * np.array([2.0, 1.0, 0.5]), rtol=1e-5)
    assert np.allclose(skewed.albedo[m], apple.albedo[m])
    pix = np.argwhere(apple.lit)[::500]
    wide, nominal = skewed.footprints(pix), apple.footprints(pix)
    k = nominal.shape[1] // 2
    share = lambda fp: fp[:, k, k] / fp.sum(axis=(1, 2))  # noqa: E731  # the light that stays in its pixel
    assert (share(wide)[:, 0] <= share(nominal)[:, 0] + 1e-6).all() and (share(wide)[:, 2] >= share(nominal)[:, 2] - 1e-6).all()
    assert rig_from_options({"mfp_skew": 0.5}).mfp_skew == 0.5
    for bad in (0.1, float("nan"), 10.0):
        with pytest.raises(InputError, match="mfp_skew"):
            rig_from_options({"mfp_skew": bad})
