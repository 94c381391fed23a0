"""The transport-footprints benchmark (benchmarks/transport_footprints.py) measures what it says."""


import numpy as np
from benchmark_script import load_benchmark

tf = load_benchmark("transport_footprints")


def test_dots_seen_by_one_pixel_add_up_in_its_footprint():
    rng = np.random.default_rng(0)
    crops = rng.random((4, 5, 5, 3)).astype(np.float32)
    pixels = np.array([[2, 7], [0, 1], [2, 7], [1, 0]])
    px, sums = tf.sum_into_pixels(pixels, crops, width=10)
    assert px.tolist() == [[0, 1], [1, 0], [2, 7]]  # row-major, each pixel once
    np.testing.assert_allclose(sums[2], crops[0] + crops[2], rtol=1e-6)
    np.testing.assert_array_equal(sums[0], crops[1])
    assert np.isclose(sums.sum(), crops.sum(), rtol=1e-6)  # no light lost or added


def test_ring_shares_place_a_delta_in_the_centre_and_a_ring_where_it_lies():
    f = np.zeros((2, 21, 21, 3), np.float32)
    f[0, 10, 10] = 1.0
    f[1, 10, 10 + 4] = f[1, 10, 10 - 4] = 0.5  # 4 px from the centre: the 3-6 px ring
    f[1, 0, 0] = -1.0  # negative values count as no light
    delta = np.zeros(len(tf.RINGS))
    delta[0] = 1.0
    np.testing.assert_allclose(tf.ring_shares(f[:1]), delta)
    ring = np.zeros(len(tf.RINGS))
    ring[3] = 1.0
    np.testing.assert_allclose(tf.ring_shares(f[1:]), ring)
    np.testing.assert_allclose(tf.ring_shares(f).sum(), 1.0, rtol=1e-6)


def test_signed_ring_shares_let_zero_mean_noise_cancel():
    rng = np.random.default_rng(0)
    f = np.zeros((4000, 21, 21, 3), np.float32)
    f[:, 10, 10] = 0.05
    f += rng.normal(0, 1e-3, f.shape).astype(np.float32)  # camera noise over the whole window
    signed = tf.signed_ring_shares(f)
    assert signed[0] > 0.97 and abs(signed[1:]).max() < 0.02
    assert tf.ring_shares(f)[0] < 0.6  # clipped per crop, the noise's positive half is a tail


def test_a_noisy_reference_is_taken_out_of_the_margins_it_compresses():
    rng = np.random.default_rng(0)
    truth = rng.random((200, 200, 3)).astype(np.float64)
    halves = [truth + rng.normal(0, 0.02, truth.shape) for _ in range(2)]
    reference = (halves[0] + halves[1]) / 2  # noise variance 0.02**2 / 2
    where = np.ones(truth.shape[:2], bool)
    noise = tf.reference_noise(halves[0], halves[1], where)
    assert np.isclose(noise, 0.02**2 / 2, rtol=0.03)
    good = truth + rng.normal(0, 0.005, truth.shape)  # true margin: 20 log10(0.02 / 0.005) = 12.04 dB
    base = truth + rng.normal(0, 0.02, truth.shape)
    mse = lambda img: float(np.mean((img - reference) ** 2))  # noqa: E731
    raw_margin = 10 * np.log10(mse(base) / mse(good))
    psnr, margin = tf.noise_corrected(mse(good), mse(base), noise)
    assert raw_margin < 5  # the reference's noise hides most of it
    assert abs(margin - 12.04) < 0.6 and abs(psnr - 10 * np.log10(1 / 0.005**2)) < 0.6


def test_ring_averaging_keeps_each_rings_energy_and_drops_the_angle():
    rng = np.random.default_rng(1)
    f = rng.random((3, 11, 11, 3)).astype(np.float32)
    avg = tf.ring_averaged(f)
    d = np.arange(11) - 5
    ring = np.rint(np.hypot(d[:, None], d[None, :]))
    for r in (0, 1, 3, 5):
        sel = ring == r
        np.testing.assert_allclose(avg[:, sel].sum(axis=1), f[:, sel].sum(axis=1), rtol=1e-5)
        assert np.ptp(avg[:, sel], axis=1).max() < 1e-6  # one value per ring
    np.testing.assert_allclose(avg[:, 5, 7], avg[:, 7, 5], rtol=1e-6)  # symmetric under a quarter turn


def test_one_shape_for_the_view_keeps_each_pixels_energy():
    rng = np.random.default_rng(2)
    f = rng.random((5, 7, 7, 3)).astype(np.float32)
    one = tf.mean_shape(f)
    np.testing.assert_allclose(one.sum(axis=(1, 2)), f.sum(axis=(1, 2)), rtol=1e-5)
    shapes = one / one.sum(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(shapes, np.broadcast_to(shapes[:1], shapes.shape), rtol=1e-5, atol=1e-7)
    assert not np.allclose(one, f)


def test_a_dot_between_pixels_is_shared_by_overlap_and_recentred_on_each():
    k = 7
    crop = np.zeros((1, k, k, 1), np.float32)
    crop[0, 3, 3] = 1.0  # light where the crop's centre pixel (5, 5) is
    crop[0, 3, 4] = 2.0  # and one pixel to its right
    # the dot lit the surface a quarter of a pixel below and half a pixel right of pixel (5, 5)
    px, fp = tf.spread_over_pixels(np.array([[5.25, 5.5]]), crop, np.array([[5, 5]]), (10, 10))
    assert px.tolist() == [[5, 5], [5, 6], [6, 5], [6, 6]]
    weights = {(5, 5): 0.75 * 0.5, (5, 6): 0.75 * 0.5, (6, 5): 0.25 * 0.5, (6, 6): 0.25 * 0.5}
    for (y, x), f in zip(px.tolist(), fp, strict=True):
        expect = np.zeros((k, k), np.float32)  # the same light, in the frame of pixel (y, x)
        expect[3 - (y - 5), 3 - (x - 5)] = 1.0
        expect[3 - (y - 5), 4 - (x - 5)] = 2.0
        np.testing.assert_allclose(f[..., 0], weights[(y, x)] * expect, atol=1e-7)
    assert np.isclose(fp.sum(), crop.sum(), rtol=1e-6)  # nothing lost inside the image


def test_a_dot_on_a_pixel_centre_stays_whole_in_that_pixel_and_light_off_the_image_is_dropped():
    crop = np.random.default_rng(1).random((2, 5, 5, 3)).astype(np.float32)
    px, fp = tf.spread_over_pixels(np.array([[2.0, 3.0], [0.0, -0.5]]), crop, np.array([[2, 3], [0, 0]]), (4, 6))
    assert px.tolist() == [[0, 0], [2, 3]]
    np.testing.assert_allclose(fp[1], crop[0], rtol=1e-6)
    shifted = np.zeros_like(crop[1])  # half of the second dot falls off the image's left edge
    shifted[:, :] = 0.5 * crop[1]
    np.testing.assert_allclose(fp[0], shifted, rtol=1e-6)


def test_a_firefly_in_the_white_capture_leaves_only_its_own_pixel_out():
    yy, xx = np.mgrid[:20, :30]
    white = np.repeat((0.3 + 0.01 * xx + 0.005 * yy)[..., None], 3, axis=-1).astype(np.float32)  # smooth shading
    white[5, 7, 1] *= 3.0  # one colour of one pixel: a Monte-Carlo firefly
    white[12:, :, :] = 0.0  # dark: the floor keeps zero and near-zero pixels steady
    white[15, 3] = 0.0008  # within 0.1 of the 0.01 floor of a dark neighbourhood
    steady = tf.steady_white(white)
    assert not steady[5, 7]
    assert steady.sum() == steady.size - 1
