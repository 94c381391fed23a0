"""Camera raw processing (median, demosaicing, develop, HDR merge) and the simulated sensor."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.processing import isp
from sssphase_core.sim.sensor import SensorConfig, bayer_mosaic, expose, expose_noise_free


def smooth_image(h: int = 64, w: int = 96) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([0.5 + 0.3 * np.sin(xx / 9.0), 0.4 + 0.2 * np.cos(yy / 7.0), 0.3 + 0.2 * np.sin((xx + yy) / 11.0)], -1)


@pytest.mark.parametrize(("method", "tol"), [("malvar", 0.01), ("opencv", 0.01)])
def test_demosaic_recovers_a_smooth_image(method, tol):
    img = smooth_image()
    out = isp.demosaic(bayer_mosaic(img), method)
    assert out.shape == img.shape and out.dtype == np.float32
    assert np.abs(out - img)[4:-4, 4:-4].max() < tol  # colour order right, interpolation smooth


@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 4), (192, 256)])
def test_malvar_is_colour_demosaicings_malvar_bit_for_bit(shape):
    """Our OpenCV Malvar-He-Cutler (no 1.7 s import of colour-science in every process that develops a frame)
    against colour-demosaicing's, the reference (a development dependency): equal in float64, borders and
    frames narrower than the 5 x 5 kernels included."""
    import warnings

    with warnings.catch_warnings():  # the package imports deprecated scipy namespaces
        warnings.simplefilter("ignore", DeprecationWarning)
        from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004

    raw = np.random.default_rng(sum(shape)).random(shape) * 4095.0
    np.testing.assert_array_equal(isp.malvar(raw), demosaicing_CFA_Bayer_Malvar2004(raw, "RGGB"))
    assert isp.demosaic(raw.astype(np.uint16)).dtype == np.float32


def test_bayer_mosaic_is_rggb():
    img = np.zeros((4, 4, 3))
    img[..., 0], img[..., 1], img[..., 2] = 1.0, 2.0, 3.0
    raw = bayer_mosaic(img)
    assert raw[0, 0] == 1 and raw[0, 1] == 2 and raw[1, 0] == 2 and raw[1, 1] == 3


def test_median_works_per_bayer_plane():
    img = np.zeros((16, 16, 3))
    img[..., 0], img[..., 1], img[..., 2] = 100.0, 200.0, 300.0
    raw = bayer_mosaic(img).astype(np.uint16)
    np.testing.assert_array_equal(isp.median3_bayer(raw), raw)  # planes never mix
    hot = raw.copy()
    hot[6, 6] = 4000  # a hot red pixel
    out = isp.median3_bayer(hot)
    assert out[6, 6] == 100 and out.dtype == np.uint16


def test_develop_subtracts_black_and_scales():
    raw = np.full((8, 8), 1256, np.uint16)
    np.testing.assert_allclose(isp.develop(raw, 256, 2000.0), 0.5, atol=1e-6)
    with pytest.raises(InputError):
        isp.develop(np.zeros((7, 8), np.uint16), 0, 1.0)


def test_sensor_noise_bit_depth_and_clipping():
    cfg = SensorConfig(bit_depth=12, full_well=10000, white_fraction=0.6, read_noise=3.0, black_level=256)
    linear = np.broadcast_to(smooth_image(), (2, 64, 96, 3)) * np.array([1.0, 5.0])[:, None, None, None]
    a = expose(linear, cfg, np.random.default_rng(3))
    b = expose(linear, cfg, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)  # seeded
    assert a.dtype == np.uint16 and a.shape == (2, 64, 96) and a.max() <= 4095
    assert (a[1] == 4095).mean() > 0.5  # 5x white saturates
    dev = isp.develop(a[0], cfg.black_level, cfg.dn_per_unit(1.0), median=False)
    truth = bayer_mosaic(smooth_image())
    err = bayer_mosaic(dev) - truth
    # Poisson-Gaussian: variance = x / (electrons per unit) + (read / electrons per unit)^2 + quantisation
    predicted = np.sqrt(truth / cfg.electrons_per_unit + (cfg.read_noise / cfg.electrons_per_unit) ** 2)
    np.testing.assert_allclose(cfg.noise_std(truth), np.sqrt(predicted**2 + 1 / 12 / (cfg.dn_per_unit()) ** 2))
    assert abs(err.std() / np.sqrt(np.mean(cfg.noise_std(truth) ** 2)) - 1) < 0.1
    assert abs(err.mean()) < 0.003


def test_white_reads_sixty_percent_of_full_scale():
    cfg = SensorConfig()
    raw = expose(np.ones((1, 32, 32, 3)), cfg, np.random.default_rng(0))
    frac = (raw.mean() - cfg.black_level) / (cfg.max_dn - cfg.black_level)
    assert abs(frac - cfg.white_fraction) < 0.01


def test_hdr_merge_recovers_values_beyond_saturation():
    cfg = SensorConfig()
    truth = smooth_image() * 4.0  # up to ~3.2, well above the 1.67 that clips at exposure 1
    exposures = [1.0, 0.25, 0.0625]
    rng = np.random.default_rng(5)
    frames = np.stack([isp.develop(expose(truth[None], cfg, rng, t)[0], cfg.black_level, cfg.dn_per_unit(t))
                       for t in exposures])
    clipped = frames[0] >= isp.SATURATION_MARGIN * cfg.saturation(1.0)
    assert clipped.mean() > 0.2
    merged = isp.hdr_merge(frames, exposures, cfg.saturation(1.0))
    inner = (slice(4, -4), slice(4, -4))
    rel = np.abs(merged - truth)[inner] / truth[inner]
    assert np.isfinite(merged).all()
    assert rel[clipped[inner]].mean() < 0.02 and np.percentile(rel, 99) < 0.1
    assert np.abs(frames[0] - truth)[inner][clipped[inner]].mean() > 0.3  # the single exposure was wrong
    with_read = isp.hdr_merge(frames, exposures, cfg.saturation(1.0), electrons_per_unit=cfg.electrons_per_unit,
                              read_noise=cfg.read_noise)
    assert np.abs(with_read - truth)[inner].mean() <= np.abs(merged - truth)[inner].mean() * 1.05


def test_hdr_merge_leaves_out_what_demosaicing_spread_from_clipped_neighbours():
    """A bright red checkerboard: the long exposure's red clips on the squares, and demosaicing carries
    that into the neighbouring pixels (in every colour) below the clipping level. Those pixels must come
    from the shorter exposures too."""
    cfg = SensorConfig()
    yy, xx = np.mgrid[:64, :64]
    square = ((yy // 6 + xx // 6) % 2).astype(np.float64)
    truth = np.stack([0.1 + 2.9 * square, 0.05 + 0.3 * square, 0.05 + 0.1 * square], -1)  # red up to 3.0
    exposures = [4.0, 1.0, 0.25]
    frames = np.stack([isp.develop(expose_noise_free(truth[None], cfg, t)[0], cfg.black_level, cfg.dn_per_unit(t))
                       for t in exposures])
    unclipped = frames[-1]  # 0.25 clips at 6.7: the camera's image of the truth, demosaicing's edges and all
    err = lambda merged: np.abs(merged - unclipped).max()  # noqa: E731
    blind = isp.hdr_merge(frames, exposures, cfg.saturation(1.0), spread=0)
    merged = isp.hdr_merge(frames, exposures, cfg.saturation(1.0))
    assert err(blind) > 0.1  # values spread from clipped samples pass the per-sample test
    assert err(merged) < 1e-4
    flat = np.stack([isp.develop(expose_noise_free(np.full((1, 16, 16, 3), 0.2), cfg, t)[0], cfg.black_level,
                                 cfg.dn_per_unit(t)) for t in exposures])
    np.testing.assert_allclose(isp.hdr_merge(flat, exposures, cfg.saturation(1.0)),  # nothing clips: unchanged
                               isp.hdr_merge(flat, exposures, cfg.saturation(1.0), spread=0))


def test_hdr_merge_keeps_the_shortest_exposure_when_everything_clips():
    frames = np.array([[2.0], [1.5]])
    out = isp.hdr_merge(frames, [1.0, 0.5], saturation=1.0)  # clips at 1.0 and 2.0: both saturated
    assert out[0] == pytest.approx(1.5)
    with pytest.raises(InputError):
        isp.hdr_merge(frames, [1.0], saturation=1.0)


def test_capture_matches_render_on_average(apple):
    pattern = np.ones((1,) + apple.shape_projector, np.float32)
    clean = apple.render(pattern)[0]
    noisy = apple.capture(pattern, np.random.default_rng(0))[0]
    raw = apple.capture(pattern, np.random.default_rng(0), raw=True)
    assert raw.dtype == np.uint16 and raw.shape == (1,) + apple.shape
    inner = apple.mask & (clean[..., 1] > 0.2)
    assert abs(np.median(noisy[inner] / clean[inner]) - 1) < 0.03
    dim = apple.capture(pattern, np.random.default_rng(0), exposure=0.25)[0]
    assert abs(np.median(dim[inner] / clean[inner]) - 1) < 0.05  # developed frames stay in linear units


def test_every_bayer_layout_develops_to_the_image_and_a_wrong_one_does_not():
    """A mosaic in GRBG, GBRG or BGGR is developed by re-phasing it to RGGB; developing it as RGGB
    instead swaps colours (what a GRBG camera's frames would have become)."""
    import cv2

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.random((64, 80, 3)).astype(np.float32), (0, 0), 4) * 3 + 0.2
    inner = (slice(4, -4), slice(4, -4))
    for layout in isp.BAYER_LAYOUTS:
        mosaic = bayer_mosaic(img, layout)
        assert mosaic.shape == (64, 80)
        good = isp.develop(mosaic, 0.0, 1.0, median=False, layout=layout)
        assert good.shape == img.shape and np.abs(good - img)[inner].max() < 0.02, layout
        seen = isp.through_camera(img[None], layout=layout)[0]
        np.testing.assert_allclose(seen, good, atol=1e-6)
        if layout != "RGGB":
            assert np.abs(isp.develop(mosaic, 0.0, 1.0, median=False) - img)[inner].max() > 0.2, layout
    with pytest.raises(InputError, match="unknown Bayer layout 'RGBG'"):
        isp.develop(np.zeros((4, 4)), 0.0, 1.0, layout="RGBG")


def test_a_bracket_that_clips_below_the_rigs_saturation_is_told_apart_from_a_dim_scene():
    """A rig file's saturation of 4095 (a sensor's top code) where developed frames clip at 1: the HDR merge
    trusted the clipped samples (relit 25 dB where the right level gave 38)."""
    from sssphase_core.processing.isp import clipping_below

    rng = np.random.default_rng(0)
    scene = rng.gamma(2.0, 0.3, (64, 64, 3))  # light with a bright tail
    exposures = [0.25, 1.0, 4.0]
    frames = np.stack([np.minimum(scene * t, 1.0) / t for t in exposures])  # the camera clips at 1 on the sensor
    assert clipping_below(frames, exposures, 4095.0) == pytest.approx(1.0)
    assert clipping_below(frames, exposures, 1.0) is None  # the right level
    dim = np.round(scene / scene.max() * 40) / 255  # a dim 8-bit scene: its brightest codes shared, nothing clipped
    assert clipping_below(np.stack([dim / t for t in exposures]), exposures, 4095.0) is None
