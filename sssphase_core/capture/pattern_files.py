"""`sss patterns`: the capture plan's projector patterns as 8-bit PNGs named by plan key, plus ``plan.json``,
for a rig this software does not drive (its captures come back through `sss import` or `sss decode`)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sssphase_core.capture.importer import GAMMA_RANGE
from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import (
    MAX_SHIFTS,
    PSPConfig,
    capture_plan,
    parse_projector_size,
    period_ladder,
    psp_config_for,
)
from sssphase_core.store.files import write_text
from sssphase_core.store.imageio import IMAGE_SUFFIXES
from sssphase_core.store.session import check_output_folder


@dataclass
class WrittenPatterns:
    out: Path
    patterns: int  # PNG files (one per plan key)
    planned: int  # planned frames (HDR brackets list a key once per exposure)


def pattern_config(width: int, height: int, *, period: float | None = None, shifts: int = 4,
                   gamma: float = 2.2) -> PSPConfig:
    """The fringes for a ``width`` x ``height`` projector: ``period`` (None: the preset for the size) with
    its unwrapping ladder, checked as `sss import` and the decoder take them (``gamma`` too)."""
    if period is not None and not (math.isfinite(period) and period >= 2):
        raise InputError(f"--period must be a finite fringe period of at least 2 projector px, got {period}")
    if shifts > MAX_SHIFTS:  # what `sss import` and the decoder take
        raise InputError(f"--shifts must be 3 to {MAX_SHIFTS}, got {shifts}")
    if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:  # NaN fails too
        raise InputError(f"--gamma must be a number in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}] (as a rig file's), got {gamma}")
    if period is not None and period > max(width, height):  # its frame names would also read p1e+06, which import refuses
        raise InputError(f"--period {period:g} is longer than the {width}x{height} projector: the fringes need at least "
                         "one period across it")
    if period is None:
        config = psp_config_for(width, height, n_shifts=shifts)
        if config.period > max(width, height):  # the default period is not shorter than a tiny projector either
            raise InputError(f"a {width}x{height} projector is smaller than one fringe period ({config.period:g} px): "
                             "PSP needs a few periods across it")
        return config
    return PSPConfig(period=period, n_shifts=shifts, unwrap_periods=period_ladder(period, max(width, height)))


def write_patterns(out: Path, projector: str, *, footprints: bool = False, dot_spacing: int = 55,
                   references: Iterable[str] = (), period: float | None = None, shifts: int = 4, unwrap: bool = True,
                   gamma: float = 2.2, hdr: str = "",
                   progress: Callable[[int, int], None] | None = None) -> WrittenPatterns:
    """Write the plan's patterns for a ``projector`` ("WxH") into the new folder ``out``: white and black
    always (an import needs both), ``references`` besides, the PSP sets (:func:`pattern_config`), the dot
    grids with ``footprints``; ``hdr``: comma-separated exposures listed in ``plan.json``.
    ``progress(done, total)`` after each PNG. A folder that already holds images or a plan is refused."""
    w, h = parse_projector_size(projector)
    config = pattern_config(w, h, period=period, shifts=shifts, gamma=gamma)
    try:
        exposures = tuple(float(e) for e in hdr.split(",") if e.strip())
    except ValueError:
        raise InputError(f"--hdr must be comma-separated numbers, got {hdr!r}") from None
    names = list(dict.fromkeys(["white", "black", *references]))  # every import needs both (mask, light)
    plan = capture_plan(w, h, psp=config, unwrap=unwrap, footprints=footprints, dot_spacing=dot_spacing,
                        references=names, hdr_exposures=exposures, gamma=gamma)
    check_output_folder(out)
    unique = list({f.key: f for f in plan}.values())
    held = None
    if out.is_dir():  # (bounded: the folder's own entries and the paths this plan writes, never a whole tree)
        mine = (out / f"{f.key}{suffix}" for f in unique for suffix in IMAGE_SUFFIXES)
        held = next((p for p in (*sorted(out.iterdir()), *mine) if p.is_file() and
                     (p.name == "plan.json" or p.suffix.lower() in IMAGE_SUFFIXES)), None)
    if held is not None:  # captured frames share the patterns' names; an earlier set would be left beside this one
        raise InputError(f"--out {out} already holds {held.relative_to(out)}: write the patterns into a new folder "
                         "(nothing was written)")
    from PIL import Image

    made = [d for d in (out, *out.parents) if not d.exists()]  # the folders this call creates, and the files it
    out.mkdir(parents=True, exist_ok=True)  # writes: what an interruption removes
    written: list[Path] = []
    try:
        for done, frame in enumerate(unique, 1):
            path = out / f"{frame.key}.png"
            if not path.parent.is_dir():
                made += [d for d in (path.parent, *path.parent.parents) if not d.exists()]
                path.parent.mkdir(parents=True)
            written.append(path)
            Image.fromarray(np.round(np.clip(frame.pattern(), 0, 1) * 255).astype(np.uint8)).save(path)
            if progress is not None:
                progress(done, len(unique))
        write_text(out / "plan.json", plan.to_json() + "\n")
    except BaseException:  # Ctrl-C, a full disk: a half set (refused by the next run) is removed, nothing else
        for path in written:
            path.unlink(missing_ok=True)
        for folder in sorted(made, key=lambda d: len(d.parts), reverse=True):  # innermost first
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty
        raise
    return WrittenPatterns(out, len(unique), len(plan))
