"""Export a session's views as OpenEXR files (linear float32, unclipped) for other tools.

Per view, into ``OUT/<object>/view_NNN/``: every image array (H, W[, C]) as ``<name>.exr`` (``/`` in
array names becomes ``_``), every stack (N, H, W, C) as ``<name>/NN.exr`` (the PSP frames with their plan
key, e.g. ``psp/x/p11/s0``, in the EXR header field ``sssphase_key`` and in ``psp/keys.csv``; the unwrapping
frames, when kept, likewise in ``unwrap/``), the footprint crops
(N, K, K, 3) as one mosaic ``footprints_crops.exr`` (tile ``i`` at row ``i // cols``, column
``i % cols``) with ``footprints_pixels.csv`` giving each tile's camera pixel (row, col), and the captured
transport's crops (one per projector dot) likewise as ``transport_crops.exr`` beside ``transport_dots.csv``
and ``transport_pixels.csv``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.store.exr import write_exr
from sssphase_core.store.files import atomic_folder, write_text
from sssphase_core.store.session import Session, view_dir_name

#: What an export writes into a view's folder (EXR images, CSV keys and pixel lists): anything else is the user's.
EXPORTED_SUFFIXES = (".exr", ".csv")


def footprint_mosaic(crops: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, K, K, C) -> (rows*K, cols*K, C) tiles in row-major order (empty tiles NaN), and cols."""
    n, k = crops.shape[0], crops.shape[1]
    cols = max(1, math.ceil(math.sqrt(n)))
    rows = max(1, math.ceil(n / cols))
    mosaic = np.full((rows * k, cols * k, crops.shape[-1]), np.nan, np.float32)
    for i in range(n):
        r, c = divmod(i, cols)
        mosaic[r * k:(r + 1) * k, c * k:(c + 1) * k] = crops[i]
    return mosaic, cols


def _is_image(shape: tuple[int, ...], height: int, width: int) -> bool:
    """Whether an array of ``shape`` is one (H, W) or (H, W, C) image of the view rather than a stack of them
    ((N, H, W[, C]): a 16x16 view's 16 unwrapping frames are (16, 16, 16, 3), whose first two sizes are H, W)."""
    return shape[:2] == (height, width) and (len(shape) == 2 or (len(shape) == 3 and shape[2] <= 4))


def export_view(session: Session, view: int, out: Path) -> list[Path]:
    """Write one view's arrays under ``out`` (see the module docstring); returns the files written."""
    height, width = session.read(view, "white").shape[:2]
    written: list[Path] = []
    for name in session.arrays(view):
        arr = session.load(view, name)  # whole: held to its checksum (an export must not launder a changed array)
        stem = out / name.replace("/", "_")
        shape = tuple(arr.shape)
        if name.endswith("/crops") and len(shape) == 4:  # footprints/crops; transport/crops (one per projector dot)
            mosaic, cols = footprint_mosaic(np.asarray(arr, np.float32))
            written.append(write_exr(stem.with_name(stem.name + ".exr"), mosaic, attributes={"tile_columns": str(cols)}))
        elif _is_image(shape, height, width):
            written.append(write_exr(stem.with_name(stem.name + ".exr"), np.asarray(arr, np.float32)))
        elif len(shape) >= 3 and shape[1:3] == (height, width):
            keys = session.manifest["views"].get(str(view), {}).get(f"{name}_keys") or (
                _psp_keys(session) if name == "psp" else _dots_keys(session) if name == "dots" else None)
            keys = keys if keys and len(keys) == shape[0] else None  # (the manifest's psp_keys, unwrap_keys)
            digits = max(2, len(str(shape[0] - 1)))  # 000 ... 288: the files sort in the stack's order
            for i in range(shape[0]):
                attributes = {"sssphase_key": keys[i]} if keys else None
                written.append(write_exr(stem / f"{i:0{digits}d}.exr", np.asarray(arr[i], np.float32), attributes=attributes))
            if keys:  # which frame each file holds, for tools that read no EXR header
                write_text(stem / "keys.csv", "file,key\n" + "".join(f"{i:0{digits}d}.exr,{k}\n" for i, k in enumerate(keys)))
                written.append(stem / "keys.csv")
        elif len(shape) == 2:  # per-row records such as footprints/pixels
            stem.parent.mkdir(parents=True, exist_ok=True)
            with open(stem.with_name(stem.name + ".csv"), "w", newline="") as f:
                csv.writer(f).writerows(np.asarray(arr).tolist())
            written.append(stem.with_name(stem.name + ".csv"))
    return written


def refuse_foreign_files(folder: Path) -> None:
    """InputError naming a file in an earlier export's view ``folder`` that no export writes (a user's notes,
    a tool's output saved beside the maps): replacing the folder would delete it."""
    if not folder.is_dir() or folder.is_symlink():
        if folder.exists() or folder.is_symlink():
            raise InputError(f"{folder} is not a folder an export wrote (a file or a link): move it, or choose another --out")
        return
    for path in sorted(folder.rglob("*")):
        if path.is_symlink() or not (path.is_dir() or (path.is_file() and path.suffix.lower() in EXPORTED_SUFFIXES)):
            raise InputError(f"{path} is no file sss export writes: exporting again replaces {folder} whole and would "
                             "delete it; move it out, or choose another --out")


def _psp_keys(session: Session) -> list[str] | None:
    """The plan keys (``psp/x/p11/s0`` ...) of a session's ``psp`` stack, in its order."""
    from sssphase_core.relight.views import paper_input_frames

    frames = paper_input_frames(session.manifest.get("plan", {}))
    return [f["key"] for f in frames] if frames else None


def _dots_keys(session: Session) -> list[str] | None:
    """The plan keys (``dots/3_5`` ...) of a session's kept ``dots`` stack (``--keep-dots``): its dot frames in
    capture order, one per grid frame (exposure brackets merged)."""
    keys = [f["key"] for f in session.manifest.get("plan", {}).get("frames", []) if f.get("kind") == "dots"]
    return list(dict.fromkeys(keys)) or None


def export_session(session: Session, out: Path, views: list[int] | None = None) -> list[Path]:
    """Export ``views`` (default: all complete views) of ``session`` to ``out/<object>/view_NNN``, each view's
    folder whole or not at all (a damaged array leaves an earlier export of that view as it was)."""
    written: list[Path] = []
    chosen = views if views is not None else session.views()
    for view in chosen:  # before any view is written: a re-export replaces each view's folder whole
        refuse_foreign_files(Path(out) / session.name / view_dir_name(view))
    for view in chosen:
        final = Path(out) / session.name / view_dir_name(view)
        with atomic_folder(final) as tmp:
            files = export_view(session, view, tmp)
        written += [final / f.relative_to(tmp) for f in files]
    plan = session.manifest.get("plan")
    if isinstance(plan, dict) and plan.get("projector"):  # as `sss patterns` writes it: an import of the export checks
        import json  # --projector and --gamma against it (a swapped 192x256 went through in silence)

        path = Path(out) / session.name / "plan.json"
        write_text(path, json.dumps(plan, indent=1))
        written.append(path)
    return written
