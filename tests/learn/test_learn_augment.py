"""PSP augmentations act identically on the 8 images of a patch."""

from __future__ import annotations

import torch

from sssphase_core.learning import augment as A


def stack_of_identical(b: int = 6, k: int = 16) -> torch.Tensor:
    img = torch.rand(b, 1, 3, k, k)
    return img.expand(b, 8, 3, k, k).reshape(b, 24, k, k).contiguous()


def images(x: torch.Tensor) -> torch.Tensor:
    return x.view(x.shape[0], 8, 3, *x.shape[-2:])


def assert_images_identical(x: torch.Tensor) -> None:
    im = images(x)
    assert torch.allclose(im, im[:, :1].expand_as(im), atol=1e-6)


def test_weak_and_imagenet_apply_the_same_parameters_to_all_images():
    torch.manual_seed(0)
    assert_images_identical(A.weak(stack_of_identical()))
    assert_images_identical(A.imagenet(stack_of_identical()))
    # blur and intensity scaling are shared too (no flip/permutation/noise)
    x = stack_of_identical()
    assert_images_identical(A.gaussian_blur(x, (0.1, 1.0)))
    cfg = A.AugmentConfig(phase_jitter=0.0, sp_p=1.0, flip_p=0.0, permute_p=1.0)
    # permuting identical images and salt & pepper at shared positions keep them identical
    assert_images_identical(A.strong(x, cfg))


def test_psp_flip_flips_x_images_horizontally_and_y_images_vertically():
    x = torch.rand(3, 24, 8, 8)
    y = A.psp_flip(x, p=1.0)
    assert torch.equal(y[:, :12], x[:, :12].flip(-1))
    assert torch.equal(y[:, 12:], x[:, 12:].flip(-2))
    assert torch.equal(A.psp_flip(x, p=0.0), x)


def test_permutation_stays_within_each_orientation():
    torch.manual_seed(1)
    b = 32
    ids = torch.arange(8.0).view(1, 8, 1, 1, 1).expand(b, 8, 3, 4, 4).reshape(b, 24, 4, 4)
    out = images(A.permute_shifts(ids, p=1.0))[:, :, 0, 0, 0]
    assert torch.equal(out[:, :4].sort(dim=1).values, torch.arange(4.0).expand(b, 4))
    assert torch.equal(out[:, 4:].sort(dim=1).values, torch.arange(4.0, 8.0).expand(b, 4))
    assert (out != torch.arange(8.0)).any()  # something was permuted
    assert torch.equal(A.permute_shifts(ids, p=0.0), ids)


def test_blur_sigma_is_sampled_per_patch():
    torch.manual_seed(2)
    x = torch.zeros(16, 24, 15, 15)
    x[..., 7, 7] = 1.0
    peaks = A.gaussian_blur(x, (0.1, 1.0))[:, 0, 7, 7]
    assert peaks.max() - peaks.min() > 0.3  # different sigmas: sharp and wide kernels
    assert torch.allclose(A.gaussian_blur(x, (0.1, 1.0)).sum(dim=(2, 3)), torch.ones(16, 24), atol=1e-3)


def test_salt_and_pepper_hits_the_same_pixels_in_every_channel():
    torch.manual_seed(3)
    x = torch.rand(4, 24, 32, 32) * 0.5 + 0.25
    y = A.salt_and_pepper(x, p=1.0, amount=0.05)
    changed = y != x
    assert torch.equal(changed, changed[:, :1].expand_as(changed))
    frac = changed[:, 0].float().mean()
    assert 0.05 < frac < 0.15
    assert set(y[changed].unique().tolist()) <= {0.0} | set(x.amax(dim=(1, 2, 3)).tolist())


def test_two_views_are_deterministic_under_a_seed_and_differ_from_each_other():
    x = torch.rand(4, 24, 16, 16)
    torch.manual_seed(5)
    a1, a2 = A.two_views(x, "psp")
    torch.manual_seed(5)
    b1, b2 = A.two_views(x, "psp")
    assert torch.equal(a1, b1) and torch.equal(a2, b2)
    assert not torch.allclose(a1, a2)
    assert a1.shape == a2.shape == x.shape


def fringes(b: int = 4, k: int = 16, offset: float = 0.4, amp: float = 0.3) -> torch.Tensor:
    """(B, 24, K, K) 4-step fringes, x then y orientation, of one colour each: offset + amp cos(phase + shift)."""
    yy, xx = torch.meshgrid(torch.arange(k).float(), torch.arange(k).float(), indexing="ij")
    imgs = []
    for phase in (2 * torch.pi * xx / 6, 2 * torch.pi * yy / 6):
        for s in range(4):
            img = offset + amp * torch.cos(phase + s * torch.pi / 2)
            imgs.append(torch.stack([img, 0.5 * img, 0.25 * img]))
    return torch.cat(imgs).expand(b, 24, k, k).contiguous()


def modulation(x: torch.Tensor) -> torch.Tensor:
    """(B, 2, 3, K, K) B/A of each orientation and colour."""
    s = x.view(x.shape[0], 2, 4, 3, *x.shape[-2:])
    return 0.5 * torch.hypot(s[:, :, 0] - s[:, :, 2], s[:, :, 1] - s[:, :, 3]) / s.mean(dim=2)


def test_camera_steps_keep_flat_light_and_the_fringe_offset():
    torch.manual_seed(0)
    flat = torch.rand(3, 1, 3, 1, 1).expand(3, 8, 3, 12, 12).reshape(3, 24, 12, 12).contiguous()
    # demosaicing a flat colour gives it back (both interpolators, every phase)
    assert torch.allclose(A.random_bayer(flat, 1.0), flat, atol=1e-5)
    assert torch.equal(A.random_bayer(flat, 0.0), flat)
    x = fringes()
    curved = A.fringe_gamma(x, (0.7, 0.7), 1.0)
    s0, s1 = x.view(4, 2, 4, 3, 16, 16), curved.view(4, 2, 4, 3, 16, 16)
    assert torch.allclose(s1.mean(dim=2), s0.mean(dim=2), atol=1e-5)  # the offset (the energy) is kept
    assert (modulation(curved) < modulation(x) - 0.05).all()  # an exponent < 1 flattens the fringes
    assert torch.allclose(A.fringe_gamma(x, (1.0, 1.0), 1.0), x, atol=1e-5)
    # the Bayer resampling of fringes lowers the colours' modulation somewhere, never raising the offset's mean
    re = A.random_bayer(x, 1.0)
    assert not torch.allclose(re, x, atol=1e-3)
    assert abs(float(re.mean() - x.mean())) < 0.01 * float(x.mean())


def test_sensor_noise_has_the_shot_and_read_variance_it_draws():
    torch.manual_seed(0)
    x = torch.full((64, 24, 32, 32), 0.5)
    noisy = A.sensor_noise(x, (1e3, 1e3), (0.01, 0.01), 1.0)
    var = float((noisy - x).var())
    assert abs(var - (0.5 / 1e3 + 0.01**2)) < 0.03 * (0.5 / 1e3 + 0.01**2)
    assert abs(float((noisy - x).mean())) < 1e-3
    assert torch.equal(A.sensor_noise(x, (1e3, 1e3), (0.01, 0.01), 0.0), x)


def test_the_camera_augmentation_is_seeded_per_patch_and_finite_on_dark_and_bright_patches():
    x = fringes(b=8)
    x[0] = 0.0  # a patch off the surface
    x[1] *= 50.0  # a specular highlight's
    torch.manual_seed(3)
    a = A.camera(x)
    torch.manual_seed(3)
    assert torch.equal(a, A.camera(x))
    assert torch.isfinite(a).all() and a.shape == x.shape
    assert float(a[0].abs().max()) < 0.02  # dark stays dark: only read noise
    changed = (a - x).flatten(1).abs().amax(dim=1) > 1e-3
    assert 0 < int(changed.sum()) <= 8  # drawn per patch


def test_phase_shift_moves_the_fringes_and_keeps_what_a_pixel_is():
    """Offset, amplitude and the non-sinusoidal remainder stay per pixel and colour; the phase moves by one
    angle per orientation and patch, shared by every pixel and colour."""
    import math

    b, k = 5, 8
    g = torch.Generator().manual_seed(0)
    phi = torch.rand(b, 2, 1, 3, k, k, generator=g) * 2 * math.pi
    amp, off = 0.3 * torch.rand(b, 2, 1, 3, k, k, generator=g), 0.5 + torch.rand(b, 2, 1, 3, k, k, generator=g)
    rest = 0.01 * torch.rand(b, 2, 1, 3, k, k, generator=g)  # a response curve's harmonic: no sinusoid's part
    shift = torch.arange(4).view(1, 1, 4, 1, 1, 1)
    x = (off + rest * (-1) ** shift + amp * torch.cos(phi - shift * math.pi / 2)).reshape(b, 24, k, k)

    def parts(t: torch.Tensor) -> tuple[torch.Tensor, ...]:
        i0, i1, i2, i3 = t.view(b, 2, 4, 3, k, k).unbind(2)
        return (i0 + i1 + i2 + i3) / 4, (i0 - i1 + i2 - i3) / 4, torch.atan2(i1 - i3, i0 - i2), torch.hypot(i0 - i2, i1 - i3) / 2

    torch.manual_seed(1)
    y = A.phase_shift(x, p=1.0)
    (a0, r0, p0, m0), (a1, r1, p1, m1) = parts(x), parts(y)
    assert torch.allclose(a1, a0, atol=1e-6) and torch.allclose(r1, r0, atol=1e-6) and torch.allclose(m1, m0, atol=1e-5)
    moved = torch.remainder(p1 - p0, 2 * math.pi)  # (b, 2, 3, k, k): one angle per patch and orientation
    flat = moved.flatten(2)
    spread = torch.minimum(flat - flat[..., :1], 2 * math.pi - (flat - flat[..., :1])).abs()
    assert float(spread.max()) < 1e-3 and float(moved.std()) > 0.5  # shared within a patch, different between them
    assert torch.equal(A.phase_shift(x, p=0.0), x)
