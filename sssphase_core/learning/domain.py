"""The footprint widths a decoder was trained on, and the pixels that lie beyond them.

A decoder learns the footprints of its training objects. Asked for one far wider than any it saw (a milky
material, a scattering length near the patch size) it cannot extrapolate: on ``sss bench stability``'s
``wide`` case (mean free path 60 mm) the demo's decoder relit at 28.6 dB where the analytic model, which
reads a footprint's width from the fringes' modulation at any scale, reached 36.6. That width
(:meth:`AnalyticBackend.estimate`, from a 5 x 5 window, no training) describes every pixel: a decoder's
checkpoint records how far its training pixels' widths reached (:func:`training_domain`), and the torch
backend gives the pixels beyond that (:func:`beyond`) the analytic model's footprints instead of the
decoder's extrapolation. Measured on the demo's training pixels, the widths' 99.5th percentile is
1.7 / 2.1 / 1.1 px (R / G / B); the ``wide`` case's pixels are 3.9 / 3.5 / 2.9 px at their 10th.

Only the wide side is guarded. At the narrow end (no scattering, a black object) the analytic model is
further from the truth than the decoder (``delta``: 50.9 against 58.7 dB), and the view calibration already
mixes the decoder with no scattering there.

**The tail.** Within the domain a decoder still learns a footprint only as far out as its training crops
hold light above their noise at most pixels. The SBH loss's log term is flat below its offset (the crops' noise
floor), and its L1 and gradient terms fit the *median* of their targets, which where the light is fainter than the
noise is set by the noise: 0 for a path tracer's Monte-Carlo grain or shot noise at a few photons (rare bright
samples), the light's own value only on average over many crops for Gaussian noise. A decoder trained on Mitsuba
renders learned almost no light beyond 10 px, where the analytic model puts 2 % of a skin's red energy (5 % at
6-10 px), and relit that skin 1 dB below the analytic model; the demo's decoder, whose simulated crops keep a
positive median out to 9 px under Gaussian noise, learned the light between 4 and 9 px from few effective samples
and relit Mitsuba's skin egg 0.3 dB below it. :func:`tail_radius` records, per colour, the first ring whose
median light is not above the crops' noise floor, and the torch backend takes the footprint from that ring
outwards from the analytic model (:func:`with_physics_tail`), keeping the decoder's energy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from sssphase_core.errors import DataError

if TYPE_CHECKING:
    import torch

    from sssphase_core.learning.data import ViewData

#: The quantile of the training pixels' widths (per colour) that bounds the domain, and the margin beyond it
#: that is still the decoder's: a few wide training pixels do not teach it the tail.
WIDTH_QUANTILE, WIDTH_MARGIN = 0.995, 2.0
#: Training pixels read for the domain (a seeded sample beyond this).
MAX_DOMAIN_PIXELS = 50_000
#: The projector black level the training widths are read with (sessions record theirs only per view).
DOMAIN_BLACK = 0.002
#: The largest tail radius a checkpoint may record (a 256 px patch's corner ring, plus one).
MAX_TAIL_RADIUS = 182


@dataclass(frozen=True)
class WidthDomain:
    """``limit`` (3,): the largest footprint width (px, the larger axis) per colour that the decoder is used
    for; ``quantile`` and ``pixels``: how it was measured."""

    limit: tuple[float, float, float]
    quantile: float = WIDTH_QUANTILE
    pixels: int = 0
    #: per colour, the first ring (px) whose light the decoder did not learn (:func:`tail_radius`); None: a
    #: checkpoint from before it was recorded, whose footprints are the decoder's out to the patch's corners
    tail_radius: tuple[int, int, int] | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"width_limit_px": list(self.limit), "quantile": self.quantile, "pixels": self.pixels}
        if self.tail_radius is not None:
            out["tail_radius_px"] = list(self.tail_radius)
        return out

    @classmethod
    def from_dict(cls, d: object) -> WidthDomain | None:
        """The domain a checkpoint recorded; None for checkpoints from before it was recorded."""
        if not isinstance(d, dict) or "width_limit_px" not in d:
            return None
        try:
            limit = np.asarray(d["width_limit_px"], np.float64)
        except (TypeError, ValueError):
            limit = np.full(1, np.nan)
        if limit.shape != (3,) or not np.isfinite(limit).all() or (limit <= 0).any():
            raise DataError(f"the checkpoint's training domain is damaged: width limits {d['width_limit_px']!r}")
        tail = d.get("tail_radius_px")
        if tail is not None:
            ok = isinstance(tail, list) and len(tail) == 3 and all(type(r) is int and 1 <= r <= MAX_TAIL_RADIUS for r in tail)
            if not ok:
                raise DataError(f"the checkpoint's training domain is damaged: tail radii {tail!r}")
            tail = tuple(tail)
        quantile, pixels = d.get("quantile", WIDTH_QUANTILE), d.get("pixels", 0)
        if isinstance(quantile, bool) or not isinstance(quantile, int | float) or not 0 <= quantile <= 1:
            raise DataError(f"the checkpoint's training domain is damaged: quantile {quantile!r}")  # was internal
        if isinstance(pixels, bool) or not isinstance(pixels, int) or pixels < 0:
            raise DataError(f"the checkpoint's training domain is damaged: pixels {pixels!r}")
        return cls(tuple(float(x) for x in limit), float(quantile), pixels, tail)  # type: ignore[arg-type]


def pixel_widths(patches: np.ndarray, patch: int, black: float = DOMAIN_BLACK) -> dict[str, np.ndarray]:
    """The analytic model's estimate of (N, 24, S, S) PSP patches (S >= 5; the centre window is read) for
    footprints of ``patch`` x ``patch`` (widths are clipped at half of it): ``widths`` (N, 3) px, each colour's
    larger axis, plus :meth:`AnalyticBackend.estimate`'s ``energy`` and ``axes`` (N, 3, 2), the widths along
    x and y (what :meth:`AnalyticBackend.render` takes)."""
    from sssphase_core.learning.backends.analytic_backend import AnalyticBackend

    est = AnalyticBackend(patch=int(patch), black=black).estimate(patches)
    return {"widths": est["widths"].max(axis=-1), "energy": est["energy"], "axes": est["widths"]}


def training_domain(views: Sequence[ViewData], patch: int, *, seed: int = 0, black: float = DOMAIN_BLACK) -> WidthDomain:
    """The width domain of the training ``views``' pixels (a seeded sample of :data:`MAX_DOMAIN_PIXELS`) for a
    decoder of ``patch`` x ``patch`` footprints."""
    from sssphase_core.learning.backends.base import as_patches

    widths = [pixel_widths(as_patches((v.psp, v.pixels), 5), patch, black)["widths"] for v in views if len(v.pixels)]
    if not widths:
        raise DataError("no training pixels to measure the decoder's width domain on")
    w = np.concatenate(widths)
    if len(w) > MAX_DOMAIN_PIXELS:
        w = w[np.random.default_rng(seed).choice(len(w), MAX_DOMAIN_PIXELS, replace=False)]
    limit = np.quantile(w, WIDTH_QUANTILE, axis=0) * WIDTH_MARGIN
    return WidthDomain(tuple(float(x) for x in limit), WIDTH_QUANTILE, len(w))  # type: ignore[arg-type]


def _rings(patch: int) -> np.ndarray:
    """(K, K) int: each pixel's distance from the centre pixel ``K // 2``, rounded."""
    off = np.arange(patch) - patch // 2
    return np.rint(np.hypot(off[:, None], off[None, :])).astype(np.int64)


def tail_radius(footprints: np.ndarray, noise: float = 0.0) -> tuple[int, int, int]:
    """Per colour, the first ring (px from the centre) at which the median over (N, 3, K, K) training
    ``footprints`` is not above ``noise`` (their noise floor, :func:`~sssphase_core.learning.losses.noise_floor`):
    from there out the SBH loss taught the decoder no light of its own. A ring beyond the patch (``K // 2``
    times sqrt 2, rounded, plus 1) where the median stays above it to the corners (noise-free footprints)."""
    fp = np.asarray(footprints, np.float64)
    rings = _rings(fp.shape[-1])
    out = []
    for c in range(3):
        lit = fp[fp[:, c].sum(axis=(1, 2)) > 0, c]
        r = 0
        while r <= rings.max() and len(lit) and np.median(lit[:, rings == r]) > noise:
            r += 1
        out.append(max(r, 1))
    return tuple(out)  # type: ignore[return-value]


def cuts_tail(radius: Sequence[int], patch: int) -> bool:
    """Whether tail radii (3,) leave any ring of a ``patch`` x ``patch`` footprint to the physics."""
    return min(radius) <= int(_rings(patch).max())


def with_physics_tail(footprints: np.ndarray | torch.Tensor, physics: np.ndarray | torch.Tensor,
                      radius: Sequence[int]) -> np.ndarray | torch.Tensor:
    """(N, K, K, 3) decoder ``footprints`` whose rings from ``radius`` (3,) px outwards, per colour, are the
    ``physics`` footprints' (the analytic model's, (N, K, K, 3)), each colour scaled back to the decoder's
    energy -> (N, K, K, 3): NumPy for NumPy, a tensor on the footprints' device for tensors."""
    import torch

    if not torch.is_tensor(footprints):
        dtype = np.asarray(footprints).dtype
        out = with_physics_tail(torch.from_numpy(np.asarray(footprints, np.float32)),
                                torch.from_numpy(np.asarray(physics, np.float32)), radius)
        return out.numpy().astype(dtype, copy=False)  # type: ignore[union-attr]
    rings = torch.from_numpy(_rings(footprints.shape[1])).to(footprints.device)
    far = rings[:, :, None] >= torch.as_tensor(list(radius), device=footprints.device)[None, None, :]  # (K, K, 3)
    out = torch.where(far[None], physics.to(footprints.dtype), footprints)
    own, now = footprints.sum(dim=(1, 2), keepdim=True), out.sum(dim=(1, 2), keepdim=True)
    return out * torch.where(now > 0, own / torch.where(now > 0, now, torch.ones_like(now)), torch.ones_like(now))


def beyond(domain: WidthDomain, widths: np.ndarray) -> np.ndarray:
    """(N,) bool: pixels with any colour's width (N, 3) px beyond the domain's limit."""
    return (np.asarray(widths) > np.asarray(domain.limit)[None]).any(axis=1)
