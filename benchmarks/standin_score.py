"""Score relit images and projector correspondences of stand-in renders against their noise-free truth.

    python benchmarks/standin_score.py relight RENDERS SESSIONS RELIT BACKEND[,BACKEND...]
    python benchmarks/standin_score.py geometry RENDERS OBJECT GEOMETRY_NPZ [GEOMETRY_NPZ ...]

``relight``: PSNR of ``RELIT/OBJECT_v0_PATTERN_BACKEND.exr`` (``sss relight --format exr``) against
``RENDERS/OBJECT_clean_ref__PATTERN.exr`` on the view's decoded mask, and >= 2 px inside it, for every
session under SESSIONS. ``geometry``: the decoded and the geometry-corrected projector x, y of
``sss geometry``'s ``correspondence_for_geometry.npz`` against ``RENDERS/OBJECT_geometry.npz``
(``standin_volumetric.py``, ``mitsuba_render.py``), median signed error by incidence angle.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np


def psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a[where] - b[where]) ** 2)))


def relight(renders: Path, sessions: Path, relit: Path, backends: list[str]) -> None:
    from sssphase_core.relight import load_view
    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.session import find_sessions

    print("| object | pattern | " + " | ".join(backends) + " |")
    print("|---|---|" + "---|" * len(backends))
    for s in find_sessions([sessions]):
        mask = load_view(s, 0).proj.mask
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        for pattern in ("checkerboard", "stripes_x", "stripes_y"):
            if not (renders / f"{s.name}_clean_ref__{pattern}.exr").exists():  # stripes_y: mitsuba_render.py's
                continue
            truth = read_exr(renders / f"{s.name}_clean_ref__{pattern}.exr")
            cells = []
            for b in backends:
                img = read_exr(relit / f"{s.name}_v0_{pattern}_{b}.exr")
                cells.append(f"{psnr(img, truth, mask):.2f} / {psnr(img, truth, inner):.2f}")
            print(f"| {s.name} | {pattern} | " + " | ".join(cells) + " |")


def geometry(renders: Path, name: str, files: list[Path]) -> None:
    exact = np.load(renders / f"{name}_geometry.npz")
    theta = exact["theta"]
    on_object = exact["mask"] if "mask" in exact.files else True  # mitsuba_render.py's: the object, not the wall
    for f in files:
        z = np.load(f)
        for label, xp, yp in (("decoded", z["xp_decoded"], z["yp_decoded"]), ("for geometry", z["xp"], z["yp"])):
            ex, ey = xp - exact["xp"], yp - exact["yp"]
            ok = z["mask"] & on_object & np.isfinite(ex) & np.isfinite(theta)
            parts = [f"|error| {np.median(np.hypot(ex, ey)[ok]):.3f} px"]
            for lo, hi in ((0, 20), (20, 40), (40, 60), (60, 90)):
                sel = ok & (theta >= lo) & (theta < hi)
                if sel.sum() > 20:
                    parts.append(f"{lo}-{hi} deg: x {np.median(ex[sel]):+.3f} y {np.median(ey[sel]):+.3f} ({sel.sum()} px)")
            print(f"{f} {label}: " + "; ".join(parts))


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) >= 5 and a[0] == "relight":
        relight(Path(a[1]), Path(a[2]), Path(a[3]), a[4].split(","))
    elif len(a) >= 4 and a[0] == "geometry":
        geometry(Path(a[1]), a[2], [Path(p) for p in a[3:]])
    else:
        sys.exit(__doc__)
