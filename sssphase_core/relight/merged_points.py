"""A turntable session's views as one point cloud (``sss geometry``): each view's triangulated points turned back by
its recorded turntable angle about the calibrated axis (:mod:`~sssphase_core.capture.turntable_calibration`) into
the frame of the turntable at 0 degrees, and written together as ``OUT/<object>/points_merged.ply``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sssphase_core.processing.triangulation import StereoCalibration, triangulate, turned

if TYPE_CHECKING:
    from sssphase_core.store.session import Session


#: Points of a view count as overlapping the view before it within this many of its median point spacings.
OVERLAP_SPACINGS = 4.0


@dataclass
class MergedCloud:
    """The merged cloud written: its file, the views in it and how many points; on a simulated session, the median
    distance (mm) of each view's merged points to the exact surface of the turntable at 0 degrees."""

    path: Path
    views: list[int]
    n_points: int
    exact: dict[int, float] | None = None
    #: the median distance from each view's points to the nearest of the view before it (by angle) where the two
    #: overlap (within :data:`OVERLAP_SPACINGS` point spacings): how well the views agree, without a truth
    agreement: float = float("nan")
    #: the merged points' largest distance from the axis, where cropped
    crop_radius: float | None = None


def recorded_angles(s: Session, views: list[int]) -> dict[int, float] | None:
    """The turntable angle (degrees) the session recorded for each view, or None where any view has none."""
    records = s.manifest.get("views", {})
    angles = {}
    for v in views:
        angle = records.get(str(v), {}).get("angle") if isinstance(records.get(str(v)), dict) else None
        if isinstance(angle, bool) or not isinstance(angle, int | float) or not np.isfinite(angle):
            return None
        angles[v] = float(angle)
    return angles


def to_turntable_frame(points: np.ndarray, stereo: StereoCalibration, angle: float) -> np.ndarray:
    """Points (..., 3) of a view recorded at turntable ``angle`` (degrees), camera frame -> where they are with the
    turntable at 0 degrees (turned back by ``angle`` about ``stereo``'s axis)."""
    return turned(points, stereo.turntable_axis, stereo.turntable_point, -angle)  # type: ignore[arg-type]


def merge_views(s: Session, clouds: dict[int, tuple[np.ndarray, np.ndarray]], stereo: StereoCalibration, out: Path,
                exact_rig: StereoCalibration | None = None, crop_radius: float | None = None) -> MergedCloud | None:
    """``clouds``: per view its points (H, W, 3, camera frame) and white capture (H, W, 3); turned into the frame of
    the turntable at 0 degrees with ``stereo``'s axis and written as ``out/<object>/points_merged.ply``. None where
    the calibration has no turntable or a view recorded no angle. ``exact_rig`` (simulated sessions): each view's
    exact surface turned the same way by the rig's own axis, to score the merge against (evaluation only).
    ``crop_radius``: only the points within that distance of the axis (a wall or the rig behind the object left out)."""
    from sssphase_core.store.pointcloud import write_point_cloud

    angles = recorded_angles(s, list(clouds))
    if stereo.turntable_axis is None or stereo.turntable_point is None or angles is None:
        return None
    axis, point = stereo.turntable_axis, stereo.turntable_point
    merged = {v: to_turntable_frame(points, stereo, angles[v]) for v, (points, _) in clouds.items()}
    if crop_radius is not None:  # (the distance to the axis is the same before and after the turn)
        for v, p in merged.items():
            offset = p - point
            with np.errstate(invalid="ignore"):
                far = np.linalg.norm(offset - (offset @ axis)[..., None] * axis, axis=-1) > crop_radius
            merged[v] = np.where(far[..., None], np.nan, p)
    xyz = np.concatenate([p.reshape(-1, 3) for p in merged.values()])
    colour = np.concatenate([white.reshape(-1, 3) for _, white in clouds.values()])
    path = out / s.name / "points_merged.ply"
    done = MergedCloud(path, list(clouds), write_point_cloud(path, xyz, colour), agreement=_agreement(merged, angles),
                       crop_radius=crop_radius)
    if exact_rig is not None and exact_rig.turntable_axis is not None:
        done.exact = {v: _exact_distance(s, v, merged[v], exact_rig, angles[v]) for v in clouds}
    return done


def _agreement(merged: dict[int, np.ndarray], angles: dict[int, float]) -> float:
    """The median distance from each view's points to the nearest point of the view before it (by angle; the first
    after the last) where they overlap, over all such pairs; NaN where no two views overlap."""
    from scipy.spatial import cKDTree

    order = sorted(merged, key=lambda v: angles[v] % 360)
    clouds = {v: merged[v].reshape(-1, 3)[np.isfinite(merged[v].reshape(-1, 3)).all(-1)] for v in order}
    found = []
    for before, after in zip(order, order[1:] + order[:1], strict=True):
        a, b = clouds[before], clouds[after]
        if before == after or len(a) < 2 or len(b) < 1:
            continue
        tree = cKDTree(a)
        spacing = float(np.median(tree.query(a, k=2)[0][:, 1]))
        distance = tree.query(b, distance_upper_bound=OVERLAP_SPACINGS * spacing)[0]
        found.append(distance[np.isfinite(distance)])
    near = np.concatenate(found) if found else np.zeros(0)
    return float(np.median(near)) if near.size else float("nan")


def _exact_distance(s: Session, view: int, merged: np.ndarray, exact_rig: StereoCalibration, angle: float) -> float:
    """The median distance of a view's merged points to its exact surface turned by the rig's own axis."""
    if "gt/proj_xy" not in s.arrays(view):
        return float("nan")
    gt = np.asarray(s.load(view, "gt/proj_xy"), np.float64)
    ok = np.isfinite(gt[..., 0]) & np.isfinite(merged).all(-1)
    exact = triangulate(exact_rig, gt[..., 0], gt[..., 1], ok).points
    truth = to_turntable_frame(exact, exact_rig, angle)
    distance = np.linalg.norm(merged - truth, axis=-1)[ok & np.isfinite(truth).all(-1)]
    return float(np.median(distance)) if distance.size else float("nan")


def merged_line(done: MergedCloud, unit: str) -> str:
    line = (f"wrote {done.path}: {done.n_points} points of views {', '.join(map(str, done.views))} turned into the frame "
            f"of the turntable at 0 degrees ({unit}{f', within {done.crop_radius:g} of its axis' if done.crop_radius else ''})")
    if np.isfinite(done.agreement):
        line += f"; neighbouring views agree to {done.agreement:.3f} (median distance where they overlap)"
    if done.exact:
        worst = max(done.exact, key=lambda v: done.exact[v])  # type: ignore[index]
        line += (f"; against the exact surface: median {np.nanmedian(list(done.exact.values())):.3f} mm over the views, "
                 f"at most {done.exact[worst]:.3f} (view {worst})")
    return line


def merge_note(stereo: StereoCalibration | None, views: list[int], angles: Any) -> str | None:
    """Why a run of several views wrote no merged cloud, or None where it needs no word."""
    if stereo is None or len(views) < 2:
        return None
    if stereo.turntable_axis is None:
        return ("note: each view's points stay in its own frame: the calibration has no turntable axis (`sss calibrate "
                "turntable` adds one from a checkerboard standing on the turntable), so the views were not merged")
    if angles is None:
        return "note: the views were not merged: the session recorded no turntable angle for some of them"
    return None
