"""The splat: each lit pixel's footprint times the projector light it receives, added onto a canvas,
chunk by chunk, for several patterns per footprint pass (:func:`relight`, :class:`Splatter`)."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol, runtime_checkable

import numpy as np
import scipy.sparse
import torch

from sssphase_core.compute import compute_device
from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.projector import area_sample_projector, emitted_light, sample_projector

#: Produces the (N, K, K, 3) footprints of camera pixels given as (N, 2) int (y, x).
FootprintSource = Callable[[np.ndarray], "np.ndarray | torch.Tensor"]


def footprint_array(footprints: np.ndarray | torch.Tensor, *, writable: bool = False) -> np.ndarray:
    """A source's (N, K, K, 3) footprints as float32 NumPy (a model's tensor, on any device, moved to the CPU);
    ``writable``: an array the caller may change in place (a source may hand out an array it keeps)."""
    if torch.is_tensor(footprints):
        return footprints.float().cpu().numpy()
    return np.array(footprints, np.float32) if writable else np.asarray(footprints, np.float32)


@runtime_checkable
class TransportColumns(Protocol):
    """A source that lights its own columns of the light transport, one crop per projector dot (the
    measured transport, :class:`~sssphase_core.relight.transport.DotTransport`), instead of giving the
    footprints of the camera pixels :func:`lit_pixels` picks."""

    def lit(self, light: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Columns lit by some pattern: (camera pixels (N, 2), light (N, P, C), rows (N,))."""
        ...

    def crops_at(self, rows: np.ndarray) -> np.ndarray:
        """The (n, K, K, 3) crops of ``rows``."""
        ...


@dataclass(frozen=True)
class Projection:
    """Where each camera pixel lands in the projector, and how the projector turns values into light."""

    xp: np.ndarray  # (H, W) float32 projector x, NaN where invalid
    yp: np.ndarray  # (H, W) float32 projector y, NaN where invalid
    mask: np.ndarray  # (H, W) bool valid surface pixels
    projector_size: tuple[int, int]  # (Wp, Hp)
    gamma: float = 2.2
    black: float = 0.0
    #: Whether each camera pixel records the mean light over its footprint on the projector, as a real camera's (and
    #: a path tracer's pixel filter) does (:func:`received_light`); False: the light at its decoded point, as our
    #: simulator's pinhole camera samples it (relighting its sessions with exact footprints reproduces its renders).
    pixel_area: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    @cached_property
    def footprint_widths(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`pixel_footprint_widths`, made once per view (every relight of it reads them)."""
        return pixel_footprint_widths(self)


#: A camera pixel whose footprint on the projector is wider than this (projector px, either axis) receives the mean
#: of the light over it (:func:`received_light`); narrower ones the bilinear lookup, which is that mean over one
#: projector pixel.
AREA_SAMPLING_WIDTH = 1.5


def pixel_footprint_widths(proj: Projection) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) each: the widths along the projector's x and y (projector px) of the box with the second moments of
    each camera pixel's footprint on the projector, ``hypot`` of the decoded points' derivatives along the camera's
    x and y (the smaller of the two one-sided differences within the mask: where the surface meets a wall behind
    it the points jump on one side only), median-filtered over 3 x 3 pixels against the decoding's noise; the
    view's median where a pixel has no decoded neighbour, 1 where none has."""
    import cv2

    m = proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp)

    def derivative(v: np.ndarray, axis: int) -> np.ndarray:
        v = np.where(m, v, 0.0).astype(np.float64)
        fwd, bwd = np.roll(v, -1, axis) - v, v - np.roll(v, 1, axis)
        ok_f, ok_b = m & np.roll(m, -1, axis), m & np.roll(m, 1, axis)
        edge = [slice(None)] * 2
        edge[axis] = -1
        ok_f[tuple(edge)] = False
        edge[axis] = 0
        ok_b[tuple(edge)] = False
        both = np.where(np.abs(fwd) <= np.abs(bwd), fwd, bwd)  # the smaller side: a depth edge jumps on one only
        return np.where(ok_f & ok_b, both, np.where(ok_f, fwd, np.where(ok_b, bwd, np.nan)))

    widths = []
    for v in (proj.xp, proj.yp):
        w = np.hypot(derivative(v, 1), derivative(v, 0))
        valid = np.isfinite(w) & m
        w = np.where(valid, w, float(np.median(w[valid])) if valid.any() else 1.0).astype(np.float32)
        widths.append(cv2.medianBlur(w, 3))
    return widths[0], widths[1]


def received_light(proj: Projection, light: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """The emitted light (P, Hp, Wp, 3) that camera pixels (``ys``, ``xs``) receive -> (N, P, 3): looked up
    bilinearly at their decoded points, and for a camera that integrates over its pixels (``proj.pixel_area``)
    averaged over their footprint on the projector where that is wider than :data:`AREA_SAMPLING_WIDTH` (a
    192 x 144 rendered camera seeing a 640 x 360 projector relit a plain wall at 24 dB from the point values, where
    each pixel records the mean of 2-3 projector pixels a side)."""
    xp, yp = proj.xp[ys, xs], proj.yp[ys, xs]
    received = sample_projector(light, xp, yp)
    if proj.pixel_area and len(ys):
        wx, wy = (w[ys, xs] for w in proj.footprint_widths)
        wide = np.maximum(wx, wy) > AREA_SAMPLING_WIDTH
        if wide.any():
            received[wide] = area_sample_projector(light, xp[wide], yp[wide], np.maximum(wx[wide], 1.0),
                                                   np.maximum(wy[wide], 1.0))
    return received


def lit_pixels(proj: Projection, light: np.ndarray, threshold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels that receive light above ``threshold`` in some pattern: (pixels (N,2), c (N,P,3))."""
    ys, xs = np.nonzero(proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp))
    c = received_light(proj, light, ys, xs)
    keep = (c > threshold).any(axis=(1, 2))
    return np.stack([ys[keep], xs[keep]], axis=1), c[keep]


#: ``fold`` splat: bytes of the dense column tensor per band of image rows (one row at least).
FOLD_BAND_BYTES = 256 * 2**20


class Splatter:
    """Accumulates scaled K x K footprints into P canvases (padded so no bounds checks are needed).

    ``method``: ``csc`` (CPU): one sparse (canvas x sources) matrix per colour channel times the
    (sources x P) light, with scipy's compiled CSC kernel (measured ~9x faster than
    ``torch.index_add_`` and ~30x faster than torch's sparse matmul on the CPU preset, see ``sss bench
    relight``). ``index`` (other devices): torch ``index_put_(accumulate=True)``, whose CUDA kernel
    sorts indices and is deterministic. ``fold``: ``torch.nn.functional.fold`` (col2im, no atomics)
    over bands of image rows, the lit pixels' windows scattered into a dense (3P, K^2, rows x W)
    column tensor (unlit pixels of the band are zero columns, so the cost follows the band's area, and
    its memory is ``3 P K^2 W`` floats per row). ``auto``: csc on the CPU, index elsewhere.
    """

    def __init__(self, height: int, width: int, patch: int, n_patterns: int, device: str = "cpu", method: str = "auto"):
        if method not in ("auto", "csc", "index", "fold"):
            raise InputError(f"unknown splat method {method!r} (auto, csc, index or fold)")
        self.method = method
        self.h, self.w, self.k, self.p = height, width, patch, n_patterns
        self.hp, self.wp = height + patch, width + patch
        self.device = compute_device(device)
        dy, dx = np.meshgrid(np.arange(patch), np.arange(patch), indexing="ij")
        self._offsets = (dy * self.wp + dx).ravel()
        self._offsets32 = self._offsets.astype(np.int32)  # (a canvas of 2^31 values would be 8 GB per pattern)
        if method == "csc" or (method == "auto" and self.device.type == "cpu"):
            self.device = torch.device("cpu")
            self.canvas: np.ndarray | torch.Tensor = np.zeros((3, self.hp * self.wp, n_patterns), np.float32)
        elif method == "fold":
            self.canvas = torch.zeros(n_patterns * 3, self.hp, self.wp, dtype=torch.float32, device=self.device)
        else:
            self.canvas = torch.zeros(self.hp * self.wp, n_patterns * 3, dtype=torch.float32, device=self.device)
            self._toffsets = torch.as_tensor(self._offsets, device=self.device)

    def add(self, pixels: np.ndarray, footprints: torch.Tensor, c: torch.Tensor) -> None:
        """Splat footprints (n, K, K, 3) scaled by light c (n, P, 3) centred on pixels (n, 2)."""
        n, kk = footprints.shape[0], self.k * self.k
        if n == 0:
            return
        # Window top-left in padded coordinates: (y - K//2) + K//2 = y, likewise for x.
        corner = pixels[:, 0].astype(np.int64) * self.wp + pixels[:, 1]
        if isinstance(self.canvas, np.ndarray):
            fp = footprints.to(torch.float32).reshape(n, kk, 3).cpu().numpy()
            light = c.to(torch.float32).cpu().numpy()
            lo, hi = int(corner.min()), int(corner.max() + self._offsets[-1]) + 1
            rows = ((corner - lo).astype(np.int32)[:, None] + self._offsets32[None, :]).ravel()  # (int32 throughout: 8x faster)
            indptr = np.arange(0, n * kk + 1, kk, dtype=np.int64 if n * kk >= 2**31 else np.int32)
            for ch in range(3):
                m = scipy.sparse.csc_array((np.ascontiguousarray(fp[:, :, ch]).ravel(), rows, indptr), shape=(hi - lo, n))
                self.canvas[ch, lo:hi] += m @ light[:, :, ch]
            return
        footprints, c = footprints.to(self.device), c.to(self.device)
        if self.method == "fold":
            self._fold(pixels, footprints, c)
            return
        base = torch.as_tensor(corner, device=self.device)
        index = (base[:, None] + self._toffsets[None, :]).reshape(-1)
        vals = footprints.to(torch.float32).reshape(n, kk, 1, 3) * c.to(torch.float32).reshape(n, 1, self.p, 3)
        self.canvas.index_put_((index,), vals.reshape(n * kk, self.p * 3), accumulate=True)

    def _fold(self, pixels: np.ndarray, footprints: torch.Tensor, c: torch.Tensor) -> None:
        n, k, kk, p3 = len(pixels), self.k, self.k * self.k, self.p * 3
        # (n, P*3, K*K): every footprint entry times each pattern's light, ordered as fold's columns
        vals = (footprints.to(torch.float32).reshape(n, 1, kk, 3) * c.to(torch.float32).reshape(n, self.p, 1, 3))
        vals = vals.permute(0, 1, 3, 2).reshape(n, p3, kk)
        ys = torch.as_tensor(pixels[:, 0], device=self.device)
        xs = torch.as_tensor(pixels[:, 1], device=self.device)
        band = max(1, FOLD_BAND_BYTES // (p3 * kk * self.w * 4))
        y_lo = int(pixels[:, 0].min())
        while y_lo <= int(pixels[:, 0].max()):
            sel = (ys >= y_lo) & (ys < y_lo + band)
            rows = min(band, self.h - y_lo)
            if bool(sel.any()):
                cols = torch.zeros(p3, kk, rows * self.w, dtype=torch.float32, device=self.device)
                # a camera pixel can carry several dots (measured transport): add, do not assign
                cols.index_add_(2, (ys[sel] - y_lo) * self.w + xs[sel], vals[sel].permute(1, 2, 0))
                out = torch.nn.functional.fold(cols, (rows + k - 1, self.w + k - 1), k)  # window top-left = (y, x)
                self.canvas[:, y_lo:y_lo + rows + k - 1, : self.w + k - 1] += out[:, 0]
            y_lo += band

    def result(self) -> np.ndarray:
        """Canvases cropped to the image, (P, H, W, 3) float32."""
        half = self.k // 2
        if self.method == "fold":
            img = self.canvas.reshape(self.p, 3, self.hp, self.wp)[:, :, half : half + self.h, half : half + self.w]
            return img.permute(0, 2, 3, 1).contiguous().cpu().numpy()
        if isinstance(self.canvas, np.ndarray):
            img = self.canvas.reshape(3, self.hp, self.wp, self.p)[:, half : half + self.h, half : half + self.w]
            return np.ascontiguousarray(img.transpose(3, 1, 2, 0))
        img = self.canvas.reshape(self.hp, self.wp, self.p, 3)[half : half + self.h, half : half + self.w]
        return img.permute(2, 0, 1, 3).contiguous().cpu().numpy()


def pattern_stack(patterns: np.ndarray | Sequence[np.ndarray], proj: Projection) -> np.ndarray:
    """Projector patterns as one (P, Hp, Wp[, 3]) array (mono and colour together: all RGB); a pattern of
    another size than the projector's is refused."""
    if isinstance(patterns, np.ndarray):
        pats = patterns
    else:
        listed = [np.asarray(p, np.float32) for p in patterns]
        if any(p.ndim == 3 for p in listed):  # mono and colour patterns together: all as RGB
            listed = [np.repeat(p[..., None], 3, axis=-1) if p.ndim == 2 else p for p in listed]
        pats = np.stack(listed)
    if pats.ndim == 2:
        pats = pats[None]
    wp, hp = proj.projector_size
    if pats.shape[1:3] != (hp, wp):
        raise InputError(
            f"pattern size {pats.shape[2]}x{pats.shape[1]} does not match the projector's {wp}x{hp} "
            "(resize it explicitly first, e.g. `sss relight --resize`)"
        )
    return pats


def crop_footprints(fp: torch.Tensor, radius: int) -> torch.Tensor:
    """Truncate (N, K, K, 3) footprints to the central (2 radius + 1)^2 window."""
    half = fp.shape[1] // 2
    if radius < 0 or radius >= half:
        return fp
    return fp[:, half - radius : half + radius + 1, half - radius : half + radius + 1]


#: The share of lit pixels whose footprints may hold NaN or inf (set to 0 with a warning) before the source is
#: taken for broken: a checkpoint of finite weights that overflow gave 24% of all footprint values non-finite and
#: relit a labelled "torch" image with exit 0.
BROKEN_SOURCE_SHARE = 0.01


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
    radius: int | None = None,
    method: str = "auto",
    progress: Callable[[int, int], None] | None = None,
    variants: Sequence[Callable[[torch.Tensor], torch.Tensor]] = (),
    plain: bool = True,
) -> np.ndarray:
    """Relight one view under P projector patterns in one fused, chunked pass -> (P, H, W, 3) float32, or with
    ``variants`` (V, P, H, W, 3): the footprints as the source gives them (unless not ``plain``: then only the
    variants), then each variant's transform of them ((n, K, K, 3) -> (n, K, K, 3), e.g. :func:`widened`), all
    splatted from one call of the source per chunk.

    ``white`` (the image under a full-white pattern, linear units) supplies the projector black
    level's contribution; without it the black level is ignored. ``dtype`` is the precision the
    footprints and the light are rounded to (accumulation is always float32). ``radius`` truncates
    footprints to the central (2 radius + 1)^2 window (cheaper splats). ``method`` picks the splat
    kernel (see :class:`Splatter`). Non-finite footprint values are set to 0 with a warning, and a source whose
    footprints are non-finite for more than :data:`BROKEN_SOURCE_SHARE` of the pixels is refused (DataError).
    ``progress(done, total)`` is called after each chunk.
    """
    pats = pattern_stack(patterns, proj)
    if chunk < 1:
        raise InputError("chunk must be >= 1")
    light = emitted_light(pats, proj.gamma) * np.float32(1.0 - proj.black)
    if isinstance(source, TransportColumns):  # measured columns of the light transport, one per projector dot
        pixels, c, rows = source.lit(light)
        fetch: Callable[[slice], np.ndarray | torch.Tensor] = lambda sl: source.crops_at(rows[sl])  # noqa: E731
    else:
        pixels, c = lit_pixels(proj, light)
        fetch = lambda sl: source(pixels[sl])  # noqa: E731
    h, w = proj.shape
    k = patch if radius is None or radius >= patch // 2 else 2 * radius + 1
    if not (plain or variants):
        raise ValueError("relight: nothing to splat (plain=False and no variants)")
    transforms = ([lambda f: f] if plain else []) + list(variants)
    splats = [Splatter(h, w, k, light.shape[0], device=device, method=method) for _ in transforms]
    total, n_bad, bad_pixels = len(pixels), 0, 0
    for start in range(0, total, chunk):
        sl = slice(start, min(start + chunk, total))
        fp = fetch(sl)
        fp = fp if torch.is_tensor(fp) else torch.from_numpy(np.ascontiguousarray(fp, dtype=np.float32))
        if fp.shape[1:] != (patch, patch, 3):
            raise InputError(f"the footprint source returned {tuple(fp.shape[1:])} footprints, expected ({patch}, {patch}, 3)")
        fp = crop_footprints(fp.to(device=device), radius if radius is not None else patch)
        # a backend's NaN/inf must not spread over the whole canvas; any of them makes the sum non-finite (one
        # reduction: 4 ms a 1,024 K = 90 footprints on 2 cores, where a mask of every value took 66)
        bad = ~torch.isfinite(fp) if not torch.isfinite(fp.sum()) else None
        if bad is not None and bad.any():  # (finite values whose sum overflowed: the mask finds none)
            n_bad += int(bad.sum())
            bad_pixels += int(bad.flatten(1).any(1).sum())
            if bad_pixels > BROKEN_SOURCE_SHARE * total:
                raise DataError(f"the footprint source gave non-finite footprints for more than {BROKEN_SOURCE_SHARE:.0%} "
                                f"of the {total} lit pixels ({bad_pixels} so far): the model is broken (a checkpoint whose "
                                "weights overflow?), and nothing it relit can be used")
            fp = torch.where(bad, torch.zeros((), dtype=fp.dtype, device=fp.device), fp)
        light_sl = torch.as_tensor(c[sl], device=device).to(dtype)
        for splat, transform in zip(splats, transforms, strict=True):
            splat.add(pixels[sl], transform(fp).to(dtype), light_sl)
        if progress is not None:
            progress(sl.stop, total)
    if n_bad:
        warnings.warn(f"{n_bad} non-finite footprint values from the footprint source were set to 0", RuntimeWarning, stacklevel=2)
    outs = [splat.result() for splat in splats]
    if white is not None and proj.black > 0:
        for out in outs:
            out += np.float32(proj.black) * np.asarray(white, np.float32)[None]
    return np.stack(outs) if variants else outs[0]


def stretched(footprints: torch.Tensor, factor: float | tuple[float, float]) -> torch.Tensor:
    """(N, K, K, 3) footprints stretched about their centre pixel ``K // 2`` by ``factor`` (one for both axes, or
    ``(along x, along y)``; bilinear resampling; light beyond the window is lost) -> (N, K, K, 3): linear in the
    footprints, so eigen-footprints stretch as the footprints they span do
    (:meth:`~sssphase_core.relight.lowrank.LowRankFootprints.widened`)."""
    fx, fy = (factor, factor) if np.isscalar(factor) else factor
    f = footprints.float().permute(0, 3, 1, 2)  # (N, 3, K, K)
    n, _, k, _ = f.shape
    centred = torch.arange(k, dtype=torch.float32, device=f.device) - k // 2
    gx, gy = ((centred / float(s) + k // 2) / (k - 1) * 2 - 1 for s in (fx, fy))  # grid_sample's [-1, 1] (align_corners)
    grid = torch.stack(torch.meshgrid(gx, gy, indexing="xy"), dim=-1)[None].expand(n, k, k, 2)  # (.., (x, y))
    out = torch.nn.functional.grid_sample(f, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.permute(0, 2, 3, 1)


#: The one-pixel box a softened footprint is convolved with, per axis: the mean of the bilinear weights of a shift
#: drawn uniformly over one pixel (centre 1 - E|u| = 3/4, each neighbour E|u| / 2 = 1/8, u in [-1/2, 1/2]).
SOFTEN_TAPS = (0.125, 0.75, 0.125)


def softened(footprints: torch.Tensor) -> torch.Tensor:
    """(N, K, K, 3) footprints convolved with a one-pixel box along both axes (:data:`SOFTEN_TAPS`; zero beyond the
    window) -> (N, K, K, 3): each footprint as if its pixel's light were spread over the pixel about its centre, its
    core softer at the same width; linear in the footprints (eigen-footprints soften as the footprints they span do)."""
    f = footprints.float().permute(0, 3, 1, 2)  # (N, 3, K, K)
    taps = torch.tensor(SOFTEN_TAPS, dtype=torch.float32, device=f.device)
    kernel = (taps[:, None] * taps[None, :])[None, None].expand(f.shape[1], 1, 3, 3)
    return torch.nn.functional.conv2d(f, kernel, padding=1, groups=f.shape[1]).permute(0, 2, 3, 1)


def energy_kept(footprints: torch.Tensor, changed: torch.Tensor) -> torch.Tensor:
    """``changed`` (N, K, K, 3), made from ``footprints`` (N, K, K, 3), scaled so that each footprint keeps each
    colour's energy (where it has any left) -> (N, K, K, 3) in ``footprints``' dtype."""
    had, has = footprints.float().sum(dim=(1, 2), keepdim=True), changed.sum(dim=(1, 2), keepdim=True)
    out = changed * torch.where(has > 0, had / torch.where(has > 0, has, torch.ones_like(has)), torch.ones_like(has))
    return out.to(footprints.dtype)


def widened(footprints: torch.Tensor, factor: float | tuple[float, float]) -> torch.Tensor:
    """(N, K, K, 3) footprints :func:`stretched` by ``factor`` (both axes, or ``(along x, along y)``), each colour's
    energy kept -> (N, K, K, 3)."""
    return energy_kept(footprints, stretched(footprints, factor))


def axis_stretches(factor: float) -> tuple[tuple[float, float], ...]:
    """The stretches ``(factor, 1), (1, factor), (factor, factor)`` (along x, along y, both) of a model's footprints
    among the members the view calibration weighs in place of the footprints themselves (:func:`member_maps`): each
    fringe orientation measures the footprints' width across it, so the fit can widen them along either axis or both,
    and narrow any of them toward no scattering."""
    f = float(factor)
    return (f, 1.0), (1.0, f), (f, f)


def member_maps(factor: float) -> tuple[Callable[[torch.Tensor], torch.Tensor], ...]:
    """The linear maps (N, K, K, 3) -> (N, K, K, 3), energy not yet kept, that make a model's members in the view
    calibration (``relight_view``'s ``widen``; named by :data:`~sssphase_core.relight.choices.WIDEN_MEMBERS`): its
    footprints stretched by ``factor`` along x, along y and along both (:func:`axis_stretches`), and :func:`softened`
    at their own width, so that the view's fringes can also give a footprint a softer core than the model predicts
    (a decoder trained on our simulator's sharp-cored footprints: measured in docs/benchmarks/relighting.md)."""
    return (*(functools.partial(stretched, factor=s) for s in axis_stretches(factor)), softened)


def calibration_members(factor: float) -> tuple[Callable[[torch.Tensor], torch.Tensor], ...]:
    """:func:`member_maps` with each footprint's energy per colour kept: what the calibration splats."""
    return tuple(functools.partial(_kept, change=m) for m in member_maps(factor))


def _kept(footprints: torch.Tensor, change: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    return energy_kept(footprints, change(footprints))
