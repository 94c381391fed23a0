"""`sss decode`: a folder of captured PSP frames decoded into camera -> projector correspondences, written
as maps (``.npy``), viewable figures and ``decode.json``."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sssphase_core.capture.importer import nothing_decoded
from sssphase_core.capture.psp_folder import FrameProgress, PspFolder, read_psp_folder
from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import psp_key
from sssphase_core.reporting import figures as fig
from sssphase_core.store.files import atomic_path, write_text
from sssphase_core.store.session import check_output_folder

if TYPE_CHECKING:
    from sssphase_core.processing.psp import Correspondence

#: The arrays of a decoded folder, each ``<name>.npy``.
DECODED_ARRAYS = ("xp", "yp", "mask", "reason", "modulation", "offset", "modulation_ratio")
#: The figures of a decoded folder (:func:`_figures`).
DECODED_FIGURES = ("phase_x", "phase_y", "xp", "yp", "mask", "reason", "modulation")
SUMMARY = "decode.json"


def decoded_files() -> list[str]:
    """Every name :func:`decode_folder` writes in its ``out`` folder."""
    return [*(f"{n}.npy" for n in DECODED_ARRAYS), *(f"{n}.png" for n in DECODED_FIGURES), SUMMARY]


def check_decode_folder(out: Path) -> None:
    """Refuse, before any work, an ``out`` that holds files of these names not written by ``sss decode`` (a
    user's ``mask.png`` or ``xp.npy`` was replaced): ``out`` must be new, hold none of them, or be a decoded
    folder (its ``decode.json`` says so, also one a stopped decode left)."""
    taken = [n for n in decoded_files() if (out / n).exists() or (out / n).is_symlink()]
    if not taken:
        return
    try:
        summary = json.loads((out / SUMMARY).read_text()) if not (out / SUMMARY).is_symlink() else None
    except (OSError, ValueError):
        summary = None
    ours = isinstance(summary, dict) and (summary.get("written_by") == "sss decode"
                                          or {"projector", "psp", "coverage"} <= summary.keys())  # (before 0.x: no tag)
    if ours and not any(
            (out / n).is_symlink() or not (out / n).is_file() for n in taken):
        return
    shown = ", ".join(taken[:3]) + (f" and {len(taken) - 3} more" if len(taken) > 3 else "")
    raise InputError(f"--out {out} holds {shown}, which sss decode did not write (no decode.json of it): "
                     "give a new or empty folder")


@dataclass
class DecodedFolder:
    """What :func:`decode_folder` wrote to ``out``: the correspondence and its ``coverage`` (pixels per reason)."""

    out: Path
    corr: Correspondence
    coverage: dict[str, int]

    @property
    def pixels(self) -> int:
        return int(self.corr.mask.size)


def decode_folder(folder: Path, out: Path, *, projector: str | None = None, min_modulation: float = 0.01,
                  saturation: float | None = None, bayer: str | None = None, progress: FrameProgress | None = None,
                  report: Callable[[str], None] | None = None) -> DecodedFolder:
    """Decode the PSP frames in ``folder`` (:func:`~sssphase_core.capture.psp_folder.read_psp_folder`) into
    ``out``: ``xp, yp, mask, reason, modulation, offset, modulation_ratio`` as ``.npy``, their figures and
    the wrapped phases as PNGs, and ``decode.json`` (projector size, PSP configuration, coverage).
    ``bayer``: the frames were demosaiced from a sensor of that layout (silhouette pixels only demosaicing lit
    are dropped). ``report(line)`` is told when float frames were scaled to camera units. Where no pixel
    decodes, the maps and figures are written and an :class:`InputError` says why."""
    from sssphase_core.processing.isp import check_layout

    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    if not (math.isfinite(min_modulation) and min_modulation >= 0):  # before the frames are read
        raise InputError(f"--min-modulation must be a finite number >= 0, got {min_modulation!r}")
    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        raise InputError(f"--saturation must be a positive finite level in the frames' units, got {saturation!r}")
    if bayer is not None:
        bayer = check_layout(bayer.upper())
    check_output_folder(out)
    frames_dir, out_dir = folder.resolve(), out.resolve()
    if out_dir == frames_dir or frames_dir in out_dir.parents:  # the maps among the frames: a later read or import fails
        raise InputError(f"--out {out} would write among the frames of {folder}: choose a folder outside it")
    check_decode_folder(out)
    view = read_psp_folder(folder, projector, saturation=saturation, progress=progress)
    if view.scale != 1.0 and report is not None:
        report(f"float frames at level {view.level:.3g} (99.9th percentile) scaled to 1 (the decoder's thresholds are "
               "in camera units)")
    from sssphase_core.processing.psp import decode_camera  # torch: after the folder and options are checked

    corr = decode_camera(view.frames, view.config, view.size, bayer=bayer, min_modulation=min_modulation,
                         saturation=view.saturation)
    out.mkdir(parents=True, exist_ok=True)
    # first: the folder is ours (a rerun may replace it) and says that it is not whole until the end
    write_text(out / SUMMARY, json.dumps({"written_by": "sss decode", "complete": False}) + "\n")
    for name in DECODED_ARRAYS:
        with atomic_path(out / f"{name}.npy", ".npy") as tmp:  # (a full disk leaves no half array)
            np.save(tmp, getattr(corr, name))
    _figures(out, view, corr)
    config, coverage = view.config, corr.coverage()
    summary = {"written_by": "sss decode", "complete": True, "projector": list(view.size),
               "psp": {"period": config.period, "n_shifts": config.n_shifts,
                       "unwrap_periods": list(config.unwrap_periods)}, "coverage": coverage}
    write_text(out / SUMMARY, json.dumps(summary, indent=1) + "\n")
    if not coverage.get("VALID"):  # the maps and figures stay: they show why
        raise InputError(f"{nothing_decoded(folder, coverage)} (the maps and figures in {out} show where)")
    return DecodedFolder(out, corr, coverage)


def _figures(out: Path, view: PspFolder, corr: Correspondence) -> None:
    """The wrapped phase per orientation, the decoded maps, the mask, the reasons and the modulation as PNGs."""
    from sssphase_core.processing.psp import Reason, wrapped_phase

    config = view.config
    for o in ("x", "y"):
        stack = [view.frames[psp_key(o, config.period, n)] for n in range(config.n_shifts)]
        phi, _, _ = wrapped_phase([f.astype(np.float32).mean(-1) if f.ndim == 3 else f for f in stack])
        fig.value_figure(out / f"phase_{o}.png", np.where(corr.mask, (phi + np.pi) / (2 * np.pi), np.nan),
                         f"wrapped phase along {o} (period {config.period:g} px)", units="phase (cycles)",
                         cmap="twilight", vmin=0, vmax=1)
    for name, values, extent in (("xp", corr.xp, view.size[0]), ("yp", corr.yp, view.size[1])):
        fig.value_figure(out / f"{name}.png", np.where(corr.mask, values, np.nan),
                         f"decoded projector {name[0]} (black: not decoded)", units="projector px", cmap="turbo",
                         vmin=0, vmax=extent - 1)
    fig.label_figure(out / "mask.png", corr.mask.astype(np.int16), {0: "not decoded", 1: "decoded"}, "decoded pixels")
    fig.label_figure(out / "reason.png", corr.reason.astype(np.int16),
                     {r.value: r.name.lower().replace("_", " ") for r in Reason}, "decoding outcome per pixel")
    fig.value_figure(out / "modulation.png", corr.modulation, "fringe modulation B", units="linear camera units",
                     cmap="magma", vmin=0, vmax=float(np.percentile(corr.modulation, 99.5)) or 1.0)
