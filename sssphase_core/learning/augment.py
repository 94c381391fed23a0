"""Augmentations for 24-channel PSP patches (8 images x RGB), applied identically to all 8 images.

Tensors are (B, 24, K, K) with channel ``img * 3 + c``; images 0-3 are the x-orientation shifts
(vertical stripes), 4-7 the y-orientation shifts. Every random parameter is drawn once per patch
from torch's global RNG (the training loop seeds it per step, which makes resume exact) and shared
by the 8 images; only the per-pixel noise of the phase jitter is drawn independently per value.

* ``weak``: random resized crop (side 80/90 of the patch, resized back) + slight brightness/contrast.
* ``strong`` (the paper's PSP set, applied after ``weak``): PSP flip, phase-shift permutation,
  Gaussian blur with sigma sampled in [0.1, 1], intensity scaling, phase jitter, salt & pepper; and ours, the
  fringes moved by a random phase (:func:`phase_shift`, exact for four-step PSP).
* ``imagenet``: the SimSiam/ImageNet baseline (crop 0.2-1, colour jitter 0.4/0.4/0.4/0.1 p 0.8,
  blur, horizontal flip), applied to the whole stack at once.
* ``camera`` (decoder training, :class:`CameraAugment`): another camera's view of the same light: Bayer
  resampling and demosaicing in a random phase, lens blur, shot and read noise, a response-curve error on
  the fringes. Each keeps the light's meaning (no gains, no geometry), since the footprint target stays
  the one the training camera recorded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import kornia.augmentation as KA
import kornia.enhance as KE
import torch
from kornia.filters import gaussian_blur2d

from sssphase_core.learning.camera import rebayer

N_IMAGES = 8


@dataclass(frozen=True)
class AugmentConfig:
    """Probabilities and ranges; defaults follow the issue (the authors' values where known)."""

    crop_side: float = 80 / 90
    jitter_weak: float = 0.1
    sp_p: float = 0.3
    sp_amount: float = 0.05
    blur_sigma: tuple[float, float] = (0.1, 1.0)
    phase_jitter: float = 0.01
    flip_p: float = 0.4
    permute_p: float = 0.4
    intensity: tuple[float, float] = (0.7, 1.3)
    phase_shift_p: float = 1.0  # ours (not the paper's): exact, see :func:`phase_shift`


def _uniform(b: int, lo: float, hi: float, like: torch.Tensor) -> torch.Tensor:
    return torch.rand(b, device=like.device, dtype=like.dtype) * (hi - lo) + lo


def _per_sample(v: torch.Tensor) -> torch.Tensor:
    return v.view(-1, 1, 1, 1)


def _chance(b: int, p: float, like: torch.Tensor) -> torch.Tensor:
    return torch.rand(b, device=like.device) < p


def random_resized_crop(x: torch.Tensor, scale: tuple[float, float], ratio: tuple[float, float]) -> torch.Tensor:
    """Kornia's crop on all 24 channels at once (geometric ops accept any channel count)."""
    k = x.shape[-1]
    return KA.RandomResizedCrop((k, k), scale=scale, ratio=ratio)(x)


def brightness_contrast(x: torch.Tensor, amount: float) -> torch.Tensor:
    """Gain and contrast about the patch mean, both in [1 - amount, 1 + amount], shared by all channels."""
    b = x.shape[0]
    gain = _per_sample(_uniform(b, 1 - amount, 1 + amount, x))
    contrast = _per_sample(_uniform(b, 1 - amount, 1 + amount, x))
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    return ((x - mean) * contrast + mean) * gain


def weak(x: torch.Tensor, cfg: AugmentConfig = AugmentConfig()) -> torch.Tensor:
    area = cfg.crop_side**2
    return brightness_contrast(random_resized_crop(x, (area, area), (1.0, 1.0)), cfg.jitter_weak)


def psp_flip(x: torch.Tensor, p: float) -> torch.Tensor:
    """Flip x-orientation images horizontally and y-orientation images vertically (chosen per patch)."""
    half = 3 * N_IMAGES // 2
    flipped = torch.cat([x[:, :half].flip(-1), x[:, half:].flip(-2)], dim=1)
    return torch.where(_per_sample(_chance(x.shape[0], p, x)), flipped, x)


def permute_shifts(x: torch.Tensor, p: float) -> torch.Tensor:
    """Randomly permute the 4 phase shifts within each orientation (independent permutations)."""
    b, _, h, w = x.shape
    n = N_IMAGES // 2
    perm = torch.rand(b, 2, n, device=x.device).argsort(-1) + torch.tensor([0, n], device=x.device).view(1, 2, 1)
    keep = ~_chance(b, p, x)
    perm = torch.where(keep.view(b, 1, 1), torch.arange(N_IMAGES, device=x.device).view(1, 2, n), perm)
    idx = perm.reshape(b, N_IMAGES, 1, 1, 1).expand(b, N_IMAGES, 3, h, w)
    return x.view(b, N_IMAGES, 3, h, w).gather(1, idx).view(b, 3 * N_IMAGES, h, w)


def phase_shift(x: torch.Tensor, p: float) -> torch.Tensor:
    """With probability ``p`` per patch, the patch as the projector's fringes shifted by a further phase, drawn in
    [0, 2 pi) per orientation and shared by the three colours and all pixels.

    Four shifts I_k hold, per pixel and colour, the offset A, the fringe's cosine and sine parts C and S and an
    alternating remainder R: I_k = A + (-1)^k R + (C, S, -C, -S)_k. Rotating (C, S) by the drawn angle is exactly
    the capture of fringes moved by it (R, the part no sinusoid explains, is kept), so the encoder learns that a
    pixel's place on the fringe, which differs between views of the same material, says nothing about it."""
    b, _, h, w = x.shape
    y = x.view(b, 2, 4, 3, h, w)
    i0, i1, i2, i3 = y.unbind(2)
    a, r = (i0 + i1 + i2 + i3) / 4, (i0 - i1 + i2 - i3) / 4
    c, s = (i0 - i2) / 2, (i1 - i3) / 2
    angle = torch.rand(b, 2, 1, 1, 1, device=x.device, dtype=x.dtype) * (2 * math.pi)
    cos, sin = torch.cos(angle), torch.sin(angle)
    c, s = c * cos - s * sin, c * sin + s * cos
    out = torch.stack([a + r + c, a - r + s, a + r - c, a - r - s], dim=2).reshape(x.shape)
    return torch.where(_per_sample(_chance(b, p, x)), out, x)


def gaussian_blur(x: torch.Tensor, sigma: tuple[float, float], p: float = 1.0) -> torch.Tensor:
    """Gaussian blur with an isotropic sigma drawn per patch in ``sigma``; kernel covers +-3 sigma."""
    b = x.shape[0]
    s = _uniform(b, *sigma, x).clamp_min(1e-3)
    size = 2 * int(3 * sigma[1] + 0.5) + 1
    blurred = gaussian_blur2d(x, (size, size), torch.stack([s, s], dim=1), border_type="reflect")
    return torch.where(_per_sample(_chance(b, p, x)), blurred, x)


def salt_and_pepper(x: torch.Tensor, p: float, amount: float) -> torch.Tensor:
    """With probability p per patch, set `amount` of the pixels to the patch max and `amount` to 0.

    The same pixel positions are hit in all 8 images and all colour channels.
    """
    b, _, h, w = x.shape
    u = torch.rand(b, 1, h, w, device=x.device)
    active = _per_sample(_chance(b, p, x))
    salt = (u < amount) & active
    pepper = (u >= 1 - amount) & active
    peak = x.amax(dim=(1, 2, 3), keepdim=True).expand_as(x)
    return torch.where(pepper, torch.zeros_like(x), torch.where(salt, peak, x))


def strong(x: torch.Tensor, cfg: AugmentConfig = AugmentConfig()) -> torch.Tensor:
    b = x.shape[0]
    x = permute_shifts(psp_flip(x, cfg.flip_p), cfg.permute_p)
    x = phase_shift(x, cfg.phase_shift_p)
    x = gaussian_blur(x, cfg.blur_sigma)
    x = x * _per_sample(_uniform(b, *cfg.intensity, x))
    x = x + cfg.phase_jitter * torch.randn_like(x)
    return salt_and_pepper(x, cfg.sp_p, cfg.sp_amount)


def colour_jitter(x: torch.Tensor, b: float, c: float, s: float, h: float, p: float) -> torch.Tensor:
    """Colour jitter with one set of factors per patch, applied to each of its 8 RGB images."""
    n, _, hh, ww = x.shape
    rgb = x.reshape(n * N_IMAGES, 3, hh, ww)

    def factor(lo: float, hi: float) -> torch.Tensor:
        return _uniform(n, lo, hi, x).repeat_interleave(N_IMAGES)

    out = KE.adjust_brightness(rgb, factor(-b, b), clip_output=False)
    out = KE.adjust_contrast(out, factor(1 - c, 1 + c), clip_output=False)
    out = KE.adjust_saturation(out, factor(1 - s, 1 + s))
    out = KE.adjust_hue(out, factor(-h, h) * torch.pi * 2)
    out = out.reshape(n, 3 * N_IMAGES, hh, ww)
    return torch.where(_per_sample(_chance(n, p, x)), out, x)


def imagenet(x: torch.Tensor) -> torch.Tensor:
    """The ImageNet-style baseline (SimSiam's recipe minus grayscale) on the whole 24-channel stack."""
    x = random_resized_crop(x, (0.2, 1.0), (3 / 4, 4 / 3))
    x = colour_jitter(x, 0.4, 0.4, 0.4, 0.1, p=0.8)
    x = gaussian_blur(x, (0.1, 2.0), p=0.5)
    return torch.where(_per_sample(_chance(x.shape[0], 0.5, x)), x.flip(-1), x)


def two_views(x: torch.Tensor, kind: str = "psp", cfg: AugmentConfig = AugmentConfig()) -> tuple[torch.Tensor, torch.Tensor]:
    """SimSiam's pair: weak/strong for ``psp`` (Mean-Shifted BYOL style), imagenet/imagenet otherwise."""
    if kind == "psp":
        return weak(x, cfg), strong(weak(x, cfg), cfg)
    if kind == "imagenet":
        return imagenet(x), imagenet(x)
    raise ValueError(f"unknown augmentation kind {kind!r} (psp or imagenet)")


@dataclass(frozen=True)
class CameraAugment:
    """Decoder-input augmentation: the PSP patch as another camera would have recorded it, for a decoder that
    must relight frames of a camera it was not trained on (measured in docs/benchmarks/three-chip.md: it helps a
    decoder trained on full-colour frames relight Bayer ones, and costs it on its own camera). Each step is
    applied to a patch with probability ``p`` and draws its parameters once per patch, shared by its 8 images."""

    p: float = 0.5
    blur_sigma: tuple[float, float] = (0.3, 1.0)  # px, a lens's
    photons: tuple[float, float] = (2e3, 3e4)  # photo-electrons per unit of signal (shot noise)
    read_noise: tuple[float, float] = (0.0, 2e-3)  # in signal units
    gamma: tuple[float, float] = (0.8, 1.25)  # response-curve exponent error on the fringes


def random_bayer(x: torch.Tensor, p: float) -> torch.Tensor:
    """(B, 24, K, K) -> (B, 24, K, K): with probability ``p`` per patch, each image sampled on a Bayer mosaic of
    a random phase and demosaiced again, by Malvar-He-Cutler or bilinear interpolation (chosen per patch).
    From a three-chip camera's frames this is a Bayer camera's; from a Bayer camera's, a second pipeline."""
    b, _, k, _ = x.shape
    chosen = _chance(b, p, x)
    if not bool(chosen.any()):
        return x
    phase = torch.randint(0, 4, (b,), device=x.device).repeat_interleave(N_IMAGES)
    malvar = _chance(b, 0.5, x).repeat_interleave(N_IMAGES)
    rgb = x.reshape(b * N_IMAGES, 3, k, k)
    out = rgb.clone()
    chosen_images = chosen.repeat_interleave(N_IMAGES)
    for method, use in (("malvar", malvar), ("bilinear", ~malvar)):  # only the chosen images, each by its method
        sel = chosen_images & use
        if bool(sel.any()):
            out[sel] = rebayer(rgb[sel], phase[sel], method)
    return out.reshape(x.shape)


def sensor_noise(x: torch.Tensor, photons: tuple[float, float], read: tuple[float, float], p: float) -> torch.Tensor:
    """Shot noise (variance ``x / photons``) and read noise (std ``read``), both drawn per patch, with
    probability ``p`` per patch; independent per value."""
    b = x.shape[0]
    n_ph = _per_sample(torch.exp(_uniform(b, math.log(photons[0]), math.log(photons[1]), x)))  # log-uniform
    sd = torch.sqrt(x.clamp_min(0) / n_ph + _per_sample(_uniform(b, *read, x)) ** 2)
    return torch.where(_per_sample(_chance(b, p, x)), x + sd * torch.randn_like(x), x)


def fringe_gamma(x: torch.Tensor, gamma: tuple[float, float], p: float) -> torch.Tensor:
    """A response-curve error on the fringes: each pixel's 4 shifts (per orientation and colour) divided by
    their mean, raised to an exponent drawn per patch in ``gamma`` and rescaled to keep that mean, with
    probability ``p`` per patch. The modulation and the fringe's shape change; the offset, which is the
    footprint's energy, does not."""
    b, _, k, _ = x.shape
    s = x.reshape(b, 2, N_IMAGES // 2, 3, k, k).clamp_min(0)
    mean = s.mean(dim=2, keepdim=True)
    g = _uniform(b, *gamma, x).view(b, 1, 1, 1, 1, 1)
    curved = (s / mean.clamp_min(1e-8)) ** g
    out = (curved * (mean / curved.mean(dim=2, keepdim=True).clamp_min(1e-8))).reshape(x.shape)
    return torch.where(_per_sample(_chance(b, p, x)), out, x)


def camera(x: torch.Tensor, cfg: CameraAugment = CameraAugment()) -> torch.Tensor:
    """(B, 24, K, K) PSP patches -> the same light through a randomised camera (:class:`CameraAugment`):
    response-curve error, lens blur, Bayer resampling and demosaicing, then noise."""
    x = fringe_gamma(x.float(), cfg.gamma, cfg.p)
    x = gaussian_blur(x, cfg.blur_sigma, cfg.p)
    x = random_bayer(x, cfg.p)
    return sensor_noise(x, cfg.photons, cfg.read_noise, cfg.p)
