"""Phase-shift profilometry decoding: wrapped phase, offset A, modulation B, temporal hierarchical
unwrapping and camera -> projector correspondence maps.

Vectorised float32 torch (faster than numpy here; ``sss bench psp`` reports both) with OpenCV's
SIMD ``cv2.phase`` for the arctangent (7x torch.atan2 here; max error 1.7e-4 rad, i.e. 3e-4 px at a
10 px period, far below sensor noise), processed in blocks of rows so a 1080p frame set never needs full-size float copies of the frames.
Blocks run on ``torch.get_num_threads()`` worker threads, each with single-threaded torch ops: no
OpenMP barrier per operation, which keeps decoding fast when other processes share the cores.
Intensities are normalised to [0, 1] for integer inputs (``/255``, ``/65535`` unless ``white_level``
is given) and taken as-is for floats (linear camera units); the thresholds are in those units.

Sign convention (ARCHITECTURE.md): ``I_n = A + B cos(phi - 2πn/N)``,
``phi = atan2(Σ I_n sin δ_n, Σ I_n cos δ_n)``, ``B = 2/N |Σ I_n e^{iδ_n}|``, ``A = mean I_n``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from sssphase_core.errors import InputError
from sssphase_core.processing.isp import SATURATION_MARGIN
from sssphase_core.processing.patterns import PSPConfig, psp_key

#: Target number of pixels per processing block (~136 rows at 1080p).
BLOCK_PIXELS = 1 << 18


class Reason(enum.IntEnum):
    """Why a camera pixel has no correspondence (uint8 codes of ``Correspondence.reason``)."""

    VALID = 0
    LOW_MODULATION = 1  # B or B/A below threshold in some fringe set
    SATURATED = 2  # some channel of some frame at or above the saturation level
    SHADOW = 3  # offset A below the shadow threshold (too dark)
    UNWRAP_INCONSISTENT = 4  # neighbouring frequencies disagree by more than the tolerance
    OUTSIDE = 5  # maps outside the projector image
    BAD_INPUT = 6  # NaN/inf in some input frame (added to the ARCHITECTURE.md codes)
    DEMOSAIC_BLEED = 7  # at the silhouette, fringes only in the colours demosaicing filled in (demosaic_bleed)


@dataclass
class Correspondence:
    """Camera -> projector correspondence, all maps ``(H, W)`` (``modulation_ratio`` is ``(H, W, C)``).

    ``xp, yp`` are projector pixel coordinates (NaN where invalid); ``mask`` is ``reason == 0``;
    ``modulation`` is the high-frequency B (min over orientations), ``offset`` its A (mean), both on
    the channel mean; ``modulation_ratio`` is the per-channel high-frequency B/A (mean over
    orientations, 0 where A <= 0).
    """

    xp: np.ndarray
    yp: np.ndarray
    mask: np.ndarray
    reason: np.ndarray
    modulation: np.ndarray
    offset: np.ndarray
    modulation_ratio: np.ndarray

    def reject(self, where: np.ndarray, reason: Reason) -> None:
        """Mark the valid pixels ``where`` (H, W) invalid for ``reason`` (a test made after decoding)."""
        where = np.asarray(where, bool) & self.mask
        self.reason[where] = int(reason)
        self.mask &= ~where
        self.xp[where] = np.nan
        self.yp[where] = np.nan

    def coverage(self) -> dict[str, int]:
        """Pixel count per reason name."""
        counts = np.bincount(self.reason.ravel(), minlength=len(Reason))
        return {r.name: int(counts[r]) for r in Reason}


def _scale_for(dtype: np.dtype, white_level: float | None) -> float:
    if white_level is not None:
        if not white_level > 0:
            raise InputError(f"white_level must be positive, got {white_level}")
        return 1.0 / float(white_level)
    if np.issubdtype(dtype, np.integer):
        return 1.0 / float(np.iinfo(dtype).max)
    if np.issubdtype(dtype, np.floating):
        return 1.0
    raise InputError(f"unsupported frame dtype {dtype}; use uint8, uint16, float16 or float32")


def _coefficients(n_shifts: int) -> tuple[list[float], list[float]]:
    """sin and cos of δ_n with exact zeros (so 4-step sets skip half of the multiply-adds)."""
    deltas = [2 * math.pi * n / n_shifts for n in range(n_shifts)]
    clean = lambda v: 0.0 if abs(v) < 1e-12 else v  # noqa: E731
    return [clean(math.sin(d)) for d in deltas], [clean(math.cos(d)) for d in deltas]


def four_step(frames: np.ndarray) -> np.ndarray:
    """The 4-step set (4, ...) of one N-step fringe set ``frames`` (N, ...), N >= 3 shifts δ_n = 2πn/N.

    A linear camera sees a sinusoid at the fringes' frequency as ``A + C cos δ + S sin δ`` per pixel, so
    the first harmonic of any N-step set (A, C, S: least squares, exact for equally spaced shifts) gives
    the images the paper's 4 shifts (δ = 0, π/2, π, 3π/2) would have given; a 4-step set is returned as it is.
    """
    frames = np.asarray(frames, np.float32)
    n = len(frames)
    if n == 4:
        return frames
    if n < 3:
        raise InputError(f"a fringe set needs at least 3 shifts, got {n}")
    sin, cos = (np.asarray(c, np.float32).reshape((n,) + (1,) * (frames.ndim - 1)) for c in _coefficients(n))
    a = frames.mean(0)
    c, s = (2.0 / n) * (frames * cos).sum(0), (2.0 / n) * (frames * sin).sum(0)
    return np.stack([a + c, a + s, a - c, a - s])


class _Block:
    """Accumulates Σ I_n sin δ_n, Σ I_n cos δ_n and Σ I_n over one block of rows.

    Sums run in raw input units and are scaled once at the end; non-finite inputs are found from the
    non-finite sums (NaN/inf propagate into Σ I_n), saturation from the running per-pixel peak.
    """

    def __init__(self, scale: float, saturation: float | None) -> None:
        self.scale, self.saturation = scale, saturation
        self.S = self.C = self.A = self.peak = None
        self.floating = False
        self.saturated: np.ndarray | None = None
        self.bad: np.ndarray | None = None

    def add(self, arr: np.ndarray, s: float, c: float, *, mono: bool = False) -> None:
        """Accumulate one frame block; ``mono`` averages colour channels first."""
        arr = np.ascontiguousarray(arr)
        self.floating = arr.dtype.kind == "f"
        if self.saturation is not None:
            p = arr.max(-1) if arr.ndim == 3 else arr
            self.peak = p.copy() if self.peak is None else np.maximum(self.peak, p, out=self.peak)
        t = torch.from_numpy(arr).to(torch.float32)
        if mono and t.ndim == 3:
            t = t.mean(-1)
        if self.A is None:
            shares_input = t.data_ptr() == torch.from_numpy(arr).data_ptr()
            self.A = t.clone() if shares_input else t
        else:
            self.A.add_(t)
        self.S = _accumulate(self.S, t, s)
        self.C = _accumulate(self.C, t, c)

    def check(self) -> None:
        """Set ``bad`` (non-finite input; those sums are zeroed) and ``saturated``."""
        if self.floating:
            finite = np.isfinite(self.A.numpy())
            if not finite.all():
                self.bad = ~(finite.all(-1) if finite.ndim == 3 else finite)
                for t in (self.A, self.S, self.C):
                    np.copyto(t.numpy(), 0.0, where=~finite)
        if self.peak is not None:
            self.saturated = _at_or_above(self.peak, self.saturation / self.scale)

    def finish(self, n: int, *, phase: bool = True) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
        """(phi or None, A, B) of the accumulated set in normalised units (after ``check``)."""
        phi = _phase(self.S, self.C) if phase else None
        return phi, self.A.mul_(self.scale / n), _modulation(self.S, self.C, 2 * self.scale / n)

    def low_modulation(self, n: int, min_modulation: float, min_contrast: float) -> np.ndarray:
        """``B < max(min_modulation, min_contrast * A)`` from the raw sums, without a square root:
        ``S² + C² < max(min_modulation * n / (2 scale), min_contrast * ΣI / 2)²``."""
        m2 = torch.mul(self.S, self.S).addcmul_(self.C, self.C)
        floor = torch.mul(self.A, min_contrast / 2).clamp_(min=min_modulation * n / (2 * self.scale)).square_()
        return np.less(m2.numpy(), floor.numpy())


def _phase(S: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
    """``atan2(S, C)`` in [0, 2π) (OpenCV's vectorised ``phase``; unwrapping works modulo 2π anyway)."""
    return torch.from_numpy(cv2.phase(np.ascontiguousarray(C.numpy()), np.ascontiguousarray(S.numpy())))


def _at_or_above(values: np.ndarray, level: float) -> np.ndarray:
    """``values >= level`` in the array's own dtype (an integer array against a float would be cast to float64)."""
    if values.dtype.kind in "ui":
        level = math.ceil(level - 1e-9)
        if level > np.iinfo(values.dtype).max:
            return np.zeros(values.shape, bool)
        level = max(level, np.iinfo(values.dtype).min)
    return np.greater_equal(values, values.dtype.type(level))


def _accumulate(total: torch.Tensor | None, t: torch.Tensor, weight: float) -> torch.Tensor | None:
    """``total + weight * t`` in place, skipping zero weights (half of them for 4 shifts)."""
    if weight == 0:
        return total
    if total is None:
        return t * weight
    return total.add_(t, alpha=weight)


def _modulation(S: torch.Tensor, C: torch.Tensor, factor: float) -> torch.Tensor:
    """``factor * sqrt(S² + C²)`` (twice as fast as torch.hypot here)."""
    return torch.mul(S, S).addcmul_(C, C).sqrt_().mul_(factor)


def _row_blocks(height: int, width: int, rows: int | None) -> list[slice]:
    step = rows or max(1, BLOCK_PIXELS // max(1, width))
    return [slice(r, min(r + step, height)) for r in range(0, height, step)]


def _for_each_block(fn: Callable[[slice], None], blocks: list[slice]) -> None:
    """Run ``fn`` on every block, on ``torch.get_num_threads()`` threads with one torch thread each."""

    def run(rows: slice) -> None:
        with torch.inference_mode():
            fn(rows)

    workers = min(torch.get_num_threads(), len(blocks))
    if workers <= 1:
        for rows in blocks:
            run(rows)
        return
    with ThreadPoolExecutor(workers, initializer=torch.set_num_threads, initargs=(1,)) as pool:
        for _ in pool.map(run, blocks):
            pass


def wrapped_phase(
    stack: np.ndarray | Sequence[np.ndarray], *, white_level: float | None = None, block_rows: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrapped phase in (-π, π], offset A and modulation B of an N-step stack ``(N, H, W[, C])``.

    Outputs have the spatial (and channel) shape of one frame, float32; non-finite inputs give NaN.
    The arctangent is accurate to 2e-4 rad.
    """
    frames = list(stack)
    n = len(frames)
    if n < 3:
        raise InputError(f"phase shifting needs at least 3 frames, got {n}")
    shape = frames[0].shape
    if any(f.shape != shape for f in frames) or len(shape) not in (2, 3):
        raise InputError(f"frames must all be (H, W) or (H, W, C) of one shape, got {[f.shape for f in frames]}")
    scale = _scale_for(frames[0].dtype, white_level)
    sin, cos = _coefficients(n)
    out = [np.empty(shape, np.float32) for _ in range(3)]

    def block(rows: slice) -> None:
        blk = _Block(scale, None)
        for f, s, c in zip(frames, sin, cos, strict=True):
            blk.add(f[rows], s, c)
        blk.check()
        for o, r in zip(out, blk.finish(n), strict=True):
            o[rows] = r.numpy()
        phi = out[0][rows]
        np.subtract(phi, np.float32(2 * math.pi), out=phi, where=phi > math.pi)  # [0, 2π) -> (-π, π]
        if blk.bad is not None:
            for o in out:
                np.copyto(o[rows], np.nan, where=blk.bad if o.ndim == 2 else blk.bad[..., None])

    _for_each_block(block, _row_blocks(shape[0], shape[1], block_rows))
    return out[0], out[1], out[2]


def modulation_ratio(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """B/A, 0 where A <= 0 or not finite (fringe contrast; 1 for a perfect sinusoid of full swing)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(A > 0, B / A, 0.0)
    return np.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def _coarse_position(phi: torch.Tensor, period: float, extent: int) -> torch.Tensor:
    """Absolute position from a wrapped phase whose period spans the screen; the ambiguity gap is
    centred outside the projector image."""
    centre = extent / 2 - 0.5
    v = phi.mul(1 / (2 * math.pi)).add_(0.5 - centre / period)
    return v.sub_(torch.floor(v)).mul_(period).add_(centre - 0.5 * period)


@dataclass(frozen=True)
class _Settings:
    scale: float
    saturation: float | None
    min_modulation: float
    min_contrast: float
    unwrap_tolerance: float


@dataclass
class _Flags:
    """Per-pixel invalidity flags of one block of rows as numpy bools (None: no pixel flagged).

    Comparisons and logic run in numpy: its SIMD compares are ~4x torch's on this CPU.
    """

    bad: np.ndarray | None = None
    saturated: np.ndarray | None = None
    low: np.ndarray | None = None
    inconsistent: np.ndarray | None = None
    outside: np.ndarray | None = None

    def add(self, name: str, value: np.ndarray | None) -> None:
        old = getattr(self, name)
        if old is None or value is None:
            setattr(self, name, value if old is None else old)
        else:
            np.logical_or(old, value, out=old)


def _unwrap(
    sets: list[list[np.ndarray]],
    periods: tuple[float, ...],
    extent: int,
    th: _Settings,
    flags: _Flags,
) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """Temporal hierarchical unwrapping of one orientation (fringe sets coarsest first).

    Returns the position in projector px and the high-frequency (A_c, B_c, A, B): per-channel and
    channel-mean offset and modulation.
    """
    n = len(sets[0])
    sin, cos = _coefficients(n)
    x = None
    for level, (frames, period) in enumerate(zip(sets, periods, strict=True)):
        is_hf = level == len(periods) - 1
        blk = _Block(th.scale, th.saturation)
        for f, s, c in zip(frames, sin, cos, strict=True):
            blk.add(f, s, c, mono=not is_hf)
        blk.check()
        flags.add("bad", blk.bad)
        flags.add("saturated", blk.saturated)
        if not is_hf:  # lower frequencies: phase and the modulation test only
            flags.add("low", blk.low_modulation(n, th.min_modulation, th.min_contrast))
            phi = _phase(blk.S, blk.C)
        elif blk.A.ndim == 3:  # colour high frequency: decode the channel mean, keep per-channel A, B
            _, A_c, B_c = blk.finish(n, phase=False)
            S, C = blk.S.mean(-1), blk.C.mean(-1)
            phi, A, B = _phase(S, C), A_c.mean(-1), _modulation(S, C, 2 * th.scale / n)
        else:
            phi, A, B = blk.finish(n)
            A_c, B_c = A[..., None], B[..., None]
        if is_hf:
            floor = torch.mul(A, th.min_contrast).clamp_(min=th.min_modulation)
            flags.add("low", np.less(B.numpy(), floor.numpy()))
        if x is None:
            x = _coarse_position(phi, period, extent)
        else:
            # residual r: coarse position minus fine phase, in fringes, less its nearest integer
            r = torch.mul(x, 1 / period).add_(phi, alpha=-1 / (2 * math.pi))
            r.sub_(torch.round(r))
            x.add_(r, alpha=-period)
            flags.add("inconsistent", np.greater(r.abs_().numpy(), th.unwrap_tolerance))
    xn = x.numpy()
    flags.add("outside", np.less(xn, -0.5) | np.greater_equal(xn, extent - 0.5))
    return x, (A_c, B_c, A, B)


def decode(
    frames: Mapping[str, np.ndarray],
    config: PSPConfig,
    projector_size: tuple[int, int],
    *,
    min_modulation: float = 0.01,
    min_contrast: float = 0.02,
    min_offset: float = 0.005,
    saturation: float | None = None,
    unwrap_tolerance: float = 0.25,
    white_level: float | None = None,
    block_rows: int | None = None,
) -> Correspondence:
    """Decode PSP frames (keyed ``psp/{x|y}/p{period}/s{n}``) into camera -> projector correspondences.

    Thresholds (in normalised intensity units, see module doc):
      * ``min_modulation`` (0.01): B of every fringe set must reach it, else LOW_MODULATION;
      * ``min_contrast`` (0.02): and B/A too;
      * ``min_offset`` (0.005): high-frequency A below it is SHADOW;
      * ``saturation`` (default 0.99 for integer inputs, off for floats): any channel of any frame at or
        above it is SATURATED;
      * ``unwrap_tolerance`` (0.25): a coarser level may disagree with the finer one by at most this
        fraction of the finer period, else UNWRAP_INCONSISTENT.
    The coarsest period must cover the projector extent in its orientation.
    """
    wp, hp = (int(v) for v in projector_size)
    for name, value in (("min_modulation", min_modulation), ("min_contrast", min_contrast), ("min_offset", min_offset),
                        ("unwrap_tolerance", unwrap_tolerance)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a finite number >= 0, got {value!r}")
    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        raise InputError(f"saturation must be a positive finite level, got {saturation!r}")
    if set(config.orientations) != {"x", "y"}:
        raise InputError("decoding needs fringe sets in both orientations ('x' and 'y')")
    keys = {(o, p, n): psp_key(o, p, n) for o in ("x", "y") for p in config.periods for n in range(config.n_shifts)}
    missing = [k for k in keys.values() if k not in frames]
    if missing:
        raise InputError(f"{len(missing)} PSP frames missing, e.g. {', '.join(missing[:4])}")
    for o, extent in (("x", wp), ("y", hp)):
        if config.periods[0] < extent:
            raise InputError(
                f"coarsest period {config.periods[0]:g} px is shorter than the projector extent {extent} px "
                f"along {o}, so its positions cannot be told apart: is the projector size right? (else the frames "
                "need coarser unwrap periods, as `sss patterns` plans them)"
            )
    first = frames[keys[("x", config.period, 0)]]
    shape = first.shape
    if len(shape) not in (2, 3) or any(frames[k].shape != shape for k in keys.values()):
        raise InputError(f"PSP frames must all share one (H, W) or (H, W, C) shape; first is {shape}")
    if any(frames[k].dtype != first.dtype for k in keys.values()):
        raise InputError("PSP frames must all share one dtype")
    scale = _scale_for(first.dtype, white_level)
    if saturation is None and np.issubdtype(first.dtype, np.integer) and white_level is None:
        saturation = 0.99
    H, W = shape[:2]
    C = shape[2] if len(shape) == 3 else 1
    out = {
        "xp": np.empty((H, W), np.float32),
        "yp": np.empty((H, W), np.float32),
        "reason": np.empty((H, W), np.uint8),
        "modulation": np.empty((H, W), np.float32),
        "offset": np.empty((H, W), np.float32),
        "modulation_ratio": np.empty((H, W, C), np.float32),
    }
    settings = _Settings(scale, saturation, min_modulation, min_contrast, unwrap_tolerance)

    def block(rows: slice) -> None:
        flags = _Flags()
        pos: dict[str, torch.Tensor] = {}
        hf: dict[str, tuple[torch.Tensor, ...]] = {}
        for o, extent in (("x", wp), ("y", hp)):
            sets = [[frames[keys[(o, p, i)]][rows] for i in range(config.n_shifts)] for p in config.periods]
            pos[o], hf[o] = _unwrap(sets, config.periods, extent, settings, flags)
        offset = (hf["x"][2] + hf["y"][2]) * 0.5
        modulation = torch.clamp(hf["x"][3], max=hf["y"][3])  # elementwise min (torch.minimum is slow)
        reason = np.zeros(offset.shape, np.uint8)
        for flag, code in (  # lowest priority first: later codes overwrite earlier ones
            (flags.outside, Reason.OUTSIDE),
            (flags.inconsistent, Reason.UNWRAP_INCONSISTENT),
            (flags.low, Reason.LOW_MODULATION),
            (np.less(offset.numpy(), min_offset), Reason.SHADOW),
            (flags.saturated, Reason.SATURATED),
            (flags.bad, Reason.BAD_INPUT),
        ):
            if flag is not None:
                np.copyto(reason, int(code), where=flag)
        invalid = reason != 0
        for name, value in (("xp", pos["x"]), ("yp", pos["y"]), ("modulation", modulation), ("offset", offset)):
            out[name][rows] = value.numpy()
        np.copyto(out["xp"][rows], np.nan, where=invalid)
        np.copyto(out["yp"][rows], np.nan, where=invalid)
        out["reason"][rows] = reason
        ratio = sum(torch.where(v[0] > 0, v[1] / v[0], torch.zeros(())) for v in hf.values()) * 0.5
        out["modulation_ratio"][rows] = torch.nan_to_num(ratio, nan=0.0, posinf=0.0, neginf=0.0).numpy()

    _for_each_block(block, _row_blocks(H, W, block_rows))
    return Correspondence(mask=out["reason"] == 0, **out)


#: A silhouette pixel whose own Bayer sample shows less than this share of the fringe modulation that its
#: demosaiced colour shows is demosaicing's bleed, not surface (:func:`demosaic_bleed`). Measured on the
#: sim rig's crab and sand rake: such background pixels 0.02-0.07 (median), lit silhouette pixels 0.1-0.9,
#: interior pixels at least the object's dimmest colour's share (0.37 and 0.49 there).
BLEED_RATIO = 0.1


def demosaic_bleed(mask: np.ndarray, fringe_sets: list[np.ndarray], layout: str = "RGGB", *,
                   ratio: float = BLEED_RATIO, border: int = 4, reach: int = 3) -> np.ndarray:
    """(H, W) bool: pixels on the edge of ``mask`` (beside a pixel outside it) whose fringes came from their
    neighbours through demosaicing, not from the surface.

    A pixel measures one colour, its own Bayer sample; demosaicing (Malvar's, OpenCV's edge-aware away from
    the image border) keeps that sample and fills the other two from the neighbours. Beside a bright
    silhouette a background pixel then shows the object's fringes in its filled colours while its own
    sample stays at the noise: it decodes as surface, and relighting gave it the object's light (on the
    sim rig's demo objects 2-4% of the mask held 23-36% of the decoder's squared error against the
    render). ``fringe_sets``: phase-shift sets ``(N, H, W, 3)`` (N equally spaced shifts); the own sample's
    modulation B (:func:`wrapped_phase`), summed over the sets, is compared with the channel mean's. Only the mask's edge is tested
    (a colour missing from an object's interior is its colour, not bleed), peeled up to ``reach`` times (the
    demosaicers reach 2 px, the 3 x 3 median per Bayer plane one more), and not within ``border`` px of
    the image border, where the demosaicers pad."""
    from sssphase_core.processing.isp import bayer_mosaic

    mask = np.asarray(mask, bool)
    h, w = mask.shape
    own = sum(wrapped_phase(bayer_mosaic(np.asarray(frames), layout))[2] for frames in fringe_sets)
    mean = sum(wrapped_phase(np.asarray(frames).mean(axis=-1))[2] for frames in fringe_sets)
    borrowed = own < ratio * mean
    borrowed[:border], borrowed[h - border:], borrowed[:, :border], borrowed[:, w - border:] = False, False, False, False
    kept, bleed = mask.copy(), np.zeros_like(mask)
    for _ in range(reach):
        padded = np.pad(kept, 1, constant_values=True)  # the image border is not a silhouette
        inner = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
        peel = kept & ~inner & borrowed
        if not peel.any():
            break
        bleed |= peel
        kept &= ~peel
    return bleed


def decode_camera(frames: Mapping[str, np.ndarray], config: PSPConfig, projector_size: tuple[int, int], *,
                  bayer: str | None = None, **thresholds: float | int | None) -> Correspondence:
    """:func:`decode` for a camera's frames: where they come from a Bayer sensor of layout ``bayer`` (its
    demosaicing keeps each pixel's own sample), silhouette pixels that only demosaicing lit are dropped
    (``Reason.DEMOSAIC_BLEED``, :func:`demosaic_bleed`)."""
    corr = decode(frames, config, projector_size, **thresholds)
    if bayer is not None and np.ndim(frames[config.input_keys[0]]) == 3:  # colour frames (a mono camera has no mosaic)
        keys = config.input_keys
        n = config.n_shifts
        sets = [np.stack([frames[k] for k in keys[i:i + n]]) for i in range(0, len(keys), n)]
        corr.reject(demosaic_bleed(corr.mask, sets, bayer), Reason.DEMOSAIC_BLEED)
    return corr



def declip(stack: np.ndarray, saturation: float, *, white: np.ndarray | None = None, white_saturation: float | None = None,
           black: float = 0.0, margin: float = SATURATION_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """Repair clipped samples of the paper's 8 inputs (4 shifts per orientation) from the others.

    With 4 shifts, ``I_n + I_{n+2} = 2A`` for both pairs (n = 0, 1), so a sample clipped at the top is
    ``2A - I_{n+2}`` once A is known: from the orientation's unclipped pair, else from the white capture
    (A = (black + (1 - black) / 2) x white for a projector with relative ``black`` level). A sample
    counts as clipped from ``margin`` x ``saturation`` (demosaicing spreads a clipped sample over its
    neighbours). Not recoverable: both samples of a pair clipped, or one in each pair without a usable
    white value (absent, or itself at ``white_saturation``).

    Args:
        stack: (8, H, W, 3) linear camera units, x shifts 0..3 then y shifts 0..3.
        saturation: the stack's clipping level in the same units.
        white: (H, W, 3) full-white capture, or None.
        white_saturation: the white's clipping level (None: it does not clip, e.g. HDR).

    Returns:
        (repaired (8, H, W, 3) float32 copy, unrecovered (H, W) bool: some colour of some orientation
        still clipped).
    """
    x = np.array(stack, np.float32, copy=True)
    if x.ndim != 4 or x.shape[0] != 8 or x.shape[-1] != 3:
        raise InputError(f"declip needs the (8, H, W, 3) paper inputs, got {x.shape}")
    if not saturation > 0:
        raise InputError(f"saturation must be positive, got {saturation}")
    level = np.float32(margin * saturation)
    a_white = None
    if white is not None:
        w = np.asarray(white, np.float32)
        a_white = np.where(np.isfinite(w), w * np.float32(black + (1.0 - black) / 2.0), np.nan)
        if white_saturation is not None:
            a_white = np.where(w < margin * white_saturation, a_white, np.nan)
    unrecovered = np.zeros(x.shape[1:3], bool)
    for o in (0, 4):
        s = x[o : o + 4]  # view: shift n, pairs (0, 2) and (1, 3)
        clipped = s >= level  # (4, H, W, 3)
        if not clipped.any():
            continue
        n_clipped = clipped[:2].astype(np.int8) + clipped[2:]  # (2, H, W, 3) per pair
        pair_a = 0.5 * (s[:2] + s[2:])
        good = n_clipped == 0
        n_good = good.sum(axis=0)
        a = np.where(n_good > 0, (pair_a * good).sum(axis=0) / np.maximum(n_good, 1), np.nan)
        if a_white is not None:
            a = np.where(n_good > 0, a, a_white)
        for n in range(4):
            fix = clipped[n] & (n_clipped[n % 2] == 1) & np.isfinite(a)
            s[n] = np.where(fix, np.maximum(2.0 * a - s[(n + 2) % 4], s[n]), s[n])  # at least what clipped
        lost = (n_clipped == 2).any(axis=0) | ((n_clipped > 0).any(axis=0) & ~np.isfinite(a))
        unrecovered |= lost.any(axis=-1)
    return x, unrecovered
