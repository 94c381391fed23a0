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
