"""Dot-grid footprint extraction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import convolve

from sssphase_core.errors import InputError
from sssphase_core.processing.footprints import DotGridExtractor
from sssphase_core.processing.patterns import dot_grid

K = 9
SPACING = 10  # wider than the 9-px kernel: neighbouring dots' footprints do not overlap


def _kernel():
    yy, xx = np.mgrid[-3:4, -4:5]  # 7 x 9 anisotropic, off-centre mass
    ker = np.exp(-(xx**2) / 4.0 - (yy - 0.5) ** 2 / 1.5)
    ker /= ker.sum()
    return np.stack([ker, 0.5 * ker, 0.2 * ker], -1)


def _scene(h=30, w=40):
    """Camera = projector (identity correspondence, some pixels masked); light spreads by a known kernel."""
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    mask = np.ones((h, w), bool)
    mask[5:8, 10:14] = False
    xp = np.where(mask, xx + 0.3, np.nan).astype(np.float32)  # rounding to the pixel itself
    yp = np.where(mask, yy - 0.2, np.nan).astype(np.float32)
    ker = _kernel()

    def frame(sx, sy):
        dots = dot_grid(w, h, SPACING, sx, sy)
        return np.stack([convolve(dots, ker[..., c], mode="constant") for c in range(3)], -1)

    return xp, yp, mask, frame


def _expected_crop(y, x, h, w):
    """The kernel placed in a K x K patch centred on (y, x), cut where it leaves the image."""
    ker = _kernel()
    patch = np.zeros((K, K, 3))
    kh, kw = ker.shape[:2]
    top, left = K // 2 - kh // 2, K // 2 - kw // 2
    patch[top : top + kh, left : left + kw] = ker
    yy = y - K // 2 + np.arange(K)
    xx = x - K // 2 + np.arange(K)
    patch[(yy < 0) | (yy >= h)] = 0
    patch[:, (xx < 0) | (xx >= w)] = 0
    return patch


def test_every_valid_pixel_gets_its_own_centred_footprint():
    h, w = 30, 40
    xp, yp, mask, frame = _scene(h, w)
    ex = DotGridExtractor(xp, yp, mask, SPACING, K)
    for sy in range(SPACING):
        for sx in range(SPACING):
            ex.add(sx, sy, frame(sx, sy))
    pixels, fps = ex.result()
    assert len(ex.missing()) == 0
    assert pixels.shape == (mask.sum(), 2) and fps.shape == (mask.sum(), K, K, 3) and fps.dtype == np.float32
    assert mask[pixels[:, 0], pixels[:, 1]].all()
    for (y, x), fp in zip(pixels, fps, strict=True):
        np.testing.assert_allclose(fp, _expected_crop(y, x, h, w), atol=1e-6)


def test_partial_capture_lists_missing_pixels():
    xp, yp, mask, frame = _scene()
    ex = DotGridExtractor(xp, yp, mask, SPACING, K)
    assert ex.add(2, 3, frame(2, 3)) > 0
    pixels, fps = ex.result()
    assert (pixels[:, 1] % SPACING == 2).all() and (pixels[:, 0] % SPACING == 3).all()
    assert len(pixels) + len(ex.missing()) == mask.sum()
    assert ex.add(0, 0, np.zeros((30, 40, 3))) > 0  # a black frame stores (zero) footprints too


def test_rounding_selects_the_lighting_frame():
    xp = np.array([[6.49, 6.51, -0.4]], np.float32)
    yp = np.array([[0.0, 0.0, 0.0]], np.float32)
    ex = DotGridExtractor(xp, yp, np.ones((1, 3), bool), 6, 3)
    assert ex.add(0, 0, np.ones((1, 3, 3))) == 2  # 6.49 -> 6 and -0.4 -> 0 are lit by shift 0
    assert ex.add(1, 0, np.ones((1, 3, 3))) == 1  # 6.51 -> 7
    pixels, fps = ex.result()
    assert len(pixels) == 3 and fps[:, 1, 1].min() == 1
    np.testing.assert_array_equal(fps[0, 0], 0)  # row above the one-row image is zero padding


def test_bad_arguments_rejected():
    xp, yp, mask, frame = _scene()
    ex = DotGridExtractor(xp, yp, mask, SPACING, K)
    with pytest.raises(InputError):
        ex.add(SPACING, 0, frame(0, 0))
    with pytest.raises(InputError):
        ex.add(0, 0, np.zeros((10, 10, 3)))
    with pytest.raises(InputError):
        DotGridExtractor(xp, yp[:5], mask, SPACING, K)


def test_dot_grid_crops_match_simulated_footprints():
    """On the simulated rig, dot-grid crops approximate the exact footprints (a dot lights the few camera
    pixels around its correspondence, so they agree in shape and energy, not exactly)."""
    sim = pytest.importorskip("sssphase_core.sim")
    scene = sim.SimScene("pear")
    wp, hp = scene.rig.projector.width, scene.rig.projector.height
    spacing, shifts = 32, [(0, 0), (16, 16), (5, 21)]
    xp, yp = scene.proj_xy[..., 0], scene.proj_xy[..., 1]
    ex = DotGridExtractor(xp, yp, scene.lit, spacing, scene.rig.patch)
    images = scene.render(np.stack([dot_grid(wp, hp, spacing, sx, sy) for sx, sy in shifts] + [np.zeros((hp, wp), np.float32)]))
    for (sx, sy), img in zip(shifts, images[:-1], strict=True):
        ex.add(sx, sy, img - images[-1])  # subtract the projector's black level
    pixels, crops = ex.result()
    assert len(pixels) > 10
    exact = scene.footprints(pixels)
    cosine = (crops * exact).sum((1, 2, 3)) / np.sqrt((crops**2).sum((1, 2, 3)) * (exact**2).sum((1, 2, 3)))
    energy = crops.sum((1, 2, 3)) / exact.sum((1, 2, 3))
    assert np.median(cosine) > 0.8
    assert 0.8 < np.median(energy) < 1.3


def _stretched_scene(h=24, w=30, spacing=10):
    """Camera pixel x sees projector columns [2x - 1, 2x + 1): |det J| = 2. A dot at an even projector
    column 2x lights half of camera pixel x (area model), spread by a 3x3 kernel of energy 1."""
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    xp, yp = 2 * xx, yy.copy()
    ker = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32) / 16

    def frame(sx, sy):
        img = np.zeros((h, w), np.float32)
        for dy in range(sy, h, spacing):
            for dx in range(sx, 2 * w, spacing):
                if dx % 2 == 0:
                    img[dy, dx // 2] += 0.5
        return np.repeat(convolve(img, ker, mode="constant")[..., None], 3, -1)

    return xp, yp, np.ones((h, w), bool), frame


def test_crops_are_normalised_per_camera_pixel():
    """A dot is one projector pixel; the footprint is one camera pixel's light: energy x |det J|."""
    xp, yp, mask, frame = _stretched_scene()
    energies = {}
    for per_pixel in (False, True):
        ex = DotGridExtractor(xp, yp, mask, 10, 9, per_camera_pixel=per_pixel)
        ex.add(0, 0, frame(0, 0))
        pixels, crops = ex.result()
        inner = (pixels[:, 0] > 1) & (pixels[:, 0] < 22) & (pixels[:, 1] > 1) & (pixels[:, 1] < 28)
        energies[per_pixel] = crops[inner].sum(axis=(1, 2))
    np.testing.assert_allclose(energies[False], 0.5, atol=1e-5)
    np.testing.assert_allclose(energies[True], 1.0, atol=1e-5)


def test_neighbouring_dots_are_cut_from_a_crop():
    """Dots 10 projector px apart are 5 camera px apart here, inside a 9 px crop: only the own dot stays."""
    xp, yp, mask, frame = _stretched_scene()
    ker = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32) / 16
    for isolate, expect_neighbours in ((False, True), (True, False)):
        ex = DotGridExtractor(xp, yp, mask, 10, 9, isolate=isolate)
        ex.add(0, 0, frame(0, 0))
        pixels, crops = ex.result()
        i = int(np.flatnonzero((pixels == (10, 10)).all(axis=1))[0])
        own = np.zeros((9, 9), np.float32)
        own[3:6, 3:6] = ker  # x |det J| = 2 of the half-pixel dot
        has_neighbours = not np.allclose(crops[i, ..., 0], own, atol=1e-6)
        assert has_neighbours == expect_neighbours


def test_jacobian_area_of_an_affine_map_and_at_a_depth_edge():
    from sssphase_core.processing.footprints import jacobian_area

    yy, xx = np.mgrid[:20, :30].astype(np.float32)
    area = jacobian_area(1.5 * xx + 0.2 * yy, 0.1 * xx + 0.8 * yy)
    np.testing.assert_allclose(area, 1.5 * 0.8 - 0.2 * 0.1, rtol=1e-5)
    jump = np.where(xx < 15, xx, xx + 500)  # a correspondence jump is no area
    assert jacobian_area(jump, yy).max() <= 8.0 + 1e-6
    assert np.isfinite(jacobian_area(np.full((1, 5), np.nan), np.full((1, 5), np.nan))).all()


def test_dark_reference_is_unbiased_and_far_less_noisy():
    from sssphase_core.processing.footprints import dark_reference

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:96, :128].astype(np.float32)
    white = np.repeat((0.4 + 0.5 * (np.sin(xx / 9) > 0))[..., None], 3, -1).astype(np.float32)
    true_black = 0.003 * white
    black = true_black + rng.normal(0, 7e-4, white.shape).astype(np.float32)
    est = dark_reference(black, white)
    inner = (slice(8, -8), slice(8, -8))
    assert abs(float((est - true_black)[inner].mean())) < 5e-5
    assert float((est - true_black)[inner].std()) < 0.25 * float((black - true_black)[inner].std())


def test_transport_weights_count_each_dot_once():
    """Camera finer than the projector (|det J| = 0.25): 4 pixels round to each dot, each stores the dot's
    response x 0.25; the weights 1 / (n |det J|) = 1 make the 4 copies sum to the response once."""
    from sssphase_core.processing.footprints import transport_weights

    yy, xx = np.mgrid[:16, :16].astype(np.float32)
    xp, yp = 0.5 * xx + 0.1, 0.5 * yy + 0.1  # camera pixels 2x and 2x+1 round to projector pixel x
    mask = np.ones((16, 16), bool)
    pixels = np.argwhere(mask)
    w = transport_weights(pixels, xp, yp, mask)
    inner = ((pixels >= 1) & (pixels < 14)).all(axis=1)  # border pixels share a dot with pixels outside
    np.testing.assert_allclose(w[inner] * 0.25 * 4, 1.0, rtol=1e-5)


def _coarse_camera(h=24, w=32, scale=2):
    """A camera coarser than the projector (each camera pixel sees scale x scale projector pixels, as on a
    grazing surface): projector pixel (x, y) lands in camera pixel (y // scale, x // scale) and spreads by a
    3 x 3 kernel there."""
    wp, hp = w * scale, h * scale
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    xp, yp = (xx + 0.5) * scale - 0.5, (yy + 0.5) * scale - 0.5
    ker = np.array([[0.05, 0.1, 0.05], [0.1, 0.4, 0.1], [0.05, 0.1, 0.05]])
    albedo = np.random.default_rng(0).uniform(0.3, 1.0, (hp, wp))

    def camera(pattern):  # (hp, wp) light -> (h, w, 3) camera image
        binned = (pattern * albedo).reshape(h, scale, w, scale).sum(axis=(1, 3))
        img = convolve(binned, ker, mode="constant")
        return np.repeat(img[..., None], 3, -1).astype(np.float32)

    return xp, yp, np.ones((h, w), bool), camera, (wp, hp)


def test_the_transport_keeps_every_dot_where_the_camera_is_coarser_than_the_projector():
    from sssphase_core.processing.footprints import DotTransportExtractor
    from sssphase_core.relight import DotTransport, Projection, relight

    xp, yp, mask, camera, (wp, hp) = _coarse_camera()
    spacing, k = 8, 7
    tx = DotTransportExtractor(xp, yp, mask, spacing, k, (wp, hp))
    for sy in range(spacing):
        for sx in range(spacing):
            tx.add(sx, sy, camera(dot_grid(wp, hp, spacing, sx, sy)))
    pixels, dots, crops = tx.result()
    assert len(dots) == wp * hp  # four dots per camera pixel, each stored once
    proj = Projection(xp, yp, mask, (wp, hp), gamma=1.0, black=0.0)
    rng = np.random.default_rng(1)
    checker = ((np.arange(wp)[None] // 5 + np.arange(hp)[:, None] // 5) % 2).astype(np.float32)
    for pattern in (np.ones((hp, wp), np.float32), checker, rng.random((hp, wp)).astype(np.float32)):
        relit = relight(DotTransport(pixels, dots, crops, noise=0.0), proj, [pattern], k)[0]
        np.testing.assert_allclose(relit, camera(pattern), atol=2e-3)  # float16 crops


def test_the_transport_keeps_dots_that_land_where_nothing_was_decoded():
    """A silhouette: the outer camera pixels have no decoded coordinate (grazing, low modulation), but
    the light of the dots landing there scatters into decoded pixels. Those dots are kept (placed at
    the nearest decoded pixel), so the decoded pixels next to the edge relight as the camera sees them."""
    from sssphase_core.processing.footprints import DotTransportExtractor
    from sssphase_core.relight import DotTransport, Projection, relight

    xp, yp, mask, camera, (wp, hp) = _coarse_camera()
    mask = mask.copy()
    mask[:, :6] = False  # a band the decoder rejected, two camera px wider than the kernel's reach
    spacing, k = 16, 9  # a frame's other dots stay outside each window (undecoded pixels cannot be cut)
    tx = DotTransportExtractor(xp, yp, mask, spacing, k, (wp, hp))
    for sy in range(spacing):
        for sx in range(spacing):
            tx.add(sx, sy, camera(dot_grid(wp, hp, spacing, sx, sy)))
    pixels, dots, crops = tx.result(drop_noise=False)  # noise-free: the ring holds only the band dots' light
    assert (dots[:, 0] < 12).sum() >= 5 * hp  # most of the rejected band's dots within reach of a decoded pixel
    proj = Projection(xp, yp, mask, (wp, hp), gamma=1.0, black=0.0)
    pattern = np.random.default_rng(2).random((hp, wp)).astype(np.float32)
    relit = relight(DotTransport(pixels, dots, crops, noise=0.0), proj, [pattern], k)[0]
    np.testing.assert_allclose(relit[4:-4, 6:-4], camera(pattern)[4:-4, 6:-4], atol=2e-3)


def test_per_camera_pixel_crops_lose_the_dots_between_pixel_centres():
    """Why the measured backend relights from the per-dot transport: the per-pixel crops store one
    dot per camera pixel, so where a pixel sees four their weighted sum misses three of them."""
    from sssphase_core.processing.footprints import transport_weights
    from sssphase_core.relight import Projection, nearest_measured_source, relight

    xp, yp, mask, camera, (wp, hp) = _coarse_camera()
    spacing, k = 8, 7
    ex = DotGridExtractor(xp, yp, mask, spacing, k)
    for sy in range(spacing):
        for sx in range(spacing):
            ex.add(sx, sy, camera(dot_grid(wp, hp, spacing, sx, sy)))
    pixels, crops = ex.result()
    white = camera(np.ones((hp, wp), np.float32))
    proj = Projection(xp, yp, mask, (wp, hp), gamma=1.0, black=0.0)
    src = nearest_measured_source(pixels, crops, white, transport_weights(pixels, xp, yp, mask))
    relit = relight(src, proj, [np.ones((hp, wp), np.float32)], k)[0]
    assert np.median(relit[4:-4, 4:-4] / white[4:-4, 4:-4]) < 0.5


def test_streamed_crops_in_a_session_equal_the_extractors_own(tmp_path):
    """The capture writes crops to the session as dot frames arrive (bounded memory at 1080p, K = 90):
    in arrival order, float16, their pixels (and dots) in the same order, checksummed like any array."""
    from sssphase_core.capture import CropStream
    from sssphase_core.processing.footprints import DotTransportExtractor
    from sssphase_core.store.session import Session, array_checksum

    h, w = 30, 40
    xp, yp, mask, frame = _scene(h, w)
    session = Session.create(tmp_path, "obj", n_views=1)
    writer = session.begin_view(0)
    grid = CropStream(writer, "footprints", DotGridExtractor(xp, yp, mask, SPACING, K), chunk_bytes=7 * K * K * 3 * 2)
    transport = CropStream(writer, "transport", DotTransportExtractor(xp, yp, mask, SPACING, K, (w, h)), drop_noise=True)
    assert grid.array.rows == 7  # several chunks, flushed while frames still arrive
    reference = DotGridExtractor(xp, yp, mask, SPACING, K)
    for sy in range(SPACING):
        for sx in range(SPACING):
            grid.add(sx, sy, frame(sx, sy))
            transport.add(sx, sy, frame(sx, sy))
            reference.add(sx, sy, frame(sx, sy))
        if sy == 2:
            assert 0 < grid.array.arr.shape[0] and grid.array.n_held < 7  # written as it goes
    info_grid, info_tx = grid.close(), transport.close()
    writer.commit({})
    px, crops = session.load(0, "footprints/pixels"), session.load(0, "footprints/crops")
    assert crops.dtype == np.float16 and info_grid["count"] == len(px) == mask.sum()
    ref_px, ref_crops = reference.result()
    order = np.lexsort((px[:, 1], px[:, 0]))
    np.testing.assert_array_equal(px[order], ref_px)
    np.testing.assert_allclose(crops[order].astype(np.float32), ref_crops, rtol=1e-3, atol=1e-6)
    assert session.manifest["views"]["0"]["arrays"]["footprints/crops"]["checksum"] == array_checksum(crops)
    dots = session.load(0, "transport/dots")
    assert info_tx["dots"] == len(dots) == len(session.load(0, "transport/pixels")) and info_tx["noise"] >= 0
    assert len(np.unique(dots[:, 1] * w + dots[:, 0])) == len(dots)


def test_crop_noise_reads_the_ring_or_else_the_outer_part_of_each_crops_own_cell():
    """The noise floor that denoises the captured transport: from the crops' outer ring where it sees
    something (off the surface), and from inside each crop's own cell where the surface fills the crops
    (the ring then lies in other dots' cells, is zeroed, and used to read 0: nothing was denoised)."""
    from sssphase_core.processing.footprints import crop_noise

    rng = np.random.default_rng(0)
    k, sigma = 16, 0.01
    r = np.hypot(*np.meshgrid(np.arange(k) - k // 2, np.arange(k) - k // 2, indexing="ij"))
    clean = np.repeat((0.09 * np.exp(-(r**2) / (2 * 1.2**2)))[None, ..., None], 200, axis=0).repeat(3, axis=-1)
    noisy = clean + rng.normal(0, sigma, clean.shape)
    assert crop_noise(noisy) == pytest.approx(sigma, rel=0.1)  # the ring holds noise
    cell = (np.abs(np.arange(k) - k // 2) <= 4)[:, None] & (np.abs(np.arange(k) - k // 2) <= 4)[None, :]
    own = noisy * cell[None, ..., None]  # a 9 x 9 cell: the ring lies in other dots' cells
    assert crop_noise(own) == pytest.approx(sigma, rel=0.15)
    assert crop_noise(clean * cell[None, ..., None]) < 0.1 * sigma  # a smooth tail is not noise
    block = np.zeros((8, k, k, 3))
    block[:, 6:10, 6:10] = 0.02
    assert crop_noise(block) == 0.0 and crop_noise(np.zeros((0, k, k, 3))) == 0.0
