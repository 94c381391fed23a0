"""How a dot-grid crop records a footprint, as differentiable torch functions (function + module, kornia
style): the camera pixels the dot lit (:func:`spread_dot`), then the camera's colour pipeline (Bayer
sampling, the optional 3x3 median per Bayer plane, linear demosaicing: :func:`through_camera`).

Captured footprints are crops of demosaiced frames. A pixel measures one colour; the other two are
interpolated from its neighbours, so a peaked footprint's colours are spread over a ring and, with
Malvar's gradient correction, given negative lobes, differently for each of the four positions of the
crop centre in the Bayer pattern (measured on the demo's crab, exact footprints through the camera: the red
centre share 0.73 -> 0.32, the blue one 0.76 -> 1.17). A decoder fitted to such crops learns their
average over positions, a blurred footprint, while relighting treats its footprints as the light that
reaches the sensor (a relit image is passed through the camera only when it is compared with captures).
And the crop of a pixel is lit by the dot at its rounded projector coordinate, whose light enters up to a
pixel or more away, over as many camera pixels as the projector pixel covers there
(:func:`sssphase_core.processing.footprints.dot_kernels`): a further blur that follows the fringes'
density. Decoder training therefore passes each predicted footprint through the way its target was
recorded (:func:`as_captured`) before the loss: the network predicts the light entering at the pixel's
centre, before the sensor, which is what relighting splats.

Modelled: Bayer sampling in the crop's own phase, the per-plane 3x3 median (the paper's ISP) and two
linear demosaicers, Malvar-He-Cutler 2004 (``malvar``, what ``processing.isp.malvar`` computes) and bilinear
(``bilinear``; it stands for OpenCV's edge-aware ``opencv``, which is not linear). Outside the crop the
footprint counts as zero.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from sssphase_core.errors import InputError
from sssphase_core.processing.isp import MALVAR_KERNELS

#: No camera model (simulated exact footprints, a three-chip camera, frames of an unknown pipeline).
NO_CAMERA = -1
#: Demosaicers with a linear model here: the session's ``camera_isp["demosaic"]`` -> the model's kernels.
DEMOSAIC_MODELS = {"malvar": "malvar", "opencv": "bilinear"}
_METHODS = ("malvar", "bilinear")

_MALVAR = MALVAR_KERNELS  # Malvar-He-Cutler 2004 (processing.isp), what ``isp.malvar`` computes
_BILINEAR = {
    "green": [[0, 0, 0, 0, 0], [0, 0, 2, 0, 0], [0, 2, 0, 2, 0], [0, 0, 2, 0, 0], [0, 0, 0, 0, 0]],
    "row": [[0, 0, 0, 0, 0], [0, 0, 0, 0, 0], [0, 4, 0, 4, 0], [0, 0, 0, 0, 0], [0, 0, 0, 0, 0]],
    "col": [[0, 0, 0, 0, 0], [0, 0, 4, 0, 0], [0, 0, 0, 0, 0], [0, 0, 4, 0, 0], [0, 0, 0, 0, 0]],
    "cross": [[0, 0, 0, 0, 0], [0, 2, 0, 2, 0], [0, 0, 0, 0, 0], [0, 2, 0, 2, 0], [0, 0, 0, 0, 0]],
}
_KERNELS = {"malvar": _MALVAR, "bilinear": _BILINEAR}
_KERNEL_ORDER = ("green", "row", "col", "cross")


def camera_code(isp: dict | None) -> int:
    """The code of a view's camera pipeline (its ``camera_isp``) without the crop's phase: ``NO_CAMERA`` where
    nothing is modelled (no record, a three-chip camera, an unknown demosaicer), else ``8 * method + 4 * median``;
    :func:`crop_codes` adds each crop's Bayer phase (0-3)."""
    if not isp or str(isp.get("demosaic")) not in DEMOSAIC_MODELS:
        return NO_CAMERA
    return 8 * _METHODS.index(DEMOSAIC_MODELS[str(isp["demosaic"])]) + 4 * bool(isp.get("median", False))


def crop_codes(isp: dict | None, pixels: np.ndarray, patch: int) -> np.ndarray:
    """(N,) int64 camera codes of the (K, K) crops centred (at ``K // 2``) on ``pixels`` (N, 2) (y, x) of a view
    whose frames ``isp`` made: :func:`camera_code` plus the phase of the crop's top-left pixel in the Bayer
    pattern (0 RGGB, 1 GRBG, 2 GBRG, 3 BGGR from there)."""
    from sssphase_core.processing.isp import BAYER_LAYOUTS, check_layout

    base = camera_code(isp)
    px = np.asarray(pixels, np.int64).reshape(-1, 2)
    if base == NO_CAMERA:
        return np.full(len(px), NO_CAMERA, np.int64)
    dy, dx = BAYER_LAYOUTS[check_layout(str((isp or {}).get("bayer", "RGGB")))]
    top, left = px[:, 0] - patch // 2 + dy, px[:, 1] - patch // 2 + dx
    return base + 2 * (top % 2) + (left % 2)


def _parities(phase: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Row and column parities ((B, H, 1), (B, 1, W)) in RGGB terms of crops whose top-left pixels have Bayer
    ``phase`` (B,): red where both are 0, blue where both are 1."""
    yy = (torch.arange(h, device=phase.device)[None, :, None] + (phase // 2)[:, None, None]) % 2
    xx = (torch.arange(w, device=phase.device)[None, None, :] + (phase % 2)[:, None, None]) % 2
    return yy, xx


#: A sorting network whose middle output is the median of 9 values (19 compare-exchanges, Paeth's): min and
#: max only, so its backward is elementwise and deterministic on every device (torch.median's is not on CUDA).
_MEDIAN9 = ((1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8), (4, 7),
            (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2))


def _median3_planes(mosaic: torch.Tensor) -> torch.Tensor:
    """The 3x3 median of each Bayer plane of (B, 1, H, W) mosaics (edges replicated, as OpenCV's medianBlur)."""
    out = mosaic.clone()
    for oy in (0, 1):
        for ox in (0, 1):
            plane = mosaic[..., oy::2, ox::2]
            h, w = plane.shape[-2:]
            padded = nn.functional.pad(plane, (1, 1, 1, 1), mode="replicate")
            v = [padded[..., i : i + h, j : j + w] for i in range(3) for j in range(3)]
            for a, b in _MEDIAN9:
                v[a], v[b] = torch.minimum(v[a], v[b]), torch.maximum(v[a], v[b])
            out[..., oy::2, ox::2] = v[4]
    return out


def bayer_demosaic(footprints: torch.Tensor, phase: int | torch.Tensor, method: str = "malvar", *,
                   median: bool = False) -> torch.Tensor:
    """What a Bayer camera records of (B, 3, H, W) linear images whose top-left pixels sit at Bayer ``phase``
    (an int, or (B,) one per image; 0 RGGB, 1 GRBG, 2 GBRG, 3 BGGR): each pixel's own colour sampled, the 3x3
    median per Bayer plane if ``median``, the other colours interpolated by ``method`` (``malvar`` or
    ``bilinear``) -> (B, 3, H, W). Linear (median aside) and differentiable; zero outside the images."""
    if method not in _KERNELS:
        raise InputError(f"unknown demosaicing model {method!r}; use one of {', '.join(_KERNELS)}")
    b, c, h, w = footprints.shape
    if c != 3:
        raise InputError(f"bayer_demosaic needs (B, 3, H, W) images, got {tuple(footprints.shape)}")
    x = footprints.float()
    phases = torch.as_tensor(phase, device=x.device).reshape(-1).expand(b)
    yy, xx = _parities(phases, h, w)
    is_r, is_b = (yy == 0) & (xx == 0), (yy == 1) & (xx == 1)  # (B, H, W)
    is_g = ~(is_r | is_b)
    own = torch.stack([is_r, is_g, is_b], dim=1).to(x.dtype)  # (B, 3, H, W) one-hot
    mosaic = (x * own).sum(dim=1, keepdim=True)  # (B, 1, H, W): each pixel's own colour
    if median:
        mosaic = _median3_planes(mosaic)
    kernels = torch.tensor([_KERNELS[method][k] for k in _KERNEL_ORDER], dtype=x.dtype, device=x.device) / 8.0
    est = nn.functional.conv2d(mosaic, kernels[:, None], padding=2)  # (B, 4, H, W): green, row, col, cross
    green, row, col, cross = est.unbind(1)
    m = mosaic[:, 0]
    r_row = yy == 0  # (B, H, 1): green sites in a red row (red rows are the even ones in RGGB terms)
    red = torch.where(is_r, m, torch.where(is_g, torch.where(r_row, row, col), cross))
    blue = torch.where(is_b, m, torch.where(is_g, torch.where(r_row, col, row), cross))
    grn = torch.where(is_g, m, green)
    return torch.stack([red, grn, blue], dim=1).to(footprints.dtype)


def through_camera(footprints: torch.Tensor, codes: torch.Tensor | np.ndarray) -> torch.Tensor:
    """(B, 3, K, K) footprints as each one's camera recorded it: ``codes`` (B,) from :func:`crop_codes`
    (``NO_CAMERA``: unchanged). One pass per camera pipeline (usually one), each crop at its own phase."""
    codes = torch.as_tensor(codes, device=footprints.device).reshape(-1)
    if len(codes) != len(footprints):
        raise InputError(f"{len(codes)} camera codes for {len(footprints)} footprints")
    if bool((codes == NO_CAMERA).all()):
        return footprints
    out = footprints
    pipelines = torch.where(codes == NO_CAMERA, -1, codes // 4)
    for pipeline in torch.unique(pipelines).tolist():
        if pipeline < 0:
            continue
        sel = (pipelines == pipeline)[:, None, None, None]  # elementwise selection: deterministic backward everywhere
        seen = bayer_demosaic(footprints, codes.clamp_min(0) % 4, _METHODS[pipeline // 2], median=bool(pipeline & 1))
        out = torch.where(sel, seen, out)
    return out


def rebayer(images: torch.Tensor, phase: int | torch.Tensor, method: str = "malvar", *,
            median: bool = False) -> torch.Tensor:
    """(B, 3, H, W) full-colour images as a Bayer camera would record them (:func:`bayer_demosaic`), their
    borders mirrored by 2 px first (a mirror keeps each pixel's Bayer parity), so that the interpolators'
    zeros outside leave no dark rim -> (B, 3, H, W)."""
    padded = nn.functional.pad(images.float(), (2, 2, 2, 2), mode="reflect")
    return bayer_demosaic(padded, phase, method, median=median)[..., 2:-2, 2:-2].to(images.dtype)


#: :func:`shift_subpixel` moves by at most this many px (its 5 x 5 kernel); dot offsets are clipped to 1.5.
MAX_SHIFT = 2.0


def _bilinear_taps(d: torch.Tensor) -> torch.Tensor:
    """(B,) shifts -> (B, 5) weights on input offsets -2..2 of the 1-D bilinear move ``out(y) = in(y - d)``."""
    d = d.clamp(-MAX_SHIFT, MAX_SHIFT - 1e-4)
    whole = torch.floor(d)
    frac = d - whole
    taps = torch.arange(-2, 3, device=d.device, dtype=d.dtype)
    lo = -whole[:, None]  # in(y - whole) weighs 1 - frac, in(y - whole - 1) weighs frac
    return (1 - frac)[:, None] * (taps == lo) + frac[:, None] * (taps == lo - 1)


def shift_subpixel(footprints: torch.Tensor, offsets: torch.Tensor | np.ndarray) -> torch.Tensor:
    """(B, C, K, K) footprints moved by ``offsets`` (B, 2) (dy, dx) px, at most :data:`MAX_SHIFT`, bilinearly
    (a one-pixel box moved by a fraction of a pixel lands on its neighbours in proportion: what a dot's light
    entering off a pixel's centre does), zero from outside -> (B, C, K, K). Differentiable; one grouped 5 x 5
    convolution, deterministic on every device."""
    off = torch.as_tensor(offsets, dtype=torch.float32, device=footprints.device).reshape(-1, 2)
    if len(off) != len(footprints):
        raise InputError(f"{len(off)} offsets for {len(footprints)} footprints")
    if not bool(off.any()):
        return footprints
    kernel = _bilinear_taps(off[:, 0])[:, :, None] * _bilinear_taps(off[:, 1])[:, None, :]  # (B, 5, 5)
    return _correlate_each(footprints, kernel.to(footprints.dtype))


def _correlate_each(footprints: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(B, C, K, K) footprints, each correlated with its own (B, k, k) weights (k odd, zero padding) -> (B, C, K,
    K): one grouped convolution, deterministic on every device."""
    b, c, h, w = footprints.shape
    weight = weights.repeat_interleave(c, dim=0)[:, None]  # (B C, 1, k, k)
    out = nn.functional.conv2d(footprints.reshape(1, b * c, h, w), weight, padding=weights.shape[1] // 2, groups=b * c)
    return out.view(b, c, h, w)


def spread_dot(footprints: torch.Tensor, kernels: torch.Tensor | np.ndarray) -> torch.Tensor:
    """(B, C, K, K) footprints of light entering at a pixel, summed over the pixels a dot lit: ``kernels`` (B, k,
    k), k odd, the dot's weight on the camera pixel at each offset from the crop's centre
    (:func:`sssphase_core.processing.footprints.dot_kernels`), each pixel's footprint taken as the centre's
    moved there; zero from outside -> (B, C, K, K). Differentiable; one grouped convolution."""
    ker = torch.as_tensor(kernels, dtype=footprints.dtype, device=footprints.device)
    if ker.ndim != 3 or len(ker) != len(footprints) or ker.shape[1] != ker.shape[2] or ker.shape[1] % 2 != 1:
        raise InputError(f"dot kernels must be (B, k, k) with k odd for {len(footprints)} footprints, got "
                         f"{tuple(ker.shape)}")
    return _correlate_each(footprints, ker.flip(1, 2))  # the lit pixel at offset d adds the footprint moved by d


def as_captured(footprints: torch.Tensor, codes: torch.Tensor | np.ndarray,
                dots: torch.Tensor | np.ndarray | None = None) -> torch.Tensor:
    """(B, 3, K, K) footprints of light entering at each pixel's centre as their dot-grid crops recorded
    them: summed over the camera pixels the crop's dot lit (``dots`` (B, k, k) kernels, :func:`spread_dot`),
    then through the crop's camera (``codes`` (B,), :func:`through_camera`)."""
    spread = footprints if dots is None else spread_dot(footprints, dots)
    return through_camera(spread, codes)


class CaptureModel(nn.Module):
    """:func:`as_captured` as a module: ``forward(footprints (B, 3, K, K), codes (B,), dots (B, k, k))``."""

    def forward(self, footprints: torch.Tensor, codes: torch.Tensor, dots: torch.Tensor | None = None) -> torch.Tensor:
        return as_captured(footprints, codes, dots)
