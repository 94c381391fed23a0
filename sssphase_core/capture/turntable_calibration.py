"""The turntable's axis, from a checkerboard standing on it (``sss calibrate turntable``).

Each view that sees the whole board gives its corners in 3D: the camera corners and their projector points (the
local homographies of :mod:`~sssphase_core.capture.stereo_calibration`) triangulated with the rig's stereo
calibration. The board's motion from the first such view to each other one is a rigid turn (Kabsch), all about one
line: its direction is the turns' common axis, oriented so that the session's recorded turntable angles turn about it
right-handed, and a point on it solves ``(I - R_v) p = t_v`` for every view at once. What it is checked by: the
board's own turn in each view against the angle the turntable recorded, how far the axis carries the first view's
corners onto each other view's (RMS), and, given the squares' size, the triangulated squares against it (the stereo
calibration's scale). ``sss geometry`` then turns every view's points into the frame of the turntable at 0 degrees
and merges them into one cloud.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from sssphase_core.capture.stereo_calibration import SQUARE_RANGE, find_boards, require_boards
from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.triangulation import (
    StereoCalibration,
    axes_apart,
    mm_per_unit,
    triangulate_points,
    turned,
)

#: Views with the whole board that an axis needs (two turns, so that one bad view shows).
MIN_TURNTABLE_VIEWS = 3
#: The largest difference (degrees) between the board's turn and the recorded angle before it is warned of (the
#: simulated board: 0.05 with the rig's exact stereo calibration, 1.1 with one calibrated from its checkerboard; a
#: turntable stepping 15 degrees where the session says 30 is off by 15).
MAX_TURN_ERROR = 2.0
#: The largest relative difference between the triangulated squares and ``--square`` before it is warned of.
MAX_SCALE_ERROR = 0.02
#: The least span of turntable angles (degrees) the board's views must cover.
MIN_TURN_SPAN = 10.0


@dataclass
class TurntableResult:
    """A turntable axis fitted to the board's views: the calibration with it, the views used (the first the
    reference) and left out with why, each view's board turn minus its recorded angle (degrees), the RMS distance
    (the calibration's unit) between the reference corners turned by the recorded angles and each view's own, and the
    triangulated squares' median side where ``square`` was given."""

    calibration: StereoCalibration
    views: list[int]
    skipped: dict[int, str] = field(default_factory=dict)
    turn_error: dict[int, float] = field(default_factory=dict)
    rms: float = float("nan")
    square: float | None = None


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R and translation t that best carry points ``a`` (N, 3) onto ``b``: b ~ R a + t."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation, cb - rotation @ ca


def _vee(r: np.ndarray) -> np.ndarray:
    """2 sin(angle) * axis of the rotation ``r``."""
    return np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])


def _wrapped(degrees: float) -> float:
    return (degrees + 180.0) % 360.0 - 180.0


def calibrate_turntable(session: Any, board: tuple[int, int], stereo: StereoCalibration, *,
                        square: float | None = None, views: Sequence[int] | None = None,
                        progress: Any = None) -> TurntableResult:
    """The turntable axis of ``session``'s views of a ``board`` (inner corners) standing on it, triangulated with
    ``stereo``; refused in one line where fewer than :data:`MIN_TURNTABLE_VIEWS` views show the whole board, where
    the session recorded no turntable angles, or where the views do not turn about one axis."""
    if square is not None and not (np.isfinite(square) and SQUARE_RANGE[0] <= square <= SQUARE_RANGE[1]):
        raise InputError(f"--square must be the board's square side, a positive length in the calibration's unit, from "
                         f"{SQUARE_RANGE[0]:g} to {SQUARE_RANGE[1]:g}, got {square!r}")
    found, skipped, _, _ = find_boards(session, board, views, progress)
    require_boards(session, found, skipped, MIN_TURNTABLE_VIEWS)
    records = session.manifest.get("views", {})
    angles = {}
    for b in found:
        record = records.get(str(b.view)) if isinstance(records, dict) else None
        angle = record.get("angle") if isinstance(record, dict) else None
        if isinstance(angle, bool) or not isinstance(angle, int | float) or not np.isfinite(angle):
            raise DataError(f"{session.path}: view {b.view} recorded no turntable angle (captured without a turntable?)")
        angles[b.view] = float(angle)
    points = {b.view: triangulate_points(stereo, b.camera, b.projector) for b in found}
    bad = [v for v, p in points.items() if not np.isfinite(p).all() or (p[:, 2] <= 0).any()]
    if bad:
        raise DataError(f"{session.path}: the board's corners in view{'s' if len(bad) > 1 else ''} "
                        f"{', '.join(map(str, bad))} do not triangulate in front of the camera: is the calibration this rig's?")
    axis, point, turns = fit_axis(points, angles, where=str(session.path))
    ref, others = found[0].view, [b.view for b in found[1:]]
    recorded = {v: _wrapped(angles[v] - angles[ref]) for v in others}
    moved = {v: turned(points[ref], axis, point, recorded[v]) for v in others}
    rms = float(np.sqrt(np.mean([np.sum((moved[v] - points[v]) ** 2, axis=1).mean() for v in others])))
    side = None
    if square is not None:
        grid = points[ref].reshape(board[1], board[0], 3)
        side = float(np.median(np.concatenate([np.linalg.norm(np.diff(grid, axis=a), axis=-1).ravel() for a in (0, 1)])))
    calibration = replace(stereo, turntable_axis=axis, turntable_point=point)
    return TurntableResult(calibration, [ref, *others], skipped, {v: turns[v] - recorded[v] for v in others}, rms, side)


def fit_axis(points: dict[int, np.ndarray], angles: dict[int, float], where: str = "the views"
             ) -> tuple[np.ndarray, np.ndarray, dict[int, float]]:
    """The axis a rigid object turned about between views: ``points`` (N, 3) of the same N features per view (the
    first view the reference) and each view's recorded turntable ``angles`` (degrees) -> (unit direction (3,), the
    point on the axis nearest the reference points' centre (3,), each other view's own turn from the reference about
    it, degrees). The direction is oriented so that the recorded angles turn about it right-handed. Refused where the
    views span less than :data:`MIN_TURN_SPAN` degrees (the axis of a small turn is lost in the points' noise)."""
    views = list(points)
    ref, others = views[0], views[1:]
    recorded = {v: _wrapped(angles[v] - angles[ref]) for v in others}
    span = max((abs(d) for d in recorded.values()), default=0.0)
    if span < MIN_TURN_SPAN:
        raise DataError(f"{where}: the views with the board span {span:.1f} degrees of the turntable: the axis of so small "
                        f"a turn is lost in the corners' noise; capture the board over at least {MIN_TURN_SPAN:g} degrees")
    motions = {v: _kabsch(points[ref], points[v]) for v in others}
    direction = sum((np.sign(recorded[v]) or 1.0) * _vee(motions[v][0]) for v in others)
    if not np.linalg.norm(direction) > 1e-3:
        raise DataError(f"{where}: the board does not turn between views {', '.join(map(str, views))} (or turns both "
                        "ways about as much): capture it at several turntable angles")
    axis = direction / np.linalg.norm(direction)
    turns = {v: float(np.degrees(np.arctan2(_vee(r) @ axis / 2, (np.trace(r) - 1) / 2))) for v, (r, _) in motions.items()}
    # a point on the axis: (I - R_v) p = t_v for every view at once, then the one nearest the reference's centre
    lhs = np.concatenate([np.eye(3) - motions[v][0] for v in others])
    rhs = np.concatenate([motions[v][1] for v in others])
    point = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    centre = points[ref].mean(0)
    return axis, point + axis * ((centre - point) @ axis), turns


def turntable_report(result: TurntableResult, session: Any, square: float | None = None) -> list[tuple[str, str]]:
    """What ``sss calibrate turntable`` says of ``result``: (line, the part of it that warns, or "")."""
    lines: list[tuple[str, str]] = []
    by_reason: dict[str, list[int]] = {}
    for v, why in result.skipped.items():
        by_reason.setdefault(why, []).append(v)
    for why, left in by_reason.items():  # (most of a turn shows the board edge-on or from behind: one line each)
        lines.append((f"left out: view{'s' if len(left) > 1 else ''} {', '.join(map(str, left))}: {why}", ""))
    c, unit = result.calibration, result.calibration.unit or "calibration units"
    axis, point = c.turntable_axis, c.turntable_point
    assert axis is not None and point is not None
    worst = max(result.turn_error.values(), key=abs)
    lines.append((f"turntable axis from {len(result.views)} views ({', '.join(map(str, result.views))}): direction "
                  f"({', '.join(f'{x:.4f}' for x in axis)}) through ({', '.join(f'{x:.1f}' for x in point)}) {unit}; the "
                  f"board's turns differ from the recorded angles by at most {abs(worst):.2f} degrees; the first view's "
                  f"corners turned by the recorded angles land {result.rms:.2f} {unit} (RMS) from each view's own", ""))
    if abs(worst) > MAX_TURN_ERROR:
        lines.append((f"warning: a view's board turned {worst:+.2f} degrees from its recorded angle: does the turntable "
                      "step by what the session records, and did the board stay put?", "warning"))
    if result.square is not None and square is not None:
        off = result.square / square - 1
        lines.append((f"the board's squares measure {result.square:.3f} {unit} (given {square:g}, {100 * off:+.1f}%)", ""))
        if abs(off) > MAX_SCALE_ERROR:
            lines.append((f"warning: the triangulated squares are {100 * off:+.1f}% off --square: is the calibration "
                          "this rig's, and --square this board's?", "warning"))
    if (line := against_simulated_turntable(session, c)) is not None:
        lines.append((line, ""))
    return lines


def against_simulated_turntable(session: Any, calibration: StereoCalibration) -> str | None:
    """On a simulated session, the fitted axis against the rig's own (evaluation only); None otherwise."""
    from sssphase_core.sim import session_rig_calibration

    exact = session_rig_calibration(session.manifest.get("rig", {}))
    factor = mm_per_unit(calibration)  # (the simulated rig's lengths are in mm)
    if exact is None or exact.turntable_axis is None or calibration.turntable_axis is None or factor is None:
        return None
    tilt, miss = axes_apart(calibration.turntable_axis, factor * np.asarray(calibration.turntable_point),
                            exact.turntable_axis, exact.turntable_point)
    return (f"against the simulated rig's turntable: the axis tilted {tilt:.2f} degrees, passing {miss:.2f} mm from the "
            "true one")
