"""Camera-projector triangulation: a stereo calibration (each device's pinhole and lens distortion, the projector's
pose) read from an OpenCV file (:func:`read_calibration`), and 3D points from camera -> projector correspondences
(:func:`triangulate`). Pixel centres are at integer coordinates on both devices, as OpenCV and the decoded maps
(``corr/xp``, ``corr/yp``) have them."""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from sssphase_core.errors import InputError

#: The names each quantity may have in a calibration file: Moreno & Taubin's projector-camera calibration
#: (``cam_K``, ``cam_kc``, ``proj_K``, ``proj_kc``, ``R``, ``T``), OpenCV's ``stereoCalibrate`` outputs as samples save them
#: (``K1``/``D1``/``K2``/``D2``, ``M1``/``M2``, ``cameraMatrix1``...), or these long names.
CALIBRATION_KEYS: dict[str, tuple[str, ...]] = {
    "camera_matrix": ("camera_matrix", "cam_K", "K1", "M1", "cameraMatrix1"),
    "camera_distortion": ("camera_distortion", "cam_kc", "D1", "distCoeffs1"),
    "projector_matrix": ("projector_matrix", "proj_K", "K2", "M2", "cameraMatrix2"),
    "projector_distortion": ("projector_distortion", "proj_kc", "D2", "distCoeffs2"),
    "rotation": ("rotation", "R"),
    "translation": ("translation", "T"),
}
#: How many of a view's points (evenly spread) its median reprojection error is measured on.
REPROJECTION_SAMPLE = 20_000
#: A calibration's length unit: a short word (mm, cm, m, in, um).
UNIT_PATTERN = re.compile(r"[A-Za-z\u00b5]{1,8}")
#: Distortion vectors OpenCV reads: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]] (none: an ideal lens).
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


@dataclass(frozen=True)
class StereoCalibration:
    """A camera and a projector as a stereo pair: 3 x 3 intrinsic matrices (pixels), OpenCV distortion vectors
    and the projector's pose, ``X_p = rotation @ X_c + translation`` (the points come out in the translation's
    unit, mm for the simulated rig). Checked on construction."""

    camera_matrix: np.ndarray
    camera_distortion: np.ndarray
    projector_matrix: np.ndarray
    projector_distortion: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    #: the translation's unit, where known (a calibration file does not say)
    unit: str = ""
    #: the turntable's axis in the camera's frame, where calibrated: its direction (3,) (a unit vector; a view at
    #: angle a is the view at 0 turned by a about it, right-handed) and a point on it (3,), the translation's unit
    turntable_axis: np.ndarray | None = None
    turntable_point: np.ndarray | None = None

    def __post_init__(self) -> None:
        with np.errstate(all="ignore"):  # (a huge entry overflows the checks' products: it is refused, not warned of)
            self._check()

    def _check(self) -> None:
        for name in ("camera_matrix", "projector_matrix"):
            k = getattr(self, name)
            if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
                raise InputError(f"{name} must be a finite 3x3 matrix with positive focal lengths, got {_shown(k)}")
        for name in ("camera_distortion", "projector_distortion"):
            d = getattr(self, name)
            if d.size not in DISTORTION_LENGTHS or not np.isfinite(d).all():
                raise InputError(f"{name} must be {', '.join(map(str, DISTORTION_LENGTHS[1:]))} finite coefficients "
                                 f"(OpenCV's order), got {_shown(d)}")
        r, t = self.rotation, self.translation
        if r.shape != (3, 3) or not np.isfinite(r).all() or np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
            raise InputError(f"rotation must be a 3x3 rotation matrix or a Rodrigues vector, got {_shown(r)}")
        if t.shape != (3,) or not np.isfinite(t).all() or not 0 < np.linalg.norm(t) <= MAX_LENGTH:
            raise InputError(f"translation must be 3 finite values, not all zero and at most {MAX_LENGTH:g} long (the "
                             f"baseline, in the calibration's unit), got {_shown(t)}")
        if (self.turntable_axis is None) != (self.turntable_point is None):
            raise InputError("a turntable needs both its turntable_axis and a turntable_point on it")
        if self.turntable_axis is not None:
            a, q = np.asarray(self.turntable_axis, np.float64), np.asarray(self.turntable_point, np.float64)
            if a.shape != (3,) or not np.isfinite(a).all() or abs(np.linalg.norm(a) - 1) > 1e-3:
                raise InputError(f"turntable_axis must be a unit vector of 3 values, got {_shown(a)}")
            if q.shape != (3,) or not np.isfinite(q).all() or np.abs(q).max() > MAX_LENGTH:
                raise InputError(f"turntable_point must be 3 finite values, each at most {MAX_LENGTH:g} in size, got "
                                 f"{_shown(q)}")

    @property
    def baseline(self) -> float:
        """Distance between the camera's and the projector's centres (the translation's unit)."""
        return float(np.linalg.norm(self.translation))


#: The longest baseline (and turntable point's distance) a calibration may give, in any unit: a pose of 1e200 gave
#: NaN points ("invalid value encountered in matmul") and an empty points.ply; a lab's rig in micrometres is 1e6.
MAX_LENGTH = 1e9

#: Millimetres per length unit, for the units a calibration's lengths can be compared in with the simulated rig's (mm).
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "um": 1e-3, "\u00b5m": 1e-3}


def mm_per_unit(calibration: StereoCalibration) -> float | None:
    """Millimetres per unit of ``calibration``'s lengths (no unit: mm), or None for a unit of no known size: a
    calibration in cm is compared with the simulated rig (in mm) after this factor, not as if it were mm."""
    return MM_PER_UNIT.get(calibration.unit or "mm")


def check_unit(unit: str, where: str) -> str:
    """``unit`` if it is a length unit's short name (:data:`UNIT_PATTERN`), else refused in one line."""
    if not isinstance(unit, str) or not UNIT_PATTERN.fullmatch(unit):
        raise InputError(f"{where} must be a length unit's short name (mm, cm, m, in), got {str(unit)[:20]!r}")
    return unit


def _shown(a: np.ndarray) -> str:
    text = np.array2string(np.asarray(a), precision=4, separator=", ", threshold=12).replace("\n", "")
    return f"{text} (shape {'x'.join(map(str, np.shape(a))) or 'scalar'})"


def calibration_from_arrays(values: dict[str, np.ndarray]) -> StereoCalibration:
    """A :class:`StereoCalibration` from arrays named by :data:`CALIBRATION_KEYS` (any of each one's names);
    a rotation may be a Rodrigues vector, a distortion vector a row or a column."""
    found: dict[str, np.ndarray] = {}
    for field, names in CALIBRATION_KEYS.items():
        name = next((n for n in names if n in values), None)
        if name is None:
            if field.endswith("distortion"):
                found[field] = np.zeros(0)
                continue
            raise InputError(f"no {field.replace('_', ' ')} (one of {', '.join(names)})")
        found[field] = np.asarray(values[name], np.float64)
    for field in ("camera_distortion", "projector_distortion", "translation"):
        found[field] = found[field].reshape(-1)
    if found["rotation"].size == 3 and np.isfinite(found["rotation"]).all():
        found["rotation"] = cv2.Rodrigues(found["rotation"].reshape(3, 1))[0]
    return StereoCalibration(**found)


def read_calibration(path: Path | str) -> StereoCalibration:
    """The stereo calibration in an OpenCV FileStorage file (YAML, XML or JSON), as projector-camera calibration
    tools write it (:data:`CALIBRATION_KEYS`); missing distortion is an ideal lens. Refused in one line naming the
    file and what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--calibration {path}: " + ("a folder, not a calibration file" if path.is_dir() else "no such file"))
    if path.stat().st_size == 0:
        raise InputError(f"{path} is empty: give the rig's calibration file (YAML, XML or JSON)")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # (a parse error surfaces as SystemError from the constructor)
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        where = str(getattr(cause, "func", ""))  # OpenCV puts the file's line and the problem here
        said = f": line {where[len(str(path)):].lstrip('(').split(')', 1)[0]}, {where.split(': ', 1)[1][:100]}" if (
            where.startswith(str(path) + "(") and ": " in where) else ""
        raise InputError(f"{path}: not an OpenCV calibration file (YAML, XML or JSON){said}") from None
    try:
        if not storage.isOpened():
            raise InputError(f"{path}: not an OpenCV calibration file (YAML, XML or JSON)")
        values = {}
        for names in CALIBRATION_KEYS.values():
            for name in names:
                node = storage.getNode(name)
                if not node.empty():
                    values[name] = _node_array(node, f"{path}: {name}")
        calibration = calibration_from_arrays(values)
        axis, point = (storage.getNode(name) for name in ("turntable_axis", "turntable_point"))
        if not (axis.empty() and point.empty()):
            calibration = replace(calibration, turntable_axis=None if axis.empty() else _node_array(axis, f"{path}: turntable_axis").reshape(-1),
                                  turntable_point=None if point.empty() else _node_array(point, f"{path}: turntable_point").reshape(-1))
        unit = storage.getNode("unit")  # (sss calibrate stereo writes it; other tools' files do not say)
        if unit.empty():
            return calibration
        return replace(calibration, unit=check_unit(unit.string() if unit.isString() else "", "unit"))
    except InputError as exc:
        message = str(exc)
        raise InputError(message if message.startswith(str(path)) else f"{path}: {message}") from None
    finally:
        storage.release()


def _node_array(node, where: str) -> np.ndarray:  # noqa: ANN001 (cv2.FileNode)
    """A FileStorage node as an array: an OpenCV matrix, a (nested) list of numbers or a number."""
    if node.isSeq():
        if node.size() > max(DISTORTION_LENGTHS):  # (each value is read one by one: a huge list would take minutes)
            raise InputError(f"{where} holds {node.size()} values where a calibration's have at most "
                             f"{max(DISTORTION_LENGTHS)}")
        try:
            return np.array([_node_array(node.at(i), where) for i in range(node.size())], np.float64)
        except ValueError:  # rows of different lengths
            raise InputError(f"{where} is a list of rows of different lengths") from None
    if node.isMap():
        not_a_matrix = f"{where} is not a matrix (an !!opencv-matrix of rows, cols, dt, data)"
        sizes = node.getNode("sizes")  # an n-d matrix (a vector written by OpenCV), else rows and cols
        dims = ([sizes.at(i) for i in range(min(sizes.size(), 4))] if sizes.isSeq() else [sizes] if not sizes.empty()
                else [node.getNode("rows"), node.getNode("cols")])
        if not dims or not all(d.isInt() for d in dims):
            raise InputError(not_a_matrix)
        shape = [int(d.real()) for d in dims]
        if min(shape) == 0 and max(shape) <= 1:  # an empty vector (0 x 1, 1 x 0): no distortion, an ideal lens
            return np.zeros(0)
        if not 0 < np.prod(np.asarray(shape, np.float64)) <= max(DISTORTION_LENGTHS):  # (OpenCV would allocate it)
            raise InputError(f"{where} is a {' x '.join(map(str, shape))} matrix where a calibration's have at "
                             f"most {max(DISTORTION_LENGTHS)} values")
        try:
            value = node.mat()
        except cv2.error:
            raise InputError(not_a_matrix) from None
        if value is None:
            raise InputError(not_a_matrix)
        return np.asarray(value, np.float64)
    if node.isInt() or node.isReal():
        return np.asarray(node.real(), np.float64)
    raise InputError(f"{where} is not a matrix, a list of numbers or a number")


@dataclass(frozen=True)
class Triangulated:
    """Points (H, W, 3) in the camera's frame (the calibration's unit), NaN where none; ``behind``: the pixels
    whose rays met behind the camera or the projector (or never: parallel), left out."""

    points: np.ndarray
    behind: int
    #: the median distance (projector px) between each point projected into the projector and its decoded projector
    #: point: how far the two rays miss each other (NaN without points); a few px or more: not this rig's calibration
    reprojection: float = float("nan")


def triangulate_points(calib: StereoCalibration, camera: np.ndarray, projector: np.ndarray) -> np.ndarray:
    """Camera points (N, 2) and their projector points (N, 2), px -> the 3D points where their rays meet (N, 3),
    float64 in the camera's frame (inf or NaN where the rays are parallel)."""
    cam_n = cv2.undistortPoints(np.asarray(camera, np.float64).reshape(-1, 1, 2), calib.camera_matrix,
                                calib.camera_distortion).reshape(-1, 2)
    proj_n = cv2.undistortPoints(np.asarray(projector, np.float64).reshape(-1, 1, 2), calib.projector_matrix,
                                 calib.projector_distortion).reshape(-1, 2)
    pose = np.hstack([calib.rotation, calib.translation[:, None]])
    homogeneous = cv2.triangulatePoints(np.eye(3, 4), pose, cam_n.T, proj_n.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (homogeneous[:3] / homogeneous[3]).T


def distance_to_axis(points: np.ndarray, axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The distance (...) of points (..., 3) from the line through ``point`` along the unit ``axis``."""
    offset = np.asarray(points, np.float64) - point
    with np.errstate(invalid="ignore"):
        return np.linalg.norm(offset - (offset @ axis)[..., None] * axis, axis=-1)


def axes_apart(axis: np.ndarray, point: np.ndarray, axis0: np.ndarray, point0: np.ndarray) -> tuple[float, float]:
    """The angle (degrees) between two lines, each a unit axis through a point, and the distance of the first's
    ``point`` from the second line."""
    return (float(np.degrees(np.arccos(np.clip(abs(axis @ axis0), -1.0, 1.0)))),
            float(distance_to_axis(point, axis0, point0)))


def turned(points: np.ndarray, axis: np.ndarray, point: np.ndarray, degrees: float) -> np.ndarray:
    """Points (..., 3) turned by ``degrees`` about the line through ``point`` along the unit ``axis`` (right-handed)."""
    rotation = cv2.Rodrigues(np.asarray(axis, np.float64) * np.deg2rad(degrees))[0]
    return (np.asarray(points, np.float64) - point) @ rotation.T + point


def triangulate(calib: StereoCalibration, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray) -> Triangulated:
    """Each camera pixel of ``mask`` (H, W) with its projector point (``xp``, ``yp``: (H, W) projector px) ->
    the 3D point where the two rays meet (linear triangulation of the undistorted points, OpenCV's
    ``triangulatePoints``), (H, W, 3) float32 in the camera's frame."""
    h, w = mask.shape
    ok = mask & np.isfinite(xp) & np.isfinite(yp)
    rows, cols = np.nonzero(ok)
    points = np.full((h, w, 3), np.nan, np.float32)
    if not len(rows):
        return Triangulated(points, 0)
    proj = np.stack([xp[ok], yp[ok]], -1).astype(np.float64).reshape(-1, 1, 2)
    xyz = triangulate_points(calib, np.stack([cols, rows], -1), proj)
    depth_projector = xyz @ calib.rotation[2] + calib.translation[2]
    front = np.isfinite(xyz).all(1) & (xyz[:, 2] > 0) & (depth_projector > 0)
    points[rows[front], cols[front]] = xyz[front]
    if not front.any():
        return Triangulated(points, int((~front).sum()))
    # the median miss from an even sample: projectPoints also computes its Jacobians (2 GB at 1080p)
    sample = np.flatnonzero(front)[np.linspace(0, front.sum() - 1, min(int(front.sum()), REPROJECTION_SAMPLE)).astype(int)]
    seen, _ = cv2.projectPoints(xyz[sample].reshape(-1, 1, 3), cv2.Rodrigues(calib.rotation)[0], calib.translation,
                                calib.projector_matrix, calib.projector_distortion)
    miss = np.linalg.norm(seen.reshape(-1, 2) - proj.reshape(-1, 2)[sample], axis=1)
    return Triangulated(points, int((~front).sum()), float(np.median(miss)))


def shaded(points: np.ndarray, light: tuple[float, float, float] = (-0.5, -0.6, -1.0)) -> np.ndarray:
    """Points (H, W, 3) in the camera's frame (NaN where none) -> (H, W) float32 in [0, 1], NaN where a pixel or a
    neighbour has none: the surface as a matte grey object lit by a distant light from ``light`` (the camera's frame,
    x right, y down, z forward; by default above left of the camera), ``max(0, n . l)`` with the normal n (the cross
    product of the central differences along the rows and columns) turned toward the camera. How a scan's shape,
    noise, ripples and holes are judged by eye."""
    p = np.asarray(points, np.float64)
    du = np.full_like(p, np.nan)
    dv = np.full_like(p, np.nan)
    du[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[1:-1] = p[2:] - p[:-2]
    normal = np.cross(du, dv)
    with np.errstate(divide="ignore", invalid="ignore"):
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        normal *= -np.sign((normal * p).sum(-1, keepdims=True))  # toward the camera, at the origin
    toward = np.asarray(light, np.float64) / np.linalg.norm(light)
    lit = np.clip(normal @ toward, 0.0, 1.0)
    return np.where(np.isfinite(lit), lit, np.nan).astype(np.float32)
