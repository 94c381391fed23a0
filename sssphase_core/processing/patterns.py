"""Projector patterns and capture plans (numpy only, never torch).

Pattern values are float32 in [0, 1] (what is sent to the projector). The projector emits
``black + (1 - black) * value**gamma``, so phase-shift patterns are pre-distorted with ``1 / gamma``
to make the emitted light sinusoidal: shift ``n`` of an N-step set emits (up to the black level)
``0.5 + 0.5 cos(2π x / period - 2π n / N)``, hence the unwrapped phase at projector coordinate x
is ``2π x / period``.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from sssphase_core.errors import InputError

Orientation = Literal["x", "y"]
ORIENTATIONS: tuple[str, ...] = ("x", "y")
DEFAULT_GAMMA = 2.2
MAX_PERIOD_RATIO = 8.0
COARSE_MARGIN = 1.1  # the coarsest period spans the screen plus 5 % on each side
REFERENCE_NAMES = ("white", "black", "checkerboard", "stripes_x", "stripes_y")


def unknown_pattern(option: str, text: str) -> str:
    """The line for an ``option`` (--pattern, --reference) that names neither a file nor a named pattern: a path (a
    folder or a suffix in it) is no such file; a name, the named patterns and the closest one."""
    import difflib
    import os
    import stat
    from pathlib import PurePath

    try:
        mode = os.stat(text).st_mode
    except (OSError, ValueError):
        mode = None
    if mode is not None and not stat.S_ISREG(mode):  # (it said "no such file" of a FIFO, /dev/zero, a folder)
        kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
        return f"{option} {text} is {kind}, not an image file"
    if "/" in text or PurePath(text).suffix:
        return f"{option} {text}: no such file"
    close = difflib.get_close_matches(text, REFERENCE_NAMES, n=1)
    return (f"{option} {text!r} is neither an image file nor one of {', '.join(REFERENCE_NAMES)}"
            + (f": did you mean {close[0]}?" if close else ""))


MAX_SIDE = 16384  # largest projector side a plan or a frame spec may name
MAX_PROJECTOR_PIXELS = 1 << 26  # and most pixels (64 MP; an 8K projector has 33 MP): 16384 x 16384 took 4 GB a frame
MAX_SHIFTS = 32  # most phase shifts per fringe set a plan, an import or the decoder takes
MAX_UNWRAP_LEVELS = 16  # most unwrapping periods (a 16384 px side needs 4 at MAX_PERIOD_RATIO)


def _check_size(width: int, height: int) -> None:
    if int(width) < 1 or int(height) < 1:
        raise InputError(f"projector size must be positive, got {width}x{height}")
    if max(int(width), int(height)) > MAX_SIDE:
        raise InputError(f"projector size {width}x{height} is larger than any projector (at most {MAX_SIDE} px a side)")
    if int(width) * int(height) > MAX_PROJECTOR_PIXELS:
        raise InputError(f"projector size {width}x{height} is larger than any projector (at most "
                         f"{MAX_PROJECTOR_PIXELS >> 20} MP)")


def parse_projector_size(text: str) -> tuple[int, int]:
    """``"1920x1080"`` -> ``(1920, 1080)``, checked (positive, at most :data:`MAX_SIDE` a side)."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"projector size must look like 1920x1080, got {text!r}") from None
    _check_size(w, h)
    return w, h


def _check_orientation(orientation: str) -> None:
    if orientation not in ORIENTATIONS:
        raise InputError(f"orientation must be 'x' or 'y', got {orientation!r}")


def phase_shift_pattern(
    width: int,
    height: int,
    *,
    period: float,
    shift: int,
    n_shifts: int = 4,
    orientation: Orientation = "x",
    gamma: float = DEFAULT_GAMMA,
) -> np.ndarray:
    """Shift ``shift`` of an N-step sinusoidal fringe set, gamma pre-distorted, float32 (Hp, Wp)."""
    _check_size(width, height)
    _check_orientation(orientation)
    if n_shifts < 3:
        raise InputError(f"phase shifting needs at least 3 shifts, got {n_shifts}")
    if not period > 0:
        raise InputError(f"fringe period must be positive, got {period}")
    if not gamma > 0:
        raise InputError(f"gamma must be positive, got {gamma}")
    length = width if orientation == "x" else height
    coord = np.arange(length, dtype=np.float64)
    profile = 0.5 + 0.5 * np.cos(2 * np.pi * coord / period - 2 * np.pi * shift / n_shifts)
    profile = np.clip(profile, 0.0, 1.0) ** (1.0 / gamma)
    profile = profile.astype(np.float32)
    if orientation == "x":
        return np.ascontiguousarray(np.broadcast_to(profile[None, :], (height, width)))
    return np.ascontiguousarray(np.broadcast_to(profile[:, None], (height, width)))


def phase_shift_patterns(
    width: int,
    height: int,
    *,
    period: float,
    n_shifts: int = 4,
    orientation: Orientation = "x",
    gamma: float = DEFAULT_GAMMA,
) -> np.ndarray:
    """All N shifts of a fringe set, float32 ``(N, Hp, Wp)``."""
    return np.stack(
        [
            phase_shift_pattern(
                width, height, period=period, shift=n, n_shifts=n_shifts, orientation=orientation, gamma=gamma
            )
            for n in range(n_shifts)
        ]
    )


def paper_inputs(width: int, height: int, *, period: float, gamma: float = DEFAULT_GAMMA) -> np.ndarray:
    """The paper's 8 high-frequency inputs: 4 x-shifts then 4 y-shifts, float32 ``(8, Hp, Wp)``."""
    return np.concatenate(
        [phase_shift_patterns(width, height, period=period, n_shifts=4, orientation=o, gamma=gamma) for o in ORIENTATIONS]
    )


def white(width: int, height: int) -> np.ndarray:
    """Full-white pattern."""
    _check_size(width, height)
    return np.ones((height, width), np.float32)


def level(width: int, height: int, value: float) -> np.ndarray:
    """A uniform pattern of ``value`` in [0, 1] (grey ramps for projector calibration)."""
    _check_size(width, height)
    if not 0.0 <= value <= 1.0:
        raise InputError(f"a level pattern needs a value in [0, 1], got {value}")
    return np.full((height, width), value, np.float32)


def black(width: int, height: int) -> np.ndarray:
    """Full-black pattern (the projector still emits its black level)."""
    _check_size(width, height)
    return np.zeros((height, width), np.float32)


def dot_grid(width: int, height: int, spacing: int, shift_x: int, shift_y: int) -> np.ndarray:
    """Single lit projector pixels at ``(shift_y + j*spacing, shift_x + i*spacing)``.

    Over all ``spacing**2`` shifts every projector pixel is lit exactly once.
    """
    _check_size(width, height)
    if spacing < 1 or not (0 <= shift_x < spacing and 0 <= shift_y < spacing):
        raise InputError(f"dot grid needs spacing >= 1 and 0 <= shift < spacing, got {spacing}, ({shift_x}, {shift_y})")
    img = np.zeros((height, width), np.float32)
    img[shift_y::spacing, shift_x::spacing] = 1.0
    return img


def checkerboard(width: int, height: int, square: int, *, phase: int = 0) -> np.ndarray:
    """Binary checkerboard with ``square``-pixel squares; the top-left square is white for ``phase=0``."""
    _check_size(width, height)
    if square < 1:
        raise InputError(f"checkerboard square must be >= 1 pixel, got {square}")
    ys = np.arange(height)[:, None] // square
    xs = np.arange(width)[None, :] // square
    return ((ys + xs + phase) % 2 == 0).astype(np.float32)


def stripes(width: int, height: int, period: int, orientation: Orientation = "x") -> np.ndarray:
    """Binary stripes (half period on, half off) varying along projector ``orientation``."""
    _check_size(width, height)
    _check_orientation(orientation)
    if period < 2:
        raise InputError(f"stripe period must be >= 2 pixels, got {period}")
    length = width if orientation == "x" else height
    profile = ((np.arange(length) % period) < period / 2).astype(np.float32)
    shape = (height, width)
    return np.ascontiguousarray(np.broadcast_to(profile[None, :] if orientation == "x" else profile[:, None], shape))


@dataclass(frozen=True)
class PSPConfig:
    """A phase-shift session: the high-frequency ``period`` (projector px) with ``n_shifts`` shifts,
    plus the lower-frequency ``unwrap_periods`` (coarsest first) for temporal hierarchical unwrapping.
    """

    period: float
    n_shifts: int = 4
    unwrap_periods: tuple[float, ...] = ()
    orientations: tuple[str, ...] = ORIENTATIONS

    def __post_init__(self) -> None:
        if isinstance(self.period, bool) or not isinstance(self.period, numbers.Real) or not 0 < self.period < math.inf:
            raise InputError(f"fringe period must be a positive number, got {self.period!r}")
        if isinstance(self.n_shifts, bool) or not isinstance(self.n_shifts, numbers.Integral):
            raise InputError(f"the number of phase shifts must be an integer, got {self.n_shifts!r}")
        if self.n_shifts < 3:
            raise InputError(f"phase shifting needs at least 3 shifts, got {self.n_shifts}")
        if self.n_shifts > MAX_SHIFTS:
            raise InputError(f"phase shifting takes at most {MAX_SHIFTS} shifts, got {self.n_shifts}")
        if len(self.unwrap_periods) > MAX_UNWRAP_LEVELS:
            raise InputError(f"at most {MAX_UNWRAP_LEVELS} unwrapping periods, got {len(self.unwrap_periods)}")
        if not all(isinstance(p, numbers.Real) and not isinstance(p, bool) for p in self.unwrap_periods):
            raise InputError(f"unwrap periods must be numbers, got {list(self.unwrap_periods)[:4]}")
        periods = tuple(sorted((float(p) for p in self.unwrap_periods), reverse=True))
        if not all(math.isfinite(p) for p in periods):
            raise InputError(f"unwrap periods must be finite, got {self.unwrap_periods}")
        if any(p <= self.period for p in periods) or len(set(periods)) != len(periods):
            raise InputError(f"unwrap periods must be distinct and longer than {self.period}, got {self.unwrap_periods}")
        object.__setattr__(self, "unwrap_periods", periods)
        for o in self.orientations:
            _check_orientation(o)

    @property
    def periods(self) -> tuple[float, ...]:
        """All periods, coarsest first, ending with the high-frequency one."""
        return (*self.unwrap_periods, float(self.period))

    @property
    def input_keys(self) -> list[str]:
        """Plan keys of the learning inputs in their stacking order (ARCHITECTURE.md): the high-frequency
        shifts of ``x``, then of ``y`` (the paper's 8 images for 4 shifts)."""
        return [psp_key(o, float(self.period), n) for o in ("x", "y") for n in range(self.n_shifts)]


def period_ladder(period: float, extent: float, max_ratio: float = MAX_PERIOD_RATIO) -> tuple[float, ...]:
    """Lower-frequency periods (coarsest first) from one period spanning ``extent`` px (plus margin)
    down to ``period``, with a constant ratio ``<= max_ratio`` between neighbours (integers)."""
    coarsest = math.ceil(extent * COARSE_MARGIN)
    if coarsest <= period:
        return ()
    levels = max(1, math.ceil(math.log(coarsest / period) / math.log(max_ratio) - 1e-9))
    ratio = (coarsest / period) ** (1.0 / levels)
    ladder = [float(math.floor(period * ratio**k)) for k in range(1, levels)] + [float(coarsest)]
    return tuple(reversed(ladder))


def high_frequency_period(width: int, height: int) -> int:
    """A fringe period suited to the resolution: ~11 px at 256 px, ~20 px at 1080p."""
    return max(4, round(11 + 3 * math.log2(max(width, height) / 256)))


def psp_config_for(width: int, height: int, *, n_shifts: int = 4) -> PSPConfig:
    """Preset for a ``width x height`` projector: high-frequency period and an unwrapping ladder."""
    _check_size(width, height)
    period = high_frequency_period(width, height)
    return PSPConfig(period=period, n_shifts=n_shifts, unwrap_periods=period_ladder(period, max(width, height)))


def psp_key(orientation: str, period: float, shift: int) -> str:
    return f"psp/{orientation}/p{period:g}/s{shift}"


@dataclass(frozen=True)
class PlannedFrame:
    """One frame of a capture session; ``pattern()`` renders its projector image on demand."""

    key: str
    kind: str  # "psp" | "white" | "black" | "level" | "dots" | "ref"
    params: dict[str, Any] = field(hash=False)
    exposure: float = 1.0

    @property
    def name(self) -> str:
        """Unique name within a plan (the key, plus the exposure for HDR brackets)."""
        return f"{self.key}@e{self.exposure:g}" if "hdr" in self.params else self.key

    def pattern(self) -> np.ndarray:
        p = self.params
        w, h = p["width"], p["height"]
        if self.kind == "psp":
            return phase_shift_pattern(
                w, h, period=p["period"], shift=p["shift"], n_shifts=p["n_shifts"], orientation=p["orientation"], gamma=p["gamma"]
            )
        if self.kind == "white":
            return white(w, h)
        if self.kind == "black":
            return black(w, h)
        if self.kind == "level":
            return level(w, h, p["value"])
        if self.kind == "dots":
            return dot_grid(w, h, p["spacing"], p["shift_x"], p["shift_y"])
        if self.kind == "ref":
            if p["name"] == "checkerboard":
                return checkerboard(w, h, p["square"])
            return stripes(w, h, p["period"], p["orientation"])
        raise InputError(f"unknown frame kind {self.kind!r}")


def frame_params_problem(kind: str, params: Mapping[str, Any]) -> str | None:
    """Why ``params`` cannot render a frame of ``kind`` (missing keys, wrong types, out of range), or None.

    The daemon checks every frame spec of a capture request with this before the job starts, so a
    client's mistake is a ``bad_args`` reply, never an error inside the capture thread.
    """
    def integer(name: str, lo: int, hi: int) -> str | None:
        v = params.get(name)
        ok = isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi
        return None if ok else f"{kind} frame needs {name} as an integer in [{lo}, {hi}], got {v!r}"

    def number(name: str, lo: float, hi: float) -> str | None:
        v = params.get(name)
        ok = isinstance(v, int | float) and not isinstance(v, bool) and lo <= v <= hi
        return None if ok else f"{kind} frame needs {name} as a number in [{lo:g}, {hi:g}], got {v!r}"

    checks = [integer("width", 1, MAX_SIDE), integer("height", 1, MAX_SIDE)]
    if kind == "psp":
        checks += [number("period", 1e-3, 1e6), integer("n_shifts", 1, 64), integer("shift", 0, 63), number("gamma", 0.05, 20)]
        if params.get("orientation") not in ("x", "y"):
            checks.append(f"psp frame needs orientation x or y, got {params.get('orientation')!r}")
    elif kind == "level":
        checks.append(number("value", 0.0, 1.0))
    elif kind == "dots":
        checks += [integer("spacing", 1, MAX_SIDE), integer("shift_x", 0, MAX_SIDE), integer("shift_y", 0, MAX_SIDE)]
    elif kind == "ref":
        name = params.get("name")
        if name == "checkerboard":
            checks.append(integer("square", 1, MAX_SIDE))
        elif name in ("stripes_x", "stripes_y"):
            checks += [number("period", 1e-3, 1e6), None if params.get("orientation") in ("x", "y") else
                       f"ref frame needs orientation x or y, got {params.get('orientation')!r}"]
        else:
            checks.append(f"ref frame needs a name among checkerboard, stripes_x, stripes_y, got {name!r}")
    return next((c for c in checks if c), None)


@dataclass(frozen=True)
class CapturePlan(Sequence[PlannedFrame]):
    """The ordered frames of one capture session (lazy: patterns are rendered per frame)."""

    width: int
    height: int
    psp: PSPConfig | None
    frames: tuple[PlannedFrame, ...]
    gamma: float = DEFAULT_GAMMA

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i):  # type: ignore[override]
        return self.frames[i]

    def __iter__(self) -> Iterator[PlannedFrame]:
        return iter(self.frames)

    def keys(self) -> list[str]:
        """Distinct keys in capture order."""
        return list(dict.fromkeys(f.key for f in self.frames))

    def to_json(self) -> str:
        psp = None if self.psp is None else asdict(self.psp)
        return json.dumps(
            {
                "projector": [self.width, self.height],
                "gamma": self.gamma,
                "psp": psp,
                "frames": [{"name": f.name, "key": f.key, "kind": f.kind, "params": f.params, "exposure": f.exposure} for f in self.frames],
            },
            indent=1,
        )


def _reference_params(name: str, width: int, height: int) -> tuple[str, str, dict[str, Any]]:
    square = max(2, round(min(width, height) / 12))
    if name in ("white", "black"):
        return name, name, {}
    if name == "checkerboard":
        return "ref/checkerboard", "ref", {"name": name, "square": square}
    if name in ("stripes_x", "stripes_y"):
        return f"ref/{name}", "ref", {"name": name, "period": 2 * square, "orientation": name[-1]}
    raise InputError(f"unknown reference pattern {name!r}; choose from {', '.join(REFERENCE_NAMES)}")


def reference_pattern(name: str, width: int, height: int) -> np.ndarray:
    """Named reference pattern ``name`` (:data:`REFERENCE_NAMES`) at the size a capture plan uses:
    checker squares of min(width, height) / 12, stripe period two squares; float32 (Hp, Wp)."""
    _check_size(width, height)
    key, kind, params = _reference_params(name, width, height)
    return PlannedFrame(key, kind, {**params, "width": width, "height": height}).pattern()


#: The widest dot grid a plan takes (projector px): spacing^2 dot frames (the paper's 55 px: 3025 frames).
MAX_DOT_SPACING = 256


def check_dot_spacing(spacing: int, width: int | None = None, height: int | None = None) -> None:
    """Refuse a dot spacing that is not 1 to :data:`MAX_DOT_SPACING` px, or wider than the projector: a
    plan holds spacing^2 dot frames (10^12 grew the client to 24 GB before anything was captured)."""
    top = min([MAX_DOT_SPACING, *(s for s in (width, height) if s)])
    if isinstance(spacing, bool) or not isinstance(spacing, int) or not 1 <= spacing <= top:
        raise InputError(f"dot spacing must be 1 to {top} projector px (the projector's side at most; the plan "
                         f"holds spacing^2 dot frames), got {spacing}")


def check_dot_stride(stride: int, spacing: int | None = None) -> None:
    """Refuse a dot stride that is not 1 to the dot spacing (every shift: 1; one shift: the spacing)."""
    top = spacing or MAX_DOT_SPACING
    if isinstance(stride, bool) or not isinstance(stride, int) or not 1 <= stride <= top:
        upto = f"{top} (the dot spacing: one shift)" if spacing else "the dot spacing (one shift; `sss rigs` gives each preset's)"
        raise InputError(f"dot stride must be 1 (every dot shift) to {upto}, got {stride}")


def capture_plan(
    width: int,
    height: int,
    *,
    psp: PSPConfig | None = None,
    unwrap: bool = True,
    footprints: bool = False,
    dot_spacing: int = 55,
    references: Sequence[str] = (),
    hdr_exposures: Sequence[float] = (),
    gamma: float = DEFAULT_GAMMA,
    dot_stride: int = 1,
) -> CapturePlan:
    """Exactly the frames a session needs: PSP sets (high frequency, plus the unwrapping ladder when
    ``unwrap``), dot grids only with ``footprints`` (plus a black frame to subtract), the named
    ``references`` (see ``REFERENCE_NAMES``), each at every HDR exposure if brackets are given.
    ``dot_stride`` S > 1 keeps every S-th dot shift along x and y: ceil(spacing / S)^2 dot frames that give
    footprints to 1 / S^2 of the pixels (a decoder trains on a few thousand per view)."""
    _check_size(width, height)
    psp = psp_config_for(width, height) if psp is None else psp
    base: dict[str, Any] = {"width": int(width), "height": int(height)}
    specs: list[tuple[str, str, dict[str, Any]]] = []
    for o in psp.orientations:
        for period in psp.periods if unwrap else (float(psp.period),):
            for n in range(psp.n_shifts):
                params = {"orientation": o, "period": period, "shift": n, "n_shifts": psp.n_shifts, "gamma": gamma}
                specs.append((psp_key(o, period, n), "psp", params))
    refs = list(dict.fromkeys(references))
    if footprints and "black" not in refs:
        refs.append("black")
    specs += [_reference_params(name, width, height) for name in refs]
    if footprints:
        check_dot_spacing(dot_spacing, width, height)
        check_dot_stride(dot_stride, dot_spacing)
        for sy in range(0, dot_spacing, dot_stride):
            for sx in range(0, dot_spacing, dot_stride):
                specs.append((f"dots/{sx}_{sy}", "dots", {"spacing": dot_spacing, "shift_x": sx, "shift_y": sy}))
    exposures = tuple(float(e) for e in hdr_exposures) or (1.0,)
    if any(not e > 0 for e in exposures):
        raise InputError(f"exposures must be positive, got {hdr_exposures}")
    hdr = {"hdr": len(exposures)} if hdr_exposures else {}
    frames = tuple(
        PlannedFrame(key, kind, {**base, **params, **hdr}, exposure) for key, kind, params in specs for exposure in exposures
    )
    return CapturePlan(int(width), int(height), psp, frames, gamma)
