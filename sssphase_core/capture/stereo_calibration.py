"""Camera-projector calibration from a session of a printed checkerboard (``sss calibrate stereo``).

Each view of the session holds the board at another pose (a turntable, or the hand between views: `sss capture`
asks for the move when the rig has no turntable). Per view, the board's inner corners are found in the white
capture (OpenCV's ``findChessboardCorners``, refined to a fraction of a pixel), and each corner's projector point
is read through a *local homography* fitted from the camera pixels around it to their decoded projector points
(Moreno and Taubin 2012: the board is flat, so near a corner the two images are related by a homography, and
fitting one over a window averages the decoding's noise). The camera and the projector are then calibrated as two
cameras (``calibrateCamera``) and as a pair (``stereoCalibrate``, intrinsics fixed), and the result written in
the names :func:`~sssphase_core.processing.triangulation.read_calibration` reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sssphase_core.errors import DataError, InputError, SssError
from sssphase_core.processing.triangulation import MM_PER_UNIT, StereoCalibration, check_unit, mm_per_unit
from sssphase_core.store.files import atomic_path

#: Half the side (camera px) of the window around a corner whose decoded points its local homography is fitted to,
#: at least; a larger board square widens it to 0.4 of the square's side.
HOMOGRAPHY_HALF_WINDOW = 5
#: Views a calibration needs at the least (three poses fix a camera's intrinsics; more make them firm).
MIN_VIEWS = 3
#: Focal lengths (in image widths) a calibration may come out with: fields of view from about 150 to 6 degrees.
#: Poses that do not pin the focal length down give any value (three views of one pose: 13.7 widths).
FOCAL_RANGE = (0.15, 10.0)
#: The uncertainty (OpenCV's standard deviations) above which a calibration is written with a warning: the focal
#: length's relative one, and the principal point's as a share of the image's larger side. The simulated board's 12
#: poses: 3.2-3.3% and 1.5% (its focal lengths came out within 0.8%); three of its mildest poses: 14% and 4%.
MAX_FOCAL_SD, MAX_CENTRE_SD = 0.05, 0.05
MORE_POSES = "capture the board in more poses, tilted and turned by 30 to 45 degrees, filling more of the view"


#: What each device's calibration estimates: square pixels, a principal point, and one radial distortion term (k1).
#: On the simulated board (12 poses, 256 x 192) freeing the aspect ratio put the projector's focal lengths 4% apart,
#: and with no distortion term at all both principal points landed 10-28 px off; k1 alone brings both focal lengths
#: within 1% and the principal points within 3 px.
LENS_MODEL = cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
#: The lens models ``--lens`` names: that one (``k1``), three radial terms (``radial``: k1, k2, k3), or OpenCV's whole
#: five-term model with free focal lengths along x and y (``full``: k1, k2, p1, p2, k3). More terms need more poses,
#: wider ones and a larger view of the board (see docs/benchmarks/calibration.md for the simulated board's figures).
LENS_MODELS = {"k1": LENS_MODEL, "radial": cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST, "full": 0}


@dataclass
class BoardView:
    """One view's board: ``camera`` and ``projector`` (N, 2) corner points, row by row."""

    view: int
    camera: np.ndarray
    projector: np.ndarray


@dataclass
class StereoResult:
    """A stereo calibration and how well it fits: RMS reprojection errors (px) of the camera's, the projector's and
    the pair's calibration, the views used and those left out with why."""

    calibration: StereoCalibration
    camera_rms: float
    projector_rms: float
    stereo_rms: float
    views: list[int]
    skipped: dict[int, str] = field(default_factory=dict)
    #: per device, OpenCV's estimate of the calibration's own uncertainty: the focal length's standard deviation
    #: relative to it, and the principal point's (px)
    uncertainty: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: per device, its image size (W, H)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)

    @property
    def errors(self) -> dict[str, float]:
        """The RMS errors by the names calibration files give them (:data:`ERROR_KEYS`)."""
        return dict(zip(ERROR_KEYS, (self.camera_rms, self.projector_rms, self.stereo_rms), strict=True))

    def shaky(self) -> list[str]:
        """The devices whose focal length is uncertain by more than :data:`MAX_FOCAL_SD`, or whose principal point
        by more than :data:`MAX_CENTRE_SD` of the image's larger side, with their figures."""
        return [f"{name}: focal length +-{100 * f:.1f}%, principal point +-{c:.1f} px"
                for name, (f, c) in self.uncertainty.items()
                if f > MAX_FOCAL_SD or c > MAX_CENTRE_SD * max(self.sizes[name])]


#: The side of a board's square a calibration takes, in any unit (a micrometre board in mm to a 10 m one in mm): beyond,
#: the board's points overflow OpenCV's fit (1e300 raised an assertion of its own).
SQUARE_RANGE = (1e-6, 1e6)


def parse_board(text: str) -> tuple[int, int]:
    """``COLSxROWS`` inner corners (e.g. ``9x6``: a board of 10 x 7 squares), each at least 2."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board must be COLSxROWS inner corners, e.g. 9x6 (a board of 10 x 7 squares), got {text!r}") from None
    if not (2 <= cols <= 100 and 2 <= rows <= 100):
        raise InputError(f"--board {text}: a board has 2 to 100 inner corners each way")
    return cols, rows


def board_corners(white: np.ndarray, mask: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """The board's inner corners (N, 2) in the white capture (H, W, 3), refined to a fraction of a pixel, row by row;
    None where the whole board is not seen."""
    grey = np.nan_to_num(white.astype(np.float32).mean(axis=-1))
    level = np.percentile(grey[mask], 99) if mask.any() else grey.max()
    image = np.round(255 * np.clip(grey / max(float(level), 1e-9), 0, 1)).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(image, board, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    refined = cv2.cornerSubPix(image, corners, (3, 3), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64)


#: Why a view's corners got no projector points (:func:`projector_corners`).
TOO_FEW_DECODED = "too few decoded pixels around a corner (does the projector's light reach the whole board?)"
NOT_FLAT = "the decoded points around a corner fit no homography (is the board flat, and lit only by the projector?)"


def projector_corners(camera: np.ndarray, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray,
                      half: int) -> np.ndarray | str:
    """Each camera corner's projector point (N, 2) through a homography fitted (robustly: RANSAC, 1 projector px) to
    the decoded points of the pixels within ``half`` px of it, or why not (:data:`TOO_FEW_DECODED`, :data:`NOT_FLAT`:
    fewer than half of them fit one)."""
    h, w = mask.shape
    out = np.empty_like(camera)
    for k, (u, v) in enumerate(camera):
        r0, r1 = max(0, int(round(v)) - half), min(h, int(round(v)) + half + 1)
        c0, c1 = max(0, int(round(u)) - half), min(w, int(round(u)) + half + 1)
        rows, cols = np.nonzero(mask[r0:r1, c0:c1] & np.isfinite(xp[r0:r1, c0:c1]) & np.isfinite(yp[r0:r1, c0:c1]))
        if len(rows) < 12:
            return TOO_FEW_DECODED
        rows, cols = rows + r0, cols + c0
        src = np.column_stack([cols, rows]).astype(np.float64)
        dst = np.column_stack([xp[rows, cols], yp[rows, cols]]).astype(np.float64)
        homography, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 1.0)
        if homography is None or inliers.sum() < len(src) / 2:
            return NOT_FLAT
        out[k] = cv2.perspectiveTransform(np.array([[[u, v]]]), homography)[0, 0]
    return out


def find_boards(session: Any, board: tuple[int, int], views: Sequence[int] | None = None, progress: Any = None
                ) -> tuple[list[BoardView], dict[int, str], tuple[int, int], tuple[int, int]]:
    """The views of ``session`` (``views``, default all) where the whole ``board`` is seen, with each corner in the
    camera and the projector -> (those views, the others with why not, the camera's and the projector's size)."""
    chosen = list(views) if views else session.views()
    projector = tuple(int(v) for v in session.manifest.get("plan", {}).get("projector", ()))
    if len(projector) != 2:
        raise DataError(f"{session.path}: its capture plan names no projector size")
    found: list[BoardView] = []
    skipped: dict[int, str] = {}
    size = None
    for i, v in enumerate(chosen):
        white = np.asarray(session.load(v, "white"), np.float32)
        mask = np.asarray(session.load(v, "corr/mask")).astype(bool)
        size = (white.shape[1], white.shape[0])
        camera = board_corners(white, mask, board)
        if camera is None:
            skipped[v] = f"no {board[0]}x{board[1]} board found in the white capture"
        else:
            spacing = float(np.median(np.linalg.norm(np.diff(camera.reshape(board[1], board[0], 2), axis=1), axis=-1)))
            half = max(HOMOGRAPHY_HALF_WINDOW, int(0.4 * spacing))
            xp, yp = (np.asarray(session.load(v, name), np.float32) for name in ("corr/xp", "corr/yp"))
            points = projector_corners(camera, xp, yp, mask, half)
            if isinstance(points, str):
                skipped[v] = points
            else:
                found.append(BoardView(v, camera, points))
        if progress:
            progress(i + 1, len(chosen))
    return found, skipped, size or (0, 0), projector  # type: ignore[return-value]


def require_boards(session: Any, found: list[BoardView], skipped: dict[int, str], needed: int) -> None:
    """Refuse, in one line giving each left-out view's reason, fewer than ``needed`` views with the board."""
    if len(found) < needed:
        by_reason: dict[str, list[int]] = {}
        for v, reason in skipped.items():
            by_reason.setdefault(reason, []).append(v)
        why = "; ".join(f"{reason}: view{'s' if len(vs) > 1 else ''} {', '.join(map(str, vs))}"
                        for reason, vs in by_reason.items())
        hint = ("; check --board (inner corners, e.g. 9x6 for 10 x 7 squares)" if any(r.startswith("no ") for r in by_reason)
                else "")
        raise DataError(f"{session.path}: the board was found in {len(found)} view(s) where a calibration needs at least "
                        f"{needed}" + (f" ({why}){hint}" if why else ": capture more poses of it"))


def calibrate_stereo(session: Any, board: tuple[int, int], square: float, views: Sequence[int] | None = None,
                     progress: Any = None, unit: str = "mm", lens: str = "k1") -> StereoResult:
    """Calibrate the camera and the projector from ``session``'s views of a checkerboard of ``board`` inner corners
    (columns, rows) and ``square`` side, in ``unit`` (the result's), each device's lens as ``lens``
    (:data:`LENS_MODELS`); refused in one line where fewer than :data:`MIN_VIEWS` views show the whole board."""
    if lens not in LENS_MODELS:
        raise InputError(f"--lens must be one of {', '.join(LENS_MODELS)} (the distortion terms to estimate), got {lens!r}")
    check_unit(unit, "--unit")
    if unit not in MM_PER_UNIT:  # (a file read may name any unit; one written here is one whose size is known)
        raise InputError(f"--unit must be one of {', '.join(MM_PER_UNIT)} (the unit of --square), got {unit!r}")
    if not square > 0 or not np.isfinite(square) or not SQUARE_RANGE[0] <= square <= SQUARE_RANGE[1]:
        raise InputError(f"--square must be the board's square side, a positive length in --unit ({unit}), from "
                         f"{SQUARE_RANGE[0]:g} to {SQUARE_RANGE[1]:g}, got {square!r}")
    found, skipped, size, projector = find_boards(session, board, views, progress)
    require_boards(session, found, skipped, MIN_VIEWS)
    grid = np.zeros((board[0] * board[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0 : board[0], 0 : board[1]].T.reshape(-1, 2) * square
    objects = [grid] * len(found)
    cams = [b.camera.astype(np.float32).reshape(-1, 1, 2) for b in found]
    projs = [b.projector.astype(np.float32).reshape(-1, 1, 2) for b in found]
    square_pixels = lambda wh: np.array([[1.0, 0, wh[0] / 2], [0, 1.0, wh[1] / 2], [0, 0, 1]])  # noqa: E731 (fx/fy = 1)
    try:
        cam_rms, k_cam, d_cam, _, _, sd_cam, _, _ = cv2.calibrateCameraExtended(
            objects, cams, size, square_pixels(size), None, flags=LENS_MODELS[lens])
        proj_rms, k_proj, d_proj, _, _, sd_proj, _, _ = cv2.calibrateCameraExtended(
            objects, projs, projector, square_pixels(projector), None, flags=LENS_MODELS[lens])
        stereo_rms, k_cam, d_cam, k_proj, d_proj, rotation, translation, _, _ = cv2.stereoCalibrate(
            objects, cams, projs, k_cam, d_cam, k_proj, d_proj, size, flags=cv2.CALIB_FIX_INTRINSIC)
        calibration = StereoCalibration(k_cam, d_cam.reshape(-1), k_proj, d_proj.reshape(-1), rotation,
                                        translation.reshape(-1), unit=unit)
    except (cv2.error, InputError) as exc:  # degenerate poses: OpenCV's solver fails, or returns no rotation
        said = str(exc).strip().splitlines()[-1][:160]
        raise DataError(f"{session.path}: the views {', '.join(map(str, (b.view for b in found)))} do not calibrate "
                        f"({said}): {MORE_POSES}") from None
    uncertainty = {name: (float(max(sd.ravel()[0] / k[0, 0], sd.ravel()[1] / k[1, 1])), float(np.hypot(*sd.ravel()[2:4])))
                   for name, k, sd in (("camera", k_cam, sd_cam), ("projector", k_proj, sd_proj))}
    for name, k, wh in (("camera", k_cam, size), ("projector", k_proj, projector)):
        if not FOCAL_RANGE[0] * max(wh) <= k[1, 1] <= FOCAL_RANGE[1] * max(wh):
            raise DataError(f"{session.path}: the {name}'s focal length came out {k[1, 1]:.0f} px, a field of view no lens "
                            f"of a {wh[0]}x{wh[1]} {name} has: the views {', '.join(str(b.view) for b in found)} do not "
                            f"pin it down; {MORE_POSES}")
    return StereoResult(calibration, float(cam_rms), float(proj_rms), float(stereo_rms), [b.view for b in found], skipped,
                        uncertainty, {"camera": size, "projector": projector})


def against_simulated_rig(session: Any, calibration: StereoCalibration) -> str | None:
    """One line comparing ``calibration`` with a simulated session's exact rig (evaluation only), or None for a session
    of another rig: each device's focal length (%) and principal point (px), the pose's rotation (degrees) and the
    baseline (%)."""
    from sssphase_core.sim import session_rig_calibration

    exact = session_rig_calibration(session.manifest.get("rig", {}))
    if exact is None:
        return None
    parts = []
    for name, got, want in (("camera", calibration.camera_matrix, exact.camera_matrix),
                            ("projector", calibration.projector_matrix, exact.projector_matrix)):
        parts.append(f"{name} focal length {100 * (got[1, 1] / want[1, 1] - 1):+.1f}%, principal point "
                     f"{np.hypot(*(got[:2, 2] - want[:2, 2])):.1f} px off")
    turn = np.degrees(np.linalg.norm(cv2.Rodrigues(calibration.rotation @ exact.rotation.T)[0]))
    factor = mm_per_unit(calibration)  # (the simulated rig's lengths are in mm)
    baseline = (f"its baseline {100 * (factor * calibration.baseline / exact.baseline - 1):+.1f}%" if factor is not None
                else f"its baseline not compared (the unit {calibration.unit!r} is none of {', '.join(MM_PER_UNIT)})")
    return (f"against the simulated rig's exact calibration: {'; '.join(parts)}; the projector's pose turned {turn:.2f} "
            f"degrees, {baseline}")


def write_calibration(path: Path | str, calibration: StereoCalibration, errors: dict[str, float] | None = None) -> Path:
    """Write ``calibration`` as an OpenCV YAML, XML or JSON file (``path``'s suffix says which) in the names
    projector-camera calibration tools use (cam_K, cam_kc, proj_K, proj_kc, R, T), its ``unit``, its turntable axis
    where it has one (turntable_axis, turntable_point) and ``errors`` (e.g. the RMS errors cam_error, proj_error,
    stereo_error), atomically."""
    path = Path(path)
    c = calibration
    with atomic_path(path, path.suffix) as tmp:  # (OpenCV writes the format the suffix names)
        storage = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            for name, value in (("cam_K", c.camera_matrix), ("cam_kc", c.camera_distortion.reshape(1, -1)),
                                ("proj_K", c.projector_matrix), ("proj_kc", c.projector_distortion.reshape(1, -1)),
                                ("R", c.rotation), ("T", c.translation.reshape(3, 1))):
                if value.size:  # (no distortion vector: an ideal lens)
                    storage.write(name, np.asarray(value, np.float64))
            if c.turntable_axis is not None and c.turntable_point is not None:
                storage.write("turntable_axis", np.asarray(c.turntable_axis, np.float64).reshape(3, 1))
                storage.write("turntable_point", np.asarray(c.turntable_point, np.float64).reshape(3, 1))
            for name, value in (errors or {}).items():
                storage.write(name, float(value))
            if c.unit:
                storage.write("unit", c.unit)
        finally:
            storage.release()
    return path


#: The RMS errors a calibration file records (:attr:`StereoResult.errors`).
ERROR_KEYS = ("cam_error", "proj_error", "stereo_error")
#: The entries :func:`write_calibration` writes: a file holding others (another tool's names, image sizes, notes) is
#: not rewritten in place.
WRITTEN_KEYS = frozenset({"cam_K", "cam_kc", "proj_K", "proj_kc", "R", "T", "unit", "turntable_axis", "turntable_point",
                          *ERROR_KEYS})


#: The files a calibration is written as (OpenCV writes the format the suffix names).
CALIBRATION_SUFFIXES = (".yml", ".yaml", ".xml", ".json")


def check_calibration_out(path: Path, what: str = "--out") -> None:
    """Refuse, in one line before any work, a calibration file to write that is no such file's name, a folder, inside
    a session (a session's ``manifest.json`` was replaced, the session lost), or an existing file that is not a
    calibration this program would write back whole (a user's notes, another tool's file with entries of its own)."""
    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.store.session import refuse_inside_session

    if path.suffix.lower() not in CALIBRATION_SUFFIXES:
        raise InputError(f"{what} {path}: name a .yml, .yaml, .xml or .json file (OpenCV writes the format its suffix "
                         "names)")
    if path.is_dir():
        raise InputError(f"{what} {path} is a folder: name the calibration file to write")
    refuse_inside_session(path, what)
    if path.exists() or path.is_symlink():
        try:
            read_calibration(path)
            others = calibration_entries(path)[1]
        except (SssError, cv2.error, OSError):
            raise InputError(f"{what} {path} exists and is not a calibration file: choose another file, or move it "
                             "away") from None
        if others:
            raise InputError(f"{what} {path} exists and holds entries sss does not write ({', '.join(others[:6])}), "
                             "which would be lost: choose another file, or move it away")


def calibration_entries(path: Path | str) -> tuple[dict[str, float], list[str]]:
    """A calibration file's recorded RMS errors (:data:`ERROR_KEYS`, those it has) and its top-level entries that
    :func:`write_calibration` would not write back (another tool's names, notes), in one read."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        nodes = {name: storage.getNode(name) for name in ERROR_KEYS}
        errors = {name: float(node.real()) for name, node in nodes.items() if node.isReal() or node.isInt()}
        return errors, sorted(set(storage.root().keys()) - WRITTEN_KEYS)
    finally:
        storage.release()
