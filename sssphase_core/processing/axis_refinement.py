"""A turntable's axis refined from the object's own points (``sss geometry --refine-axis``).

The axis a calibration gives (``sss calibrate turntable``, from a board) carries that calibration's errors into the
merge: an axis tilted by a degree or passing a few millimetres off sets the views apart by as much at the object.
The views themselves say where the axis is, where they overlap: each one's points turned back by its recorded angle
must lie on the surface its neighbours show. This is a point-to-plane ICP (Chen and Medioni) constrained to the
turntable: the views do not move freely, only the axis does, its direction (2 degrees of freedom) and where it passes
(2). Each round pairs a sample of each view's points, turned into the frame of the turntable at 0 degrees, with the
nearest points of the view before it (by angle) within a distance that shrinks from round to round, and fits the four
parameters to the pairs' point-to-plane distances with a robust loss (scipy's ``least_squares``, soft L1) and a weak
pull toward the given axis, which holds what the points cannot fix (the tilt of a sphere's axis).

What it cannot see: anything that moves every view alike (a depth offset of the stereo calibration, the scale), and
the axis where the views do not overlap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sssphase_core.processing.triangulation import axes_apart, turned

#: Points of each view that take part in a round (evenly drawn from its valid points).
SAMPLE = 4000
#: Points of each view that the others are paired with (evenly picked beyond: a 1080p view's 2 M would make each
#: round's search trees take seconds).
TREE_POINTS = 50_000
#: The most rounds (pairing, then fitting); most refinements settle in 5-15.
MAX_ROUNDS = 40
#: The pairing distance in the first round and the last, in median point spacings; it halves each round between.
FIRST_REACH, LAST_REACH = 32.0, 3.0
#: What holds the axis where the views cannot place it (an object nearly symmetric about it, a sphere, a cylinder):
#: a tilt of this many degrees, or a move of this many point spacings, costs as much as one pair a spacing apart, so
#: that the thousands of pairs decide wherever they can and the calibration's axis stands where they cannot.
PRIOR_TILT, PRIOR_SHIFT = 1.0, 10.0
#: The restarts that test whether the views pin the axis down begin this far off the result (degrees, spacings), and
#: must come back within these.
PROBE_TILT, PROBE_SHIFT = 1.0, 5.0
MAX_SLIDE_TILT, MAX_SLIDE = 0.2, 2.0
#: Point pairs a round needs to fit four parameters with some confidence.
MIN_PAIRS = 200
#: A refinement that tilts the axis further than this (degrees) or moves it further than this many times the cloud's
#: radius is not an error of the calibration but a fit gone astray (symmetric objects, little overlap).
MAX_TILT, MAX_SHIFT = 10.0, 0.5


@dataclass
class AxisRefinement:
    """A refined turntable axis: its unit ``axis`` and a ``point`` on it (the input's frame), how far it turned
    (``tilt``, degrees) and moved (``shift``, the distance between the two lines at the given point, the input's unit)
    from the given one, the rounds it took, the point pairs of the last round, and their RMS point-to-plane distance
    before and after (``rms_before`` with the given axis)."""

    axis: np.ndarray
    point: np.ndarray
    tilt: float
    shift: float
    rounds: int
    pairs: int
    rms_before: float
    rms_after: float
    #: how far (degrees, the input's unit) the refinement ended from this one when restarted a little off it: small
    #: where the views pin the axis down, large where the object is nearly symmetric about it
    slide_tilt: float = float("nan")
    slide_shift: float = float("nan")
    #: whether the restarts came back (within :data:`MAX_SLIDE_TILT` and :data:`MAX_SLIDE` point spacings)
    pinned: bool = False
    #: why the refinement was not kept (the given axis stands), or None
    refused: str | None = None


def surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised cloud (H, W, 3) from its central differences along rows and columns;
    NaN where a neighbour is missing (edges, holes)."""
    p = np.asarray(points, np.float64)
    p = np.where(np.isfinite(p), p, np.nan)  # (an infinite coordinate is no point either)
    normals = np.full(p.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        n = np.cross(p[1:-1, 2:] - p[1:-1, :-2], p[2:, 1:-1] - p[:-2, 1:-1])
        normals[1:-1, 1:-1] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(np.isfinite(normals).all(-1, keepdims=True), normals, np.nan)


def _basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``axis`` and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(axis * np.deg2rad(degrees))[0]


def refine_axis(clouds: dict[int, np.ndarray], angles: dict[int, float], axis: np.ndarray, point: np.ndarray, *,
                sample: int = SAMPLE, seed: int = 0) -> AxisRefinement:
    """The axis about which ``clouds`` (per view its organised points (H, W, 3) in the camera's frame, NaN where
    none), recorded at turntable ``angles`` (degrees), overlap best, starting from ``axis`` (unit) through ``point``.
    Views are paired with the view before them by angle (the first with the last); a refinement without
    :data:`MIN_PAIRS` pairs, or that turns or moves the axis implausibly far, keeps the given axis (``refused`` says
    why)."""
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    axis0 = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    point0 = np.asarray(point, np.float64)
    e1, e2 = _basis(axis0)
    rng = np.random.default_rng(seed)
    order = sorted(clouds, key=lambda v: angles[v] % 360)
    valid, normals, drawn = {}, {}, {}
    for v in order:
        p = np.asarray(clouds[v], np.float64)
        n = surface_normals(p)
        ok = np.isfinite(p).all(-1) & np.isfinite(n).all(-1)
        valid[v], normals[v] = p[ok], n[ok]
        if len(valid[v]) > TREE_POINTS:
            picked = np.round(np.linspace(0, len(valid[v]) - 1, TREE_POINTS)).astype(int)
            valid[v], normals[v] = valid[v][picked], normals[v][picked]
        drawn[v] = rng.choice(len(valid[v]), min(sample, len(valid[v])), replace=False) if len(valid[v]) else []
    pairs = [(b, a) for b, a in zip(order, order[1:] + order[:1], strict=True) if b != a]
    every = np.concatenate([valid[v] for v in order]) if order else np.zeros((0, 3))
    spacing = median_spacing(max(valid.values(), key=len)) if order else float("nan")
    if len(every) < MIN_PAIRS or not pairs or not (np.isfinite(spacing) and spacing > 0):
        return _kept(axis0, point0, "the views have too few points to refine the axis")
    radius = float(np.max(np.linalg.norm(every - every.mean(0), axis=-1)))

    def line(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = axis0 + x[0] * e1 + x[1] * e2
        return a / np.linalg.norm(a), point0 + x[2] * e1 + x[3] * e2

    def matched(x: np.ndarray, reach: float) -> list[tuple[float, float, np.ndarray, np.ndarray, np.ndarray]]:
        """Per pair of views: (angle after, angle before, its drawn points, their nearest points before, the normals
        there), camera frame, the pairs closer than ``reach``."""
        a, p = line(x)
        found = []
        for b, v in pairs:
            tree = cKDTree(turned(valid[b], a, p, -angles[b]))
            mine = valid[v][drawn[v]]
            distance, index = tree.query(turned(mine, a, p, -angles[v]), distance_upper_bound=reach)
            near = np.isfinite(distance)
            found.append((angles[v], angles[b], mine[near], valid[b][index[near]], normals[b][index[near]]))
        return found

    prior = spacing / np.array([np.deg2rad(PRIOR_TILT), np.deg2rad(PRIOR_TILT), PRIOR_SHIFT * spacing,
                                PRIOR_SHIFT * spacing])

    def residuals(x: np.ndarray, found: list, with_prior: bool = True) -> np.ndarray:
        a, p = line(x)
        parts = [prior * x] if with_prior else []
        for angle, angle_before, mine, theirs, n in found:
            here, there = turned(mine, a, p, -angle), turned(theirs, a, p, -angle_before)
            parts.append(np.sum((n @ _rotation(a, -angle_before).T) * (here - there), -1))
        return np.concatenate(parts) if parts else np.zeros(0)

    scale = np.array([1e-2, 1e-2, 10 * spacing, 10 * spacing])

    def fit(x: np.ndarray, reach: float, with_prior: bool = True) -> tuple[np.ndarray, int, int]:
        """Rounds of pairing and fitting from ``x``, the reach halving to its last: (x, rounds, pairs at the end)."""
        for rounds in range(1, MAX_ROUNDS + 1):
            found = matched(x, reach)
            n_pairs = sum(len(f[2]) for f in found)
            if n_pairs < MIN_PAIRS:
                return x, rounds, n_pairs
            step = least_squares(residuals, x, args=(found, with_prior), loss="soft_l1", f_scale=spacing,
                                 x_scale=scale).x - x
            x = x + step
            if reach <= LAST_REACH * spacing and float(np.max(np.abs(step) / scale)) < 1e-4:
                break
            reach = max(reach / 2, LAST_REACH * spacing)
        return x, rounds, sum(len(f[2]) for f in matched(x, LAST_REACH * spacing))

    start = np.zeros(4)
    rms_before = _rms(residuals(start, matched(start, LAST_REACH * spacing), with_prior=False))
    x, rounds, n_pairs = fit(start, FIRST_REACH * spacing)
    if n_pairs < MIN_PAIRS:
        return _kept(axis0, point0, f"the views overlap in only {n_pairs} point pairs (at least {MIN_PAIRS} needed)")
    a, p = line(x)
    tilt, shift = axes_apart(a, p, axis0, point0)
    # Restarted a little off the result and without the pull toward the given axis: an axis the views pin down comes
    # back to it; one they do not (an object nearly symmetric about it) stays off or slides elsewhere.
    probe = np.tan(np.deg2rad(PROBE_TILT))
    slide_tilt, slide_shift = 0.0, 0.0
    for nudge in ([probe, 0, PROBE_SHIFT * spacing, 0], [0, probe, 0, PROBE_SHIFT * spacing]):
        again = line(fit(x + np.array(nudge), 4 * PROBE_SHIFT * spacing, with_prior=False)[0])
        apart = axes_apart(*again, a, p)
        slide_tilt, slide_shift = max(slide_tilt, apart[0]), max(slide_shift, apart[1])
    done = AxisRefinement(a, p, tilt, shift, rounds, n_pairs, rms_before,
                          _rms(residuals(x, matched(x, LAST_REACH * spacing), with_prior=False)), slide_tilt,
                          slide_shift, pinned=slide_tilt <= MAX_SLIDE_TILT and slide_shift <= MAX_SLIDE * spacing)
    if tilt > MAX_TILT or shift > MAX_SHIFT * radius:
        done.refused = (f"the refinement turned the axis {tilt:.1f} degrees and moved it {shift:.3g}, beyond what a "
                        f"calibration is off by ({MAX_TILT:g} degrees, half the object's size): the views "
                        "overlap too little or the object is too symmetric about the axis to place it")
    return done


def _kept(axis: np.ndarray, point: np.ndarray, why: str) -> AxisRefinement:
    return AxisRefinement(axis, point, 0.0, 0.0, 0, 0, float("nan"), float("nan"), refused=why)


def median_spacing(points: np.ndarray, tree: object | None = None) -> float:
    """The median distance between neighbouring points (N, 3) of a view, over a sample of at most 5,000 of them
    (a 1080p view's 2 M would take seconds); ``tree``: a ``cKDTree`` of ``points`` already built."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return float("nan")
    some = points[:: max(1, len(points) // 5000)]
    return float(np.median((tree or cKDTree(points)).query(some, k=2)[0][:, 1]))


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
