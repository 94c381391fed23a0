"""The object catalogue: procedural SDF shapes with spatially varying materials (paper's object names).

Object space is in mm with the origin at the turntable centre and y pointing down (like the
camera); "up" is -y. Each object's ``sdf`` and ``shade`` take object-space points (N, 3). Shapes
are toys sized to fit a sphere of ``radius`` <= 55 mm, which every preset's view holds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sssphase_core.errors import UnknownObjectError
from sssphase_core.sim import geometry as g
from sssphase_core.sim.materials import MATERIAL_NAMES, MATERIALS, Material


@dataclass(frozen=True)
class MaterialSample:
    """Per-point material: albedo (N, 3), mean free path mfp (N, 3) mm, rho_s (N,), label (N,) int."""

    albedo: np.ndarray
    mfp: np.ndarray
    rho_s: np.ndarray
    label: np.ndarray


def mix(weights: np.ndarray, materials: Sequence[Material]) -> MaterialSample:
    """Blend materials with per-point weights (N, M) (normalised here); label = dominant material."""
    w = np.clip(np.asarray(weights, np.float64), 0.0, None)
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    alb = np.array([m.albedo for m in materials])
    mfp = np.array([m.mfp for m in materials])
    rho = np.array([m.rho_s for m in materials])
    ids = np.array([MATERIAL_NAMES.index(m.name) if m.name in MATERIAL_NAMES else -1 for m in materials])
    return MaterialSample(w @ alb, w @ mfp, w @ rho, ids[np.argmax(w, axis=1)].astype(np.int16))


def uniform(material: Material) -> Callable[[np.ndarray], MaterialSample]:
    """Shader of a homogeneous object."""
    return lambda p: mix(np.ones((len(p), 1)), [material])


@dataclass(frozen=True)
class SimObject:
    """A catalogue entry. ``pose`` rotates the object's natural frame into object space."""

    name: str
    split: str  # "train", "unseen", "extra" (measured materials outside the paper's splits) or "test"
    description: str
    radius: float
    natural_sdf: Callable[[np.ndarray], np.ndarray]
    natural_shade: Callable[[np.ndarray], MaterialSample]
    pose: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    #: a target held by hand rather than turned by the turntable: per view (cycled), its tilt about x and its turn
    #: about y (degrees)
    hand_poses: tuple[tuple[float, float], ...] = ()

    def orientation(self, angle: float, view: int) -> np.ndarray:
        """The object -> camera rotation (3, 3) of a view: the turntable's at ``angle`` degrees, or a hand-held
        target's own pose for that view."""
        if not self.hand_poses:
            return g.rotation_y(np.deg2rad(angle))
        tilt, turn = self.hand_poses[view % len(self.hand_poses)]
        return g.rotation_y(np.deg2rad(turn)) @ g.rotation_x(np.deg2rad(tilt))

    def _natural(self, p: np.ndarray) -> np.ndarray:
        return p @ np.asarray(self.pose)  # row vectors: q = R^T p

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return self.natural_sdf(self._natural(p))

    def shade(self, p: np.ndarray) -> MaterialSample:
        return self.natural_shade(self._natural(p))


def _pose(*rotations: np.ndarray) -> tuple[tuple[float, ...], ...]:
    r = np.eye(3)
    for rot in rotations:
        r = rot @ r
    return tuple(tuple(float(v) for v in row) for row in r)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


M = MATERIALS
deg = np.deg2rad


# --- training objects --------------------------------------------------------------------------


def _apple_sdf(p):
    body = g.ellipsoid(p, (0, 0, 0), (38, 34, 38))
    rho = np.hypot(p[:, 0], p[:, 2])
    dimple = 7.0 * np.exp(-((rho / 9.0) ** 2))
    stem = g.capsule(p, (0, -26, 0), (2.5, -42, 1), 1.6)
    return np.minimum(body + dimple, stem)


def _apple_shade(p):
    n = g.value_noise(p, 25.0, seed=1)
    streaks = g.value_noise(p * np.array([4.0, 0.4, 4.0]), 18.0, seed=2)
    red = _smoothstep(-0.4, 0.4, p[:, 0] / 38 + 0.35 * n + 0.25 * streaks)
    stem = (g.capsule(p, (0, -26, 0), (2.5, -42, 1), 1.6) < 0.3).astype(float)
    return mix(np.stack([(1 - red) * (1 - stem), red * (1 - stem), stem], 1), [M["apple_flesh"], M["apple_red"], M["stem"]])


def _pear_sdf(p):
    body = g.sphere(p, (0, 15, 0), 30)
    neck = g.ellipsoid(p, (0, -13, 0), (17, 22, 17))
    stem = g.capsule(p, (0, -33, 0), (4, -47, 0), 1.5)
    return np.minimum(g.smin(body, neck, 12.0), stem)


def _pear_shade(p):
    spots = _smoothstep(0.55, 0.75, g.value_noise(p, 6.0, seed=3))
    stem = (g.capsule(p, (0, -33, 0), (4, -47, 0), 1.5) < 0.3).astype(float)
    return mix(np.stack([1 - stem, 0.4 * spots * (1 - stem) + stem], 1), [M["pear"], M["stem"]])


def _orange_sdf(p):
    return g.sphere(p, (0, 0, 0), 38) + 0.25 * g.value_noise(p, 2.5, seed=4)


def _orange_shade(p):
    rho = np.hypot(p[:, 0], p[:, 2])
    scar = ((rho < 3.0) & (p[:, 1] < 0)).astype(float)
    return mix(np.stack([1 - scar, scar], 1), [M["orange_peel"], M["stem"]])


def _star_sdf(p):
    return g.extrude(g.star2d(p[:, 0], p[:, 1], 44.0, 19.0), p[:, 2], 7.0) - 2.0


def _shovel_sdf(p):
    q = p.copy()
    q[:, 2] -= (q[:, 0] ** 2) / 150.0  # curved blade
    blade = g.round_box(q, (0, 20, 0), (22, 21, 2.5), 2.0)
    handle = g.capsule(p, (0, -2, 0), (0, -38, 0), 4.0)
    grip = g.capsule(p, (-11, -41, 0), (11, -41, 0), 4.5)
    return g.smin(blade, np.minimum(handle, grip), 3.0)


# --- unseen objects ----------------------------------------------------------------------------


def _crab_parts(p):
    body = g.ellipsoid(p, (0, 0, 0), (30, 11, 22))
    claws = [g.ellipsoid(p, (s * 28, -2, -27), (9, 6, 12)) for s in (-1, 1)]
    arms = [g.capsule(p, (s * 18, 0, -12), (s * 27, -1, -22), 3.5) for s in (-1, 1)]
    legs = [
        g.capsule(p, (s * 24, 2, z), (s * 44, 12, z + 8), 2.2)
        for s in (-1, 1)
        for z in (-4.0, 5.0, 14.0)
    ]
    eyes = [g.capsule(p, (s * 5, -8, -18), (s * 6, -13, -21), 1.5) for s in (-1, 1)]
    return body, g.union(*claws, *arms), g.union(*legs, *eyes)


def _crab_sdf(p):
    body, claws, legs = _crab_parts(p)
    return g.smin(g.smin(body, claws, 3.0), legs, 2.0)


def _crab_shade(p):
    top = _smoothstep(-2.0, 4.0, -p[:, 1] + 3.0 * g.value_noise(p, 10.0, seed=5))
    return mix(np.stack([top, 1 - top], 1), [M["crab_shell"], M["crab_belly"]])


_FINGERS = (
    ((-12, -12, 0), (-14, -44, 0), 5.5),
    ((-3.5, -14, 0), (-4, -50, 0), 5.8),
    ((5, -13, 0), (6, -46, 0), 5.5),
    ((13, -10, 0), (17, -36, 0), 5.0),
    ((-19, 12, 0), (-35, -6, -4), 6.0),
)


def _hand_sdf(p):
    palm = g.round_box(p, (0, 8, 0), (19, 21, 7), 6.5)
    fingers = g.union(*(g.capsule(p, a, b, r) for a, b, r in _FINGERS))
    wrist = g.capsule(p, (0, 28, 0), (0, 48, 2), 13.0)
    return g.smin(g.smin(palm, fingers, 4.0), wrist, 6.0)


def _hand_shade(p):
    tips = [np.asarray(b, float) for _, b, _ in _FINGERS]
    near_tip = np.min([g.length(p - t) for t in tips], axis=0)
    nail = ((near_tip < 6.5) & (p[:, 2] > 2.5)).astype(float)
    palm_side = _smoothstep(-1.0, 1.0, -p[:, 2])
    return mix(np.stack([(1 - palm_side) * (1 - nail), palm_side * (1 - nail), nail], 1),
               [M["skin"], M["skin_palm"], M["nail"]])


def _tangerine_sdf(p):
    return g.ellipsoid(p, (0, 0, 0), (31, 24, 31)) + 0.2 * g.value_noise(p, 2.0, seed=6)


def _tangerine_shade(p):
    rho = np.hypot(p[:, 0], p[:, 2])
    scar = ((rho < 2.5) & (p[:, 1] < 0)).astype(float)
    return mix(np.stack([1 - scar, scar], 1), [M["tangerine_peel"], M["stem"]])


def _rake_sdf(p):
    head = g.round_box(p, (0, 8, 0), (38, 4.5, 4), 2.0)
    tines = g.union(*(g.capsule(p, (x, 10, 0), (x, 30, -4), 2.2) for x in np.linspace(-33, 33, 7)))
    handle = g.capsule(p, (0, 4, 0), (0, -42, 4), 4.0)
    return g.smin(g.smin(head, tines, 2.0), handle, 3.0)


def _soap_sdf(p):
    return g.round_box(p, (0, 0, 0), (36, 13, 24), 8.0)


def _soap_shade(p):
    warp = 3.0 * g.value_noise(p, 30.0, seed=7)
    vein = _smoothstep(0.25, 0.05, np.abs(np.sin(0.11 * (p[:, 0] + 0.6 * p[:, 2]) + warp)))
    return mix(np.stack([1 - vein, vein], 1), [M["marble"], M["soap_vein"]])


def _leaf_sdf(p):
    q = p.copy()
    q[:, 2] += (q[:, 0] ** 2) / 60.0 - (q[:, 1] ** 2) / 400.0  # curled blade
    width = 24.0 * np.sqrt(np.clip(1 - ((q[:, 1] + 2) / 46.0) ** 2, 0.0, 1.0)) * (1 - 0.25 * (q[:, 1] < -10) * ((-q[:, 1] - 10) / 36))
    blade2d = np.abs(q[:, 0]) - width
    blade2d = np.maximum(blade2d, np.abs(q[:, 1] + 2) - 46.0)
    blade = g.extrude(blade2d, q[:, 2], 1.6) - 0.5
    stalk = g.capsule(p, (0, 42, 0), (1, 54, 2), 1.6)
    return np.minimum(0.7 * blade, stalk)


def _leaf_shade(p):
    x, y = p[:, 0], p[:, 1]
    mid = _smoothstep(1.6, 0.6, np.abs(x))
    lateral = _smoothstep(0.9, 0.3, np.abs(np.mod(y + 0.9 * np.abs(x), 9.0) - 4.5)) * (np.abs(x) < 18)
    vein = np.maximum(mid, 0.8 * lateral)
    return mix(np.stack([1 - vein, vein], 1), [M["leaf"], M["leaf_vein"]])


_STUDS = [(x, z) for x in (-30.0, -10.0, 10.0, 30.0) for z in (-10.0, 10.0)]


def _lego_sdf(p):
    brick = g.round_box(p, (0, 0, 0), (40, 12, 20), 0.8)
    studs = g.union(*(g.cylinder_y(p, (x, -14.0, z), 6.0, 2.2) - 0.4 for x, z in _STUDS))
    return np.minimum(brick, studs)


# --- extra objects: measured materials (Jensen et al. 2001) outside the paper's splits ------------


def _chicken_sdf(p):
    return g.ellipsoid(p, (0, 0, 0), (44, 30, 14)) + 0.6 * g.value_noise(p, 12.0, seed=11)


def _chicken_shade(p):
    streak = _smoothstep(0.3, 0.7, g.value_noise(p * np.array([0.5, 3.0, 1.0]), 20.0, seed=12))
    return mix(np.stack([1 - streak, streak], 1), [M["chicken"], M["chicken_fat"]])


def _potato_sdf(p):
    return g.ellipsoid(p, (0, 0, 0), (42, 27, 30)) + 1.5 * g.value_noise(p, 18.0, seed=13)


def _milk_sdf(p):
    return g.cylinder_y(p, (0, 0, 0), 36.0, 22.0) - 2.0


# --- a calibration target --------------------------------------------------------------------------

#: The simulated checkerboard: squares (columns, rows), their side (mm); its inner corners, the pattern
#: `sss calibrate stereo --board 6x4 --square 9` looks for, are one fewer each way.
BOARD_SQUARES, BOARD_SQUARE_MM = (7, 5), 9.0
#: Its poses, one per view (cycled): tilt about x and turn about y (degrees), as a hand holds a board to calibrate.
BOARD_POSES = ((0.0, 0.0), (-40.0, 0.0), (40.0, 0.0), (0.0, -45.0), (0.0, 40.0), (-35.0, -35.0), (35.0, 35.0),
               (30.0, -40.0), (-30.0, 35.0), (-20.0, -15.0), (20.0, 15.0), (45.0, -10.0))


def _board_sdf(p):
    return g.round_box(p, (0, 0, 0), (35.0, 26.0, 1.5), 0.5)


def _board_shade(p):
    """Printed on its front (the face toward -z, the camera at view 0): black squares on white; the back is grey, so
    that a board seen from behind is not found mirrored."""
    (cols, rows), side = BOARD_SQUARES, BOARD_SQUARE_MM
    i, j = np.floor(p[:, 0] / side + cols / 2), np.floor(p[:, 1] / side + rows / 2)
    on_grid = (i >= 0) & (i < cols) & (j >= 0) & (j < rows)
    black = on_grid & ((i + j) % 2 == 0) & (p[:, 2] < 0)
    albedo = np.where(black[:, None], 0.04, np.where((p[:, 2] < 0)[:, None], 0.82, 0.35))
    paper = M["backdrop"]  # opaque: its light leaves where it enters
    n = len(p)
    return MaterialSample(np.repeat(albedo, 3, axis=1), np.tile(np.asarray(paper.mfp, np.float64), (n, 1)), np.full(n, paper.rho_s),
                          np.full(n, paper.label, np.int16))


#: Where the turntable board stands: its centre 25 mm from the turntable's axis, toward the camera at view 0 (mm).
TURNTABLE_BOARD_OFFSET = np.array([0.0, 0.0, -25.0])


def _turntable_board_sdf(p):
    return _board_sdf(p - TURNTABLE_BOARD_OFFSET)


def _turntable_board_shade(p):
    return _board_shade(p - TURNTABLE_BOARD_OFFSET)


def _build() -> dict[str, SimObject]:
    objs = [
        SimObject("apple", "train", "apple with red and yellow sides and a stem (Jensen apple)", 46, _apple_sdf, _apple_shade),
        SimObject("pear", "train", "weakly scattering pear with russet spots", 50, _pear_sdf, _pear_shade),
        SimObject("orange", "train", "orange with a dimpled peel", 40, _orange_sdf, _orange_shade),
        SimObject("star", "train", "near-opaque plastic star", 50, _star_sdf, uniform(M["plastic_star"]),
                  _pose(g.rotation_x(deg(15)))),
        SimObject("shovel", "train", "translucent toy shovel", 52, _shovel_sdf, uniform(M["plastic_shovel"]),
                  _pose(g.rotation_x(deg(-35)))),
        SimObject("crab", "unseen", "toy crab: shell, belly, claws and legs", 54, _crab_sdf, _crab_shade,
                  _pose(g.rotation_x(deg(40)))),
        SimObject("hand", "unseen", "hand with skin (Jensen skin1/skin2) and nails", 55, _hand_sdf, _hand_shade),
        SimObject("tangerine", "unseen", "oblate tangerine", 33, _tangerine_sdf, _tangerine_shade),
        SimObject("sand_rake", "unseen", "toy sand rake", 52, _rake_sdf, uniform(M["plastic_rake"]),
                  _pose(g.rotation_x(deg(-25)))),
        SimObject("soap", "unseen", "soap bar, marble base (Jensen marble) with veins", 46, _soap_sdf, _soap_shade,
                  _pose(g.rotation_x(deg(30)), g.rotation_y(deg(20)))),
        SimObject("leaf", "unseen", "thin curled leaf with veins", 56, _leaf_sdf, _leaf_shade,
                  _pose(g.rotation_y(deg(20)))),
        SimObject("lego", "unseen", "large near-opaque lego brick with studs", 50, _lego_sdf, uniform(M["plastic_lego"]),
                  _pose(g.rotation_x(deg(30)), g.rotation_y(deg(25)))),
        SimObject("chicken", "extra", "chicken fillet with fat streaks (Jensen chicken1/chicken2)", 46, _chicken_sdf,
                  _chicken_shade, _pose(g.rotation_x(deg(-50)))),
        SimObject("potato", "extra", "lumpy potato (Jensen potato)", 44, _potato_sdf, uniform(M["potato"]),
                  _pose(g.rotation_x(deg(20)))),
        SimObject("milk", "extra", "puck of skim milk, as in a thin dish (Jensen skimmilk)", 46, _milk_sdf,
                  uniform(M["skimmilk"]), _pose(g.rotation_x(deg(-30)))),
        SimObject("calibration_board", "calibration", "printed checkerboard, 7 x 5 squares of 9 mm, held in 12 poses "
                  "(views) for `sss calibrate stereo --board 6x4 --square 9`", 46, _board_sdf, _board_shade,
                  hand_poses=BOARD_POSES),
        SimObject("turntable_board", "calibration", "the same checkerboard standing on the turntable, 25 mm off its "
                  "axis and leaning back 20 degrees, for `sss calibrate turntable` (its front faces the camera at "
                  "view 0; `--views 12` shows it whole in 3: 0, 30 and 330 degrees)", 50, _turntable_board_sdf,
                  _turntable_board_shade,
                  _pose(g.rotation_x(deg(-20)))),
    ]
    return {o.name: o for o in objs}


CATALOGUE: dict[str, SimObject] = _build()
TRAIN_OBJECTS = ("apple", "pear", "orange", "star", "shovel")
UNSEEN_OBJECTS = ("crab", "hand", "tangerine", "sand_rake", "soap", "leaf", "lego")
EXTRA_OBJECTS = ("chicken", "potato", "milk")  # measured materials, outside the paper's splits
CALIBRATION_OBJECTS = ("calibration_board", "turntable_board")  # targets to calibrate the rig with (`sss calibrate ...`)


def get_object(name: str) -> SimObject:
    """Catalogue lookup; an unknown name raises :class:`UnknownObjectError` listing the catalogue."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise UnknownObjectError(
            f"unknown object {name!r}; the catalogue has: training {', '.join(TRAIN_OBJECTS)}; "
            f"unseen {', '.join(UNSEEN_OBJECTS)}; extra (measured materials) {', '.join(EXTRA_OBJECTS)}; "
            f"calibration {', '.join(CALIBRATION_OBJECTS)}"
        ) from None


def object_materials(obj: SimObject, samples: int = 20000, seed: int = 0) -> list[str]:
    """Names of the materials an object is made of (dominant label of points sampled inside it),
    most frequent first."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-obj.radius, obj.radius, size=(samples, 3))
    inside = p[obj.sdf(p) <= 0]
    if len(inside) == 0:
        return []
    labels, counts = np.unique(obj.shade(inside).label, return_counts=True)
    return [MATERIAL_NAMES[int(i)] for i in labels[np.argsort(-counts)]]
