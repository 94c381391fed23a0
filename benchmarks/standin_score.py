"""Score relit images and projector correspondences of stand-in renders against their noise-free truth.

    python benchmarks/standin_score.py relight RENDERS SESSIONS RELIT BACKEND[,BACKEND...] [--truth converged]
    python benchmarks/standin_score.py geometry RENDERS OBJECT GEOMETRY_NPZ [GEOMETRY_NPZ ...]
    python benchmarks/standin_score.py edges RENDERS SESSIONS RELIT BACKEND[,BACKEND...]
    python benchmarks/standin_score.py regions RENDERS SESSIONS RELIT BACKEND[,BACKEND...]

``relight``: PSNR of ``RELIT/OBJECT_v0_PATTERN_BACKEND.exr`` (``sss relight --format exr``) against
``RENDERS/OBJECT_clean_ref__PATTERN.exr`` on the view's decoded mask, and >= 2 px inside it, for every
session under SESSIONS; with ``--truth converged`` against ``OBJECT_converged_ref__PATTERN.exr`` (`mitsuba_render.py
--converged`: random numbers of their own, so the captures' fixed Monte-Carlo pattern is not in the truth), on the
mask and on its calm pixels: chosen from the converged halves and the inputs only (the halves agree within 0.01 in
every colour, the white capture has no firefly: `transport_footprints.py`'s selection), so that no source's error
picks its own pixels; there each figure is followed by its margin over the analytic model (where scored) with the
converged reference's own noise taken out (a quarter of its halves' mean squared difference).
Every truth is read in the renderer's units and multiplied by the rig's ``frame_scale`` (where `sss import` rescaled
the frames) before it is compared, since relit images are in the session's units.
``geometry``: the decoded and the geometry-corrected projector x, y of
``sss geometry``'s ``correspondence_for_geometry.npz`` against ``RENDERS/OBJECT_geometry.npz``
(``standin_volumetric.py``, ``mitsuba_render.py``), median signed error by incidence angle.
``edges``: where the relit error lies across the patterns' edges: on the calm pixels within 2 projector pixels of an
edge (by their decoded projector coordinate, the bright side positive), the mean over the white of the converged
reference and of each backend's image, and the RMS of each one's error over the white, in quarter-pixel bins.
``regions``: where on the view the relit error lies, against the converged reference: PSNR on the object (the render's
own object mask in ``RENDERS/OBJECT_geometry.npz``, for evaluation only) and on the calm pixels by signed distance to
its silhouette (:data:`REGIONS`: the background beyond 3 px, the 3 px either side of the silhouette, 3-12 px inside,
deeper), each followed by its margin over the analytic model where scored.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np


def psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a[where] - b[where]) ** 2)))


def session_scale(session) -> float:  # noqa: ANN001
    """The factor `sss import` scaled the renders' frames by (the rig's ``frame_scale``): relit images are in the
    session's units, so every truth read from the render folder is multiplied by it before it is compared."""
    return float(session.manifest["rig"].get("frame_scale", 1.0))


def converged_halves(renders: Path, name: str, pattern: str, rv, scale: float = 1.0) -> tuple[list[np.ndarray], np.ndarray]:  # noqa: ANN001
    """The converged reference's two halves under ``pattern`` (in the session's units: times ``scale``) and the view's
    calm pixels (H, W): decoded, a steady white, and the halves within CALM of each other in every colour."""
    from transport_footprints import CALM, steady_white

    from sssphase_core.store.exr import read_exr

    halves = [read_exr(renders / f"{name}_converged_half{i}_ref__{pattern}.exr") * scale for i in (0, 1)]
    return halves, rv.proj.mask & steady_white(rv.white) & (np.abs(halves[0] - halves[1]).max(axis=-1) <= CALM)


def relight(renders: Path, sessions: Path, relit: Path, backends: list[str], truth: str = "clean") -> None:
    from transport_footprints import noise_corrected, reference_noise

    from sssphase_core.relight import load_view
    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.session import find_sessions

    print("| object | pattern | " + " | ".join(backends) + " |")
    print("|---|---|" + "---|" * len(backends))
    for s in find_sessions([sessions]):
        rv = load_view(s, 0)
        scale = session_scale(s)
        mask = rv.proj.mask
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        for pattern in ("checkerboard", "stripes_x", "stripes_y"):
            reference = renders / f"{s.name}_{truth}_ref__{pattern}.exr"
            if not reference.exists():  # stripes_y: mitsuba_render.py's; converged: where rendered
                continue
            truth_img = read_exr(reference) * scale
            imgs = {b: read_exr(relit / f"{s.name}_v0_{pattern}_{b}.exr") for b in backends}
            if truth != "converged":
                cells = [f"{psnr(imgs[b], truth_img, mask):.2f} / {psnr(imgs[b], truth_img, inner):.2f}" for b in backends]
                print(f"| {s.name} | {pattern} | " + " | ".join(cells) + " |")
                continue
            halves, calm = converged_halves(renders, s.name, pattern, rv, scale)
            noise = reference_noise(*halves, calm)
            mse = {b: float(np.mean((imgs[b][calm] - truth_img[calm]) ** 2)) for b in backends}
            cells = []
            for b in backends:
                cell = f"{psnr(imgs[b], truth_img, mask):.2f} / {psnr(imgs[b], truth_img, calm):.2f}"
                if "analytic" in mse:
                    cell += " ({:+.2f})".format(noise_corrected(mse[b], mse["analytic"], noise)[1])
                cells.append(cell)
            print(f"| {s.name} | {pattern} ({calm.sum() / mask.sum():.0%} calm, reference noise "
                  f"{10 * np.log10(1 / noise):.1f} dB) | " + " | ".join(cells) + " |")


EDGE_BINS = np.arange(-2.0, 2.01, 0.25)  # signed distance to a pattern edge, projector px (bright side positive)


def edge_distance(pattern: np.ndarray, coord: np.ndarray, across: np.ndarray, axis: int, where: np.ndarray) -> np.ndarray:
    """(H, W) signed distance (projector px, NaN beyond 3) of each pixel's decoded projector coordinate ``coord`` along
    ``axis`` (1: x, 0: y) to the nearest edge of the (Hp, Wp) ``pattern`` along that axis, positive on its bright side;
    ``across``: the other coordinate (which row or column of the pattern the pixel sees). Projector pixel i spans
    [i - 0.5, i + 0.5]."""
    steps = np.abs(np.diff(pattern, axis=axis)).max(axis=1 - axis) > 0.5
    dist = np.full(coord.shape, np.nan)
    c = np.where(where, coord, -99.0)
    other = np.clip(np.round(np.nan_to_num(across)).astype(int), 0, pattern.shape[1 - axis] - 1)
    for e in np.flatnonzero(steps) + 1:  # between projector pixels e - 1 and e
        d = c - (e - 0.5)
        near = where & (np.abs(d) < 3) & ~(np.abs(dist) <= np.abs(d))
        o = other[near]
        after, before = (pattern[o, e], pattern[o, e - 1]) if axis == 1 else (pattern[e, o], pattern[e - 1, o])
        dist[near] = np.where(after > before, d[near], -d[near])
    return dist


def edges(renders: Path, sessions: Path, relit: Path, backends: list[str]) -> None:
    from sssphase_core.relight import load_view
    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.session import find_sessions

    for s in find_sessions([sessions]):
        rv, scale = load_view(s, 0), session_scale(s)
        white = rv.white.mean(axis=-1)
        for name in ("checkerboard", "stripes_x", "stripes_y"):
            reference = renders / f"{s.name}_converged_ref__{name}.exr"
            if name not in rv.references or not reference.exists():
                continue
            pattern = np.asarray(rv.references[name], np.float32)
            pattern = pattern.mean(axis=-1) if pattern.ndim == 3 else pattern
            calm = converged_halves(renders, s.name, name, rv, scale)[1]
            images = {"truth": read_exr(reference).mean(axis=-1) * scale}
            images |= {b: read_exr(relit / f"{s.name}_v0_{name}_{b}.exr").mean(axis=-1) for b in backends}
            for axis, coord, across in ((1, rv.proj.xp, rv.proj.yp), (0, rv.proj.yp, rv.proj.xp)):
                dist = edge_distance(pattern, coord, across, axis, calm & np.isfinite(coord))
                sel = np.isfinite(dist)
                if sel.sum() < 100:
                    continue
                idx = np.digitize(dist[sel], EDGE_BINS)
                print(f"{s.name} {name}, edges along {'xy'[1 - axis]} ({sel.sum()} calm px), by distance (projector px, "
                      "bright side +): mean over the white, then RMS error over the white")
                print(f"  {'':10s} " + " ".join(f"{b:+5.2f}" for b in EDGE_BINS[:-1]))
                for label, img in images.items():
                    ratio = img[sel] / white[sel]
                    print(f"  {label[:10]:10s} " + " ".join(f"{ratio[idx == j].mean():5.2f}" for j in range(1, len(EDGE_BINS))))
                for label, img in list(images.items())[1:]:
                    err = (img[sel] - images["truth"][sel]) / white[sel]
                    print(f"  {label[:10]:10s} " + " ".join(f"{np.sqrt(np.mean(err[idx == j] ** 2)):5.3f}"
                                                         for j in range(1, len(EDGE_BINS))))


#: Signed distance to the object's silhouette (px, inside positive): (label, low, high], for ``regions``.
REGIONS = (("background", -np.inf, -3.0), ("silhouette ±3 px", -3.0, 3.0), ("3-12 px inside", 3.0, 12.0),
           ("> 12 px inside", 12.0, np.inf))


def silhouette_distance(inside: np.ndarray) -> np.ndarray:
    """(H, W) signed distance (px) of each pixel to the boundary of the bool mask ``inside``: positive inside."""
    mask = inside.astype(np.uint8)
    return cv2.distanceTransform(mask, cv2.DIST_L2, 5) - cv2.distanceTransform(1 - mask, cv2.DIST_L2, 5)


def regions(renders: Path, sessions: Path, relit: Path, backends: list[str]) -> None:
    from sssphase_core.relight import load_view
    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.session import find_sessions

    print("| object | pattern | region | pixels | " + " | ".join(backends) + " |")
    print("|---|---|---|---|" + "---|" * len(backends))
    for s in find_sessions([sessions]):
        rv, scale = load_view(s, 0), session_scale(s)
        inside = np.load(renders / f"{s.name}_geometry.npz")["object"].astype(bool)
        signed = silhouette_distance(inside)
        for name in ("checkerboard", "stripes_x", "stripes_y"):
            reference = renders / f"{s.name}_converged_ref__{name}.exr"
            if not reference.exists():
                continue
            truth = read_exr(reference) * scale
            calm = converged_halves(renders, s.name, name, rv, scale)[1]
            imgs = {b: read_exr(relit / f"{s.name}_v0_{name}_{b}.exr") for b in backends}
            wheres = [("object", rv.proj.mask & inside)]
            wheres += [(f"calm, {label}", calm & (signed > lo) & (signed <= hi)) for label, lo, hi in REGIONS]
            for label, where in wheres:
                if not where.any():
                    continue
                scores = {b: psnr(imgs[b], truth, where) for b in backends}
                cells = [f"{v:.2f}" + (f" ({v - scores['analytic']:+.2f})" if "analytic" in scores else "")
                         for v in scores.values()]
                print(f"| {s.name} | {name} | {label} | {int(where.sum())} | " + " | ".join(cells) + " |")


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
    truth = "clean"
    if len(a) >= 2 and a[-2] == "--truth":
        if a[-1] not in ("clean", "converged"):
            sys.exit(f"--truth must be clean or converged, got {a[-1]!r}")
        truth, a = a[-1], a[:-2]
    from sssphase_core.errors import SssError

    try:
        if len(a) >= 5 and a[0] == "relight":
            relight(Path(a[1]), Path(a[2]), Path(a[3]), a[4].split(","), truth)
        elif len(a) >= 5 and a[0] == "edges":
            edges(Path(a[1]), Path(a[2]), Path(a[3]), a[4].split(","))
        elif len(a) >= 5 and a[0] == "regions":
            regions(Path(a[1]), Path(a[2]), Path(a[3]), a[4].split(","))
        elif len(a) >= 4 and a[0] == "geometry":
            geometry(Path(a[1]), a[2], [Path(p) for p in a[3:]])
        else:
            sys.exit(__doc__)
    except (SssError, FileNotFoundError) as e:  # a relit image not written yet, a render not there: one line
        sys.exit(f"error: {e}")
