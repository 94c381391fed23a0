"""Relighting by footprint splatting: I(q) = sum_p PSF_p(q - p) * c(p), with c(p) = L(pi(p)).

The footprint of every lit surface pixel is produced once per chunk (by a network, an analytic model,
measured captures or the simulator) and splatted for all requested patterns at once, so several
patterns share the footprint cost and footprints are never all held in memory.

Only pixels that are valid *and* receive light from at least one pattern are evaluated. The
projector's black level lights every pixel weakly; its contribution is ``black * white`` (the
captured white image is the sum of all footprints at unit light), so it costs nothing per pixel.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from sssphase_core.errors import InputError

#: Produces the (N, K, K, 3) footprints of camera pixels given as (N, 2) int (y, x).
FootprintSource = Callable[[np.ndarray], "np.ndarray | torch.Tensor"]


@dataclass(frozen=True)
class Projection:
    """Where each camera pixel lands in the projector, and how the projector turns values into light."""

    xp: np.ndarray  # (H, W) float32 projector x, NaN where invalid
    yp: np.ndarray  # (H, W) float32 projector y, NaN where invalid
    mask: np.ndarray  # (H, W) bool valid surface pixels
    projector_size: tuple[int, int]  # (Wp, Hp)
    gamma: float = 2.2
    black: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape


def emitted_light(patterns: np.ndarray, gamma: float) -> np.ndarray:
    """Pattern values in [0, 1] -> relative emitted radiance above black, (P, Hp, Wp, 3) float32."""
    pats = np.asarray(patterns, dtype=np.float32)
    if pats.ndim == 3:
        pats = np.repeat(pats[..., None], 3, axis=-1)
    if pats.ndim != 4 or pats.shape[-1] != 3:
        raise InputError(f"patterns must be (P, Hp, Wp) or (P, Hp, Wp, 3), got shape {pats.shape}")
    if not np.isfinite(pats).all():
        raise InputError("patterns contain NaN or inf values")
    return np.clip(pats, 0.0, 1.0) ** np.float32(gamma)


def sample_projector(light: np.ndarray, xp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Bilinear lookup of emitted light (P, Hp, Wp, 3) at projector points -> (N, P, 3); 0 outside."""
    _, hp, wp, _ = light.shape
    x0 = np.floor(xp).astype(np.int64)
    y0 = np.floor(yp).astype(np.int64)
    fx = (xp - x0).astype(np.float32)[:, None, None]
    fy = (yp - y0).astype(np.float32)[:, None, None]
    out = np.zeros((xp.shape[0], light.shape[0], 3), np.float32)
    for dy, dx, w in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi < wp) & (yi >= 0) & (yi < hp)
        vals = np.zeros_like(out)
        vals[inside] = light[:, yi[inside], xi[inside], :].transpose(1, 0, 2)
        out += w * vals
    return out


def lit_pixels(proj: Projection, light: np.ndarray, threshold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels that receive light above ``threshold`` in some pattern: (pixels (N,2), c (N,P,3))."""
    ys, xs = np.nonzero(proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp))
    c = sample_projector(light, proj.xp[ys, xs], proj.yp[ys, xs])
    keep = (c > threshold).any(axis=(1, 2))
    return np.stack([ys[keep], xs[keep]], axis=1), c[keep]


class Splatter:
    """Accumulates scaled K x K footprints into P canvases (padded so no bounds checks are needed)."""

    def __init__(self, height: int, width: int, patch: int, n_patterns: int, device: str = "cpu"):
        self.h, self.w, self.k, self.p = height, width, patch, n_patterns
        self.hp, self.wp = height + patch, width + patch
        self.canvas = torch.zeros(self.hp * self.wp, n_patterns * 3, dtype=torch.float32, device=device)
        dy, dx = np.meshgrid(np.arange(patch), np.arange(patch), indexing="ij")
        self._offsets = torch.as_tensor((dy * self.wp + dx).ravel(), device=device)

    def add(self, pixels: np.ndarray, footprints: torch.Tensor, c: torch.Tensor) -> None:
        """Splat footprints (n, K, K, 3) scaled by light c (n, P, 3) centred on pixels (n, 2)."""
        n, k = footprints.shape[0], self.k
        # Window top-left in padded coordinates: (y - K//2) + K//2 = y, likewise for x.
        base = torch.as_tensor(pixels[:, 0] * self.wp + pixels[:, 1], device=self.canvas.device)
        index = (base[:, None] + self._offsets[None, :]).reshape(-1)
        vals = footprints.to(self.canvas.dtype).reshape(n, k * k, 1, 3) * c.to(self.canvas.dtype).reshape(n, 1, self.p, 3)
        self.canvas.index_add_(0, index, vals.reshape(n * k * k, self.p * 3))

    def result(self) -> np.ndarray:
        """Canvases cropped to the image, (P, H, W, 3) float32."""
        half = self.k // 2
        img = self.canvas.reshape(self.hp, self.wp, self.p, 3)[half : half + self.h, half : half + self.w]
        return img.permute(2, 0, 1, 3).contiguous().cpu().numpy()


def relight(
    source: FootprintSource,
    proj: Projection,
    patterns: np.ndarray | Sequence[np.ndarray],
    patch: int,
    *,
    white: np.ndarray | None = None,
    chunk: int = 1024,
    dtype: torch.dtype = torch.float32,
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Relight one view under P projector patterns in one fused, chunked pass -> (P, H, W, 3) float32.

    ``white`` (the image under a full-white pattern, linear units) supplies the projector black
    level's contribution; without it the black level is ignored. ``dtype`` is the precision the
    footprints are scaled in (accumulation is always float32). ``progress(done, total)`` is called
    after each chunk.
    """
    pats = np.stack(list(patterns)) if not isinstance(patterns, np.ndarray) else patterns
    wp, hp = proj.projector_size
    if pats.shape[1:3] != (hp, wp):
        raise InputError(
            f"pattern size {pats.shape[2]}x{pats.shape[1]} does not match the projector's {wp}x{hp} "
            "(resize it explicitly first)"
        )
    if chunk < 1:
        raise InputError("chunk must be >= 1")
    light = emitted_light(pats, proj.gamma) * np.float32(1.0 - proj.black)
    pixels, c = lit_pixels(proj, light)
    h, w = proj.shape
    splat = Splatter(h, w, patch, light.shape[0], device=device)
    total = len(pixels)
    for start in range(0, total, chunk):
        sl = slice(start, min(start + chunk, total))
        fp = source(pixels[sl])
        fp = (fp if torch.is_tensor(fp) else torch.from_numpy(np.ascontiguousarray(fp))).to(device=device, dtype=dtype)
        splat.add(pixels[sl], fp, torch.as_tensor(c[sl], device=device, dtype=dtype))
        if progress is not None:
            progress(sl.stop, total)
    out = splat.result()
    if white is not None and proj.black > 0:
        out += np.float32(proj.black) * np.asarray(white, np.float32)[None]
    return out
