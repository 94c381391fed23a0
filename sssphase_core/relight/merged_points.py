"""A turntable session's views as one point cloud (``sss geometry``): each view's triangulated points turned back by
its recorded turntable angle about the calibrated axis (:mod:`~sssphase_core.capture.turntable_calibration`) into
the frame of the turntable at 0 degrees, and written together as ``OUT/<object>/points_merged.ply``."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.axis_refinement import AxisRefinement, median_spacing, refine_axis
from sssphase_core.processing.triangulation import (
    StereoCalibration,
    distance_to_axis,
    mm_per_unit,
    triangulate,
    turned,
)

if TYPE_CHECKING:
    from sssphase_core.store.session import Session


#: Points of a view count as overlapping the view before it within this many of its median point spacings.
OVERLAP_SPACINGS = 4.0
#: Neighbouring views that agree only to this many point spacings or worse are merged about an axis that is off
#: (the simulated soap: 0.9 spacings with the rig's own axis, 2.9 with one turned 3 degrees and moved 8 mm).
POOR_AGREEMENT = 2.0


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
    #: the views' median point spacing (what the agreement is read against)
    spacing: float = float("nan")
    #: the axis refined from the views' overlaps (``refine=True``) and the agreement with the calibration's axis
    refinement: AxisRefinement | None = None
    agreement_before: float = float("nan")
    #: the calibration with the refined axis, where it was written
    refined_calibration: Path | None = None
    #: the views' range-image meshes turned the same way (``mesh=True``), and their triangles
    mesh: Path | None = None
    n_faces: int = 0


def recorded_angles(s: Session, views: list[int]) -> dict[int, float] | None:
    """The turntable angle (degrees) the session recorded for each view, or None where any view has none."""
    from sssphase_core.store.session import angle_problem

    records = s.manifest.get("views", {})
    angles = {}
    for v in views:
        angle = records.get(str(v), {}).get("angle") if isinstance(records.get(str(v)), dict) else None
        if angle is None:
            return None
        if (problem := angle_problem(angle)) is not None:  # (1e300 turned view 1's points to NaN: merged without it)
            raise DataError(f"{s.path}: view {v}'s turntable angle {problem} (`sss validate` lists it)")
        angles[v] = float(angle)
    return angles


def to_turntable_frame(points: np.ndarray, stereo: StereoCalibration, angle: float) -> np.ndarray:
    """Points (..., 3) of a view recorded at turntable ``angle`` (degrees), camera frame -> where they are with the
    turntable at 0 degrees (turned back by ``angle`` about ``stereo``'s axis)."""
    return turned(points, stereo.turntable_axis, stereo.turntable_point, -angle)  # type: ignore[arg-type]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and a.samefile(b)
    except OSError:
        return False


def merge_views(s: Session, clouds: dict[int, tuple[np.ndarray, np.ndarray]], stereo: StereoCalibration, out: Path,
                exact_rig: StereoCalibration | None = None, crop_radius: float | None = None, refine: bool = False,
                errors: dict[str, float] | None = None, mesh: bool = False,
                calibration: Path | str | None = None) -> MergedCloud | None:
    """``clouds``: per view its points (H, W, 3, camera frame) and white capture (H, W, 3); turned into the frame of
    the turntable at 0 degrees with ``stereo``'s axis and written as ``out/<object>/points_merged.ply``. None where
    the calibration has no turntable or a view recorded no angle. ``exact_rig`` (simulated sessions): each view's
    exact surface turned the same way by the rig's own axis, to score the merge against (evaluation only).
    ``crop_radius``: only the points within that distance of the axis (a wall or the rig behind the object left out).
    ``refine``: the axis refined from the views' overlaps first (:func:`~sssphase_core.processing.axis_refinement.
    refine_axis`); where the views pin it down, the merge is about it and the calibration with it is written as
    ``out/<object>/calibration_refined.yml`` (keeping ``errors``, the stereo calibration's recorded RMS errors); where
    they do not, the calibration's axis stands. ``mesh``: each view's range-image mesh turned the same way, together
    as ``out/<object>/mesh_merged.ply``. ``calibration``: the file ``stereo`` was read from, never removed (an
    earlier run's refined calibration given back as this run's)."""
    from sssphase_core.store.pointcloud import write_point_cloud

    angles = recorded_angles(s, list(clouds))
    if stereo.turntable_axis is None or stereo.turntable_point is None or angles is None:
        return None
    points = {v: np.asarray(p, np.float64) for v, (p, _) in clouds.items()}
    if crop_radius is not None:  # (the distance to the axis is the same in every view's frame)
        nearest = np.inf
        for v, p in points.items():
            distance = distance_to_axis(p, stereo.turntable_axis, stereo.turntable_point)
            nearest = min(nearest, float(np.nanmin(distance, initial=np.inf)))
            points[v] = np.where((distance > crop_radius)[..., None], np.nan, p)
        if not any(np.isfinite(p).all(-1).any() for p in points.values()):  # (an empty cloud, "median nan", exit 0)
            raise InputError(f"--crop-radius {crop_radius:g}: no point lies within it of the turntable's axis (the "
                             f"nearest is {nearest:.4g} {stereo.unit or 'units'} from it): give a larger radius")
    merged = {v: to_turntable_frame(p, stereo, angles[v]) for v, p in points.items()}
    agreement, spacing = _agreement(merged, angles)
    refinement, before, used = None, float("nan"), False
    if refine:
        refinement = refine_axis(points, angles, stereo.turntable_axis, stereo.turntable_point)
        if refinement.refused is None:
            # An axis the views do not pin down is not taken, even where they agree better about it: two views half
            # a turn apart slide into each other (the simulated soap: agreeing 1.4 mm in place of 2.1, 12 mm off its
            # surface in place of 0.1).
            used = refinement.pinned
            if used:
                stereo = replace(stereo, turntable_axis=refinement.axis, turntable_point=refinement.point)
                before, merged = agreement, {v: to_turntable_frame(p, stereo, angles[v]) for v, p in points.items()}
                agreement, spacing = _agreement(merged, angles)
    xyz = np.concatenate([p.reshape(-1, 3) for p in merged.values()])
    colour = np.concatenate([white.reshape(-1, 3) for _, white in clouds.values()])
    path = out / s.name / "points_merged.ply"
    done = MergedCloud(path, list(clouds), write_point_cloud(path, xyz, colour), agreement=agreement,
                       crop_radius=crop_radius, spacing=spacing, refinement=refinement, agreement_before=before)
    refined = out / s.name / "calibration_refined.yml"
    if used:
        from sssphase_core.capture.stereo_calibration import write_calibration

        done.refined_calibration = write_calibration(refined, stereo, errors)
    elif refine and not (calibration is not None and _same_file(refined, Path(calibration))):
        refined.unlink(missing_ok=True)  # an earlier run's axis is not this run's answer (unless it is this run's input)
    if mesh:
        from sssphase_core.store.pointcloud import write_range_meshes

        done.mesh = out / s.name / "mesh_merged.ply"
        done.n_faces = write_range_meshes(done.mesh, [(merged[v], white) for v, (_, white) in clouds.items()])[1]
    if exact_rig is not None and exact_rig.turntable_axis is not None:
        factor = mm_per_unit(stereo)  # (the rig's truth is in mm; a calibration in cm is compared after this factor)
        if factor is not None:
            done.exact = {v: _exact_distance(s, v, factor * merged[v], exact_rig, angles[v]) for v in clouds}
    return done


def _agreement(merged: dict[int, np.ndarray], angles: dict[int, float]) -> tuple[float, float]:
    """The median distance from each view's points to the nearest point of the view before it (by angle; the first
    after the last) where they overlap, over all such pairs (NaN where no two views overlap), and the views' median
    point spacing."""
    from scipy.spatial import cKDTree

    order = sorted(merged, key=lambda v: angles[v] % 360)
    clouds = {v: merged[v].reshape(-1, 3)[np.isfinite(merged[v].reshape(-1, 3)).all(-1)] for v in order}
    found, spacings = [], []
    for before, after in zip(order, order[1:] + order[:1], strict=True):
        a, b = clouds[before], clouds[after]
        if before == after or len(a) < 2 or len(b) < 1:
            continue
        tree = cKDTree(a)
        spacing = median_spacing(a, tree)
        spacings.append(spacing)
        distance = tree.query(b, distance_upper_bound=OVERLAP_SPACINGS * spacing)[0]
        found.append(distance[np.isfinite(distance)])
    near = np.concatenate(found) if found else np.zeros(0)
    return (float(np.median(near)) if near.size else float("nan"),
            float(np.median(spacings)) if spacings else float("nan"))


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
        line += f"; neighbouring views agree to {done.agreement:.3f} (median distance where they overlap"
        line += f", {done.agreement_before:.3f} about the calibration's axis)" if np.isfinite(done.agreement_before) else ")"
    if done.mesh is not None:
        line += f"; and {done.mesh}: their meshes, {done.n_faces} triangles"
    if done.exact:
        worst = max(done.exact, key=lambda v: done.exact[v])  # type: ignore[index]
        line += (f"; against the exact surface: median {np.nanmedian(list(done.exact.values())):.3f} mm over the views, "
                 f"at most {done.exact[worst]:.3f} (view {worst})")
    return line


def refinement_lines(done: MergedCloud, unit: str) -> list[str]:
    """What the axis refinement did (or why not), and a hint to refine where the views agree poorly without it;
    ``unit``: the calibration's length unit ("" where it names none)."""
    r, unit = done.refinement, f" {unit}" if unit else ""
    if r is None:
        if not np.isfinite(done.agreement) and len(done.views) >= 3:  # (two views may face away from each other)
            return [f"warning: no two neighbouring views overlap (no point within {OVERLAP_SPACINGS:g} point spacings of "
                    "the other view's): the axis is far off (is the calibration's turntable_point in its unit?) or the "
                    "views are too far apart; --refine-axis fits the axis where they overlap"]
        poor = np.isfinite(done.agreement) and done.agreement > POOR_AGREEMENT * done.spacing
        return [f"note: neighbouring views agree only to {done.agreement / done.spacing:.1f} point spacings: the axis may "
                "be off; --refine-axis fits it to the views' overlaps"] if poor else []
    if r.refused is not None:
        return [f"warning: the calibration's axis was kept: {r.refused}"]
    before = f"{r.rms_before:.3f}" if np.isfinite(r.rms_before) else "(no pairs within 3 point spacings about the calibration's axis)"
    lines = [f"axis refined from the views' overlaps ({r.pairs} point pairs, {r.rounds} rounds): turned {r.tilt:.3f} "
             f"degrees and moved {r.shift:.3f}{unit} from the calibration's; point-to-plane RMS {before} -> "
             f"{r.rms_after:.3f}; axis ({', '.join(f'{c:.5f}' for c in r.axis)}) through "
             f"({', '.join(f'{c:.3f}' for c in r.point)})"]
    if done.refined_calibration is not None:
        lines.append(f"wrote {done.refined_calibration}: the calibration with the refined axis (restarted 1 degree off, "
                     f"the refinement came back to within {r.slide_tilt:.3f} degrees and {r.slide_shift:.3f}{unit})")
        return lines
    lines.append(f"warning: the calibration's axis was kept: the views do not pin the refined one down (restarted 1 "
                 f"degree off, the refinement ended {r.slide_tilt:.2f} degrees and {r.slide_shift:.3f}{unit} away): they "
                 "overlap too little, or the object is nearly symmetric about the axis; views closer together (30-45 "
                 "degrees apart) or an object with more shape pin it down")
    return lines


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
