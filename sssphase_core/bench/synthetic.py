"""Flat synthetic scenes whose footprints are known analytically: the data of `sss bench gpu` (no
simulator, any size) and of the learning tests."""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

from sssphase_core.learning.data import ViewData, sample_pixels, view_seed


def synthetic_views(
    objects: Sequence[str] = ("a", "b"),
    views: Sequence[int] = (0, 1),
    *,
    size: tuple[int, int] = (48, 48),
    patch: int = 16,
    period: float = 6.0,
    pixels_per_view: int | None = 64,
    noise: float = 0.002,
    seed: int = 0,
) -> tuple[list[ViewData], dict[str, np.ndarray]]:
    """Flat test scenes: each object one homogeneous material with a known per-RGB exponential kernel.

    The PSP images are the exact fringe images blurred by the kernel (light enters, spreads, exits)
    and the footprint targets are the kernel itself, so the ground truth is analytic. Returns the
    views and the kernels {object: (K, K, 3)}. Views differ by fringe phase offset and albedo
    shading. Material label = object index.
    """
    h, w = size
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    c = patch // 2
    ky, kx = np.mgrid[:patch, :patch].astype(np.float32) - c
    r = np.hypot(ky, kx)
    kernels: dict[str, np.ndarray] = {}
    out = []
    for oi, obj in enumerate(objects):
        prng = np.random.default_rng(zlib.crc32(f"{seed}/{obj}".encode()))
        widths = prng.uniform(0.4, 2.5, 3)
        albedo = prng.uniform(0.4, 0.9, 3)
        kern = np.exp(-r[..., None] / widths)
        kern = (kern / kern.sum(axis=(0, 1)) * albedo).astype(np.float32)
        kernels[obj] = kern
        otf = np.stack([np.fft.rfft2(np.fft.ifftshift(_embed(kern[..., ch], h, w, c))) for ch in range(3)], -1)
        for view in views:
            rng = np.random.default_rng(view_seed(seed, obj, int(view)))
            offset = rng.uniform(0, 2 * np.pi)
            imgs = []
            for coord in (xx, yy):
                for n in range(4):
                    light = 0.5 + 0.5 * np.cos(2 * np.pi * coord / period - 2 * np.pi * n / 4 + offset)
                    spread = np.fft.irfft2(np.fft.rfft2(light)[..., None] * otf, s=(h, w), axes=(0, 1))
                    imgs.append(spread)
            psp = np.stack(imgs).astype(np.float32)
            psp += noise * rng.standard_normal(psp.shape).astype(np.float32)
            inner = np.zeros((h, w), bool)
            inner[c : h - c, c : w - c] = True
            pixels = sample_pixels(inner, pixels_per_view, view_seed(seed + 1, obj, int(view)))
            fp = np.broadcast_to(kern, (len(pixels), *kern.shape)).copy()
            out.append(ViewData(obj, int(view), psp, pixels, np.full(len(pixels), oi, np.int64), fp))
    return out, kernels


def _embed(kernel: np.ndarray, h: int, w: int, c: int) -> np.ndarray:
    """Place a K x K kernel centred in an (h, w) canvas (for circular FFT convolution)."""
    canvas = np.zeros((h, w), np.float32)
    k = kernel.shape[0]
    y0, x0 = h // 2 - c, w // 2 - c
    canvas[y0 : y0 + k, x0 : x0 + k] = kernel
    return canvas
