"""One view's PSP frames from a folder of files named by plan key (`sss decode`), read by the importer's
:class:`~sssphase_core.capture.importer.FrameLoader`, with the PSP configuration its ``plan.json`` (as
`sss patterns` writes it) or its file names give."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.capture.importer import (
    FrameLoader,
    frame_files,
    frame_scale,
    frames_encoding,
    psp_config_from_names,
)
from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.patterns import PSPConfig, parse_projector_size, psp_config_for, psp_key
from sssphase_core.store.imageio import stores_integers
from sssphase_core.store.session import plan_problem

#: ``progress(done, total)``: frames read so far.
FrameProgress = Callable[[int, int], None]


def read_plan(path: Path) -> dict[str, Any]:
    """A folder's ``plan.json`` (as `sss patterns` writes it), checked: one line naming the file otherwise."""
    from sssphase_core.store.files import read_json_input

    try:
        plan = read_json_input(path, "the capture plan")
    except OSError as exc:
        raise InputError(f"{path}: not a readable capture plan ({type(exc).__name__}: {str(exc).splitlines()[0][:80]})") from None
    problem = plan_problem(plan) or (None if isinstance(plan, dict) and "projector" in plan else "it names no projector size")
    if problem:
        raise InputError(f"{path}: {problem}")
    return plan


def psp_from_plan(plan: dict[str, Any], path: Path) -> PSPConfig:
    """The PSP configuration of a plan read by :func:`read_plan` from ``path`` (named in the error)."""
    psp = plan.get("psp")
    if not isinstance(psp, dict) or not psp:
        raise InputError(f"{path} has no PSP configuration (psp: period, n_shifts, unwrap_periods)")
    try:
        return PSPConfig(period=psp["period"], n_shifts=psp["n_shifts"], unwrap_periods=tuple(psp["unwrap_periods"]),
                         orientations=tuple(psp.get("orientations", ("x", "y"))))
    except InputError as exc:  # (a ValueError too) a value out of its range: named as it is
        raise InputError(f"{path}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: its psp configuration is incomplete or of the wrong type ({type(exc).__name__}: {exc})") from None


class _OneCamera(FrameLoader):
    """`sss decode`'s reader: NaN / inf refused, and a frame of another size named beside the first frame."""

    def refuse_size(self, path: Path, shape: tuple[int, ...]) -> None:
        assert self.shape is not None
        raise DataError(f"{path} is {shape[1]}x{shape[0]}, but {self.first} is {self.shape[1]}x{self.shape[0]}: every "
                        "frame must come from the same camera")


@dataclass
class PspFolder:
    """A folder's PSP frames by plan key, in camera units (float frames scaled by ``scale``, their 99.9th
    percentile ``level`` put at 1), with the projector ``size`` (W, H), the PSP ``config`` and the
    ``saturation`` level to decode them with (in the same units; None: no clipping)."""

    folder: Path
    size: tuple[int, ...]
    config: PSPConfig
    frames: dict[str, np.ndarray]
    saturation: float | None
    level: float
    scale: float


def read_psp_folder(folder: Path, projector: str | None = None, *, saturation: float | None = None,
                    progress: FrameProgress | None = None) -> PspFolder:
    """The PSP frames of one view in ``folder`` (files named by plan key, as `sss import` reads them; other
    images are skipped), for the projector ``projector`` ("WxH"; default: the folder's ``plan.json``).
    The PSP configuration is the plan's, else the file names', else the preset for the projector's size.
    ``saturation`` (None: 0.99 for integer files, none for float files) is in the files' units."""
    plan_path = folder / "plan.json"
    plan = read_plan(plan_path) if plan_path.is_file() else None
    if projector is not None:
        size = parse_projector_size(projector)
    elif plan is not None:
        size = tuple(plan["projector"])
    else:
        raise InputError(f"no plan.json in {folder}: give --projector WxH")
    files = frame_files(folder, strict=False)  # other images (e.g. `sss decode`'s own figures) are not frames
    if plan is not None:
        config = psp_from_plan(plan, plan_path)
    elif any(key.startswith("psp/") for key in files):  # the file names say the periods and shifts, as for `sss import`
        config = psp_config_from_names(folder, files)
    else:
        config = psp_config_for(*size)  # (names the first missing frame below)
    keys = [psp_key(o, p, n) for o in ("x", "y") for p in config.periods for n in range(config.n_shifts)]
    missing = [key for key in keys if key not in files]
    if missing and any(p.is_dir() and p.name.startswith("view_") for p in folder.iterdir()):
        raise InputError(f"{folder} holds view folders: decode one view at a time (sss decode {folder / 'view_000'} ...)")
    if missing:
        raise DataError(f"frame {missing[0]!r} not found in {folder} (expected {missing[0].replace('/', '__')}.png/.tif/"
                        f".exr/.npy or {missing[0]}.*; {len(missing)} of {len(keys)} PSP frames missing)")
    frames_encoding([files[key] for key in keys])  # one bit depth and colour tag, no JPEG: as `sss import` refuses
    integers = any(stores_integers(files[key]) for key in keys)
    if saturation is None and integers:
        saturation = 0.99  # integer files clip at their top code; EXR and float files do not clip
    loader = _OneCamera("auto", repair=False)  # tagged sRGB files as light, as `sss import` reads them
    frames = {}
    for done, key in enumerate(keys, 1):
        frames[key] = loader.read(files[key])
        if progress is not None:
            progress(done, len(keys))
    level = max(float(np.percentile(f, 99.9)) for f in frames.values())
    if not integers and not (level > 0 and np.isfinite(level)):
        raise InputError(f"the PSP frames in {folder} hold no light (99.9th percentile {level:.3g}): they must be "
                         "linear images of the fringe patterns")
    scale = frame_scale([files[key] for key in keys], [level])  # float frames in a renderer's units, as `sss import`
    if scale != 1.0:
        frames = {k: (f.astype(np.float64) * scale).astype(np.float32) for k, f in frames.items()}
        saturation = None if saturation is None else saturation * scale
    return PspFolder(folder, size, config, frames, saturation, level, scale)
