"""Camera-projector triangulation: calibration files as calibration tools write them, and 3D points from
correspondences, against the simulator's own surface and against points projected through distorting lenses."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.processing.triangulation import StereoCalibration, read_calibration, triangulate
from sssphase_core.sim import SimScene, rig_preset, stereo_calibration


def test_the_simulated_rigs_exact_correspondences_triangulate_to_its_surface():
    """The rig's calibration and the exact projector points give the scene's own surface points (camera frame, mm):
    the pixel-centre and pose conventions of both devices agree with OpenCV's."""
    rig = rig_preset("cpu")
    scene = SimScene("soap", rig=rig, view=1, n_views=4)
    xy = scene.proj_xy
    lit = np.isfinite(xy[..., 0])
    res = triangulate(stereo_calibration(rig), xy[..., 0], xy[..., 1], lit)
    assert res.behind == 0 and res.reprojection < 1e-3
    assert np.isnan(res.points[~lit]).all() and np.isfinite(res.points[lit]).all()
    error = np.linalg.norm(res.points[lit] - scene.points[lit], axis=-1)
    assert np.median(error) < 1e-4 and error.max() < 1e-3, error.max()


def _distorting_rig() -> StereoCalibration:
    base = stereo_calibration(rig_preset("cpu"))
    return StereoCalibration(base.camera_matrix, np.array([-0.21, 0.08, 0.001, -0.002, 0.0]), base.projector_matrix,
                             np.array([0.05, -0.02, 0.0, 0.0]), base.rotation, base.translation)


def test_points_seen_through_distorting_lenses_are_recovered():
    """Camera pixels (integer centres) back-projected through the camera's lens distortion to random depths, those
    points projected through the projector's distortion, and the pair triangulated: the points come back, so the
    distortion is undone on both sides (and ignoring it would have cost over half a millimetre)."""
    calib = _distorting_rig()
    h, w, step = 192, 256, 8
    rows, cols = (a.ravel() for a in np.mgrid[0:h:step, 0:w:step])
    depth = np.random.default_rng(0).uniform(350, 450, len(rows))
    direction = cv2.undistortPoints(np.column_stack([cols, rows]).astype(np.float64).reshape(-1, 1, 2),
                                    calib.camera_matrix, calib.camera_distortion).reshape(-1, 2)
    truth = np.column_stack([direction * depth[:, None], depth])
    proj, _ = cv2.projectPoints(truth, cv2.Rodrigues(calib.rotation)[0], calib.translation, calib.projector_matrix,
                                calib.projector_distortion)
    xp, yp = (np.full((h, w), np.nan, np.float32) for _ in range(2))
    mask = np.zeros((h, w), bool)
    xp[rows, cols], yp[rows, cols], mask[rows, cols] = proj[:, 0, 0], proj[:, 0, 1], True
    res = triangulate(calib, xp, yp, mask)
    assert res.behind == 0 and res.reprojection < 0.01
    error = np.linalg.norm(res.points[rows, cols] - truth, axis=-1)
    assert np.median(error) < 0.01 and error.max() < 0.1, (np.median(error), error.max())  # float32 projector points
    ideal = StereoCalibration(calib.camera_matrix, np.zeros(0), calib.projector_matrix, np.zeros(0), calib.rotation,
                              calib.translation)
    assert np.median(np.linalg.norm(triangulate(ideal, xp, yp, mask).points[rows, cols] - truth, axis=-1)) > 0.5


def test_a_calibration_of_another_pose_misses_and_one_that_puts_points_behind_counts_them():
    rig = rig_preset("cpu")
    scene = SimScene("soap", rig=rig, view=0, n_views=4)
    xy, lit = scene.proj_xy, np.isfinite(scene.proj_xy[..., 0])
    c = stereo_calibration(rig)
    inverted = StereoCalibration(c.camera_matrix, c.camera_distortion, c.projector_matrix, c.projector_distortion,
                                 c.rotation.T, -c.rotation.T @ c.translation)  # the camera's pose in the projector's frame
    assert triangulate(inverted, xy[..., 0], xy[..., 1], lit).reprojection > 0.75
    mirrored = StereoCalibration(c.camera_matrix, c.camera_distortion, c.projector_matrix, c.projector_distortion,
                                 c.rotation, -c.translation)
    res = triangulate(mirrored, xy[..., 0], xy[..., 1], lit)
    assert res.behind == lit.sum() and np.isnan(res.points).all()


def test_calibration_files_are_read_in_the_names_calibration_tools_write(tmp_path):
    """Moreno & Taubin's YAML (cam_K, cam_kc, proj_K, proj_kc, R, T), OpenCV-sample JSON (K1, D1, K2, D2) with a
    Rodrigues rotation, and XML; distortion left out is an ideal lens."""
    c = stereo_calibration(rig_preset("cpu"))
    yml = tmp_path / "calibration.yml"
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
    for name, value in (("cam_K", c.camera_matrix), ("cam_kc", np.zeros((1, 5))), ("proj_K", c.projector_matrix),
                        ("proj_kc", np.zeros((1, 5))), ("R", c.rotation), ("T", c.translation.reshape(3, 1))):
        fs.write(name, value)
    fs.write("stereo_error", 0.3)
    fs.release()
    js = tmp_path / "stereo.json"
    js.write_text(json.dumps({"K1": c.camera_matrix.tolist(), "D1": [[0, 0, 0, 0, 0]], "K2": c.projector_matrix.tolist(),
                              "R": cv2.Rodrigues(c.rotation)[0].ravel().tolist(), "T": c.translation.tolist()}))
    xml = tmp_path / "stereo.xml"
    fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_WRITE)
    for name, value in (("M1", c.camera_matrix), ("M2", c.projector_matrix), ("R", c.rotation), ("T", c.translation)):
        fs.write(name, value)
    fs.release()
    for path in (yml, js, xml):
        read = read_calibration(path)
        for field in ("camera_matrix", "projector_matrix", "rotation", "translation"):
            np.testing.assert_allclose(getattr(read, field), getattr(c, field), atol=1e-9, err_msg=f"{path.name} {field}")
        assert not read.camera_distortion.any() and read.baseline == pytest.approx(c.baseline)


@pytest.mark.parametrize(("content", "message"), [
    ("", "is empty"),
    ("cam_K: [1, 2\n", r"not an OpenCV calibration file \(YAML, XML or JSON\): line 1, Missing , between"),
    ('{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [1, 0, 0]}', "no camera matrix"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [[1, 0, 0], [0, 1, 0]], "T": [1, 0, 0]}', "rotation must be a 3x3 rotation matrix"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [1, 0, 0]}', "rotation must be a 3x3 rotation matrix"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [[1, 0, 0], [0, 1, 0], [0, 0]], "T": [1, 0, 0]}', "list of rows of different lengths"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": "eye", "T": [1, 0, 0]}', "R is not a matrix"),
    ('{"R": [' + ", ".join(["1"] * 100000) + "]}", "R holds 100000 values where a calibration's have at most 14"),
    ("%YAML:1.0\n---\nR: !!opencv-matrix\n   rows: 100000\n   cols: 100000\n   dt: d\n   data: [ 1. ]\n",
     "R is a 100000 x 100000 matrix where a calibration's have at most 14 values"),  # (OpenCV would allocate 80 GB)
    ("%YAML:1.0\n---\nR: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: q\n   data: [ 1. ]\n", "R is not a matrix"),
    ("%YAML:1.0\n---\nR:\n   a: 1\n", "R is not a matrix"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [0, 0, 0]}', "translation must be 3 finite values, not all zero"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1e200, 0, 0]}', r"not all zero and at most 1e\+09 long"),  # (NaN points, an empty PLY)
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1, 0, 0], "turntable_axis": [0, 1, 0], "turntable_point": [0, 0, 1e200]}',
     r"turntable_point must be 3 finite values, each at most 1e\+09"),
    ('{"K1": [[-600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1, 0, 0]}', "camera_matrix must be a finite 3x3 matrix with positive focal lengths"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "D1": [0.1, 0.2, 0.3], "K2": [[600, 0, 128], [0, 600, 96], '
     '[0, 0, 1]], "R": [0, 0, 0], "T": [1, 0, 0]}', "camera_distortion must be 4, 5, 8, 12, 14 finite coefficients"),
    pytest.param('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
                 '"R": [0, 0, 0], "T": [1, 0, 0], "unit": "' + "m" * 100 + '"}', "unit must be a length unit's short name",
                 id="a 100-letter unit"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1, 0, 0], "unit": 3}', "unit must be a length unit's short name"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1, 0, 0], "turntable_axis": [0, 1, 0]}', "a turntable needs both its turntable_axis and a turntable_point"),
    ('{"K1": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], "K2": [[600, 0, 128], [0, 600, 96], [0, 0, 1]], '
     '"R": [0, 0, 0], "T": [1, 0, 0], "turntable_axis": [0, 2, 0], "turntable_point": [0, 0, 400]}',
     "turntable_axis must be a unit vector of 3 values"),
])
def test_a_calibration_file_that_cannot_be_used_is_refused_naming_the_file_and_the_problem(tmp_path, content, message):
    path = tmp_path / ("c.json" if content.startswith("{") else "c.yml")
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        read_calibration(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)
    with pytest.raises(InputError, match="no such file"):
        read_calibration(tmp_path / "missing.yml")


def test_the_shaded_surface_follows_the_normals_and_leaves_holes_and_degenerate_points_out():
    """A plane facing the light is lit fully, one turned away not at all; a sphere is brightest where its normal
    meets the light; a hole takes its neighbours with it, and points that all coincide (no normal) are left out,
    without a warning."""
    from sssphase_core.processing.triangulation import shaded

    rows, cols = np.mgrid[0:40, 0:50].astype(np.float64)
    light = np.array([-0.5, -0.6, -1.0]) / np.linalg.norm([-0.5, -0.6, -1.0])
    facing = np.stack([cols, rows, 400 + 0 * cols], -1)  # a plane at z = 400, its normal toward the camera
    lit = shaded(facing)
    inner = lit[1:-1, 1:-1]
    assert np.isnan(lit[0]).all() and np.isnan(lit[:, -1]).all()  # no central difference at the border
    np.testing.assert_allclose(inner, -light[2], atol=1e-6)  # n = (0, 0, -1)
    assert np.nanmax(shaded(facing, light=(0, 0, 1))) == 0  # lit from behind: dark
    # a sphere of radius 30 at z = 200: its brightest point is where the normal is the light direction
    u, v = np.mgrid[-1:1:301j, -1:1:301j]
    inside = u**2 + v**2 < 0.95
    z = 200 - 30 * np.sqrt(np.clip(1 - u**2 - v**2, 0, None))
    sphere = np.where(inside[..., None], np.stack([30 * u, 30 * v, z], -1), np.nan)
    s = shaded(sphere)
    peak = np.unravel_index(np.nanargmax(s), s.shape)
    np.testing.assert_allclose([u[peak], v[peak]], light[:2], atol=0.02)  # (-0.5, -0.6)/|l|: up and left
    assert np.nanmax(s) > 0.999 and np.isnan(s[~inside]).all()
    holed = facing.copy()
    holed[20, 25] = np.nan
    hole = np.isnan(shaded(holed))
    assert hole[19:22, 24:27].sum() == 5 and hole[1:-1, 1:-1].sum() == 5  # the pixel and its four neighbours
    with np.errstate(all="raise"):
        flat = shaded(np.full((5, 5, 3), 7.0))
    assert np.isnan(flat).all()


def test_a_calibration_written_with_ideal_lenses_and_a_turntable_reads_back_the_same(tmp_path):
    """No distortion vector is written for an ideal lens (OpenCV wrote an empty one as a 1 x 0 matrix, which was read
    as a damaged file); such a matrix from another tool reads as an ideal lens too."""
    from sssphase_core.capture.stereo_calibration import write_calibration

    c = stereo_calibration(rig_preset("cpu"))
    for suffix in (".yml", ".xml", ".json"):
        path = write_calibration(tmp_path / f"c{suffix}", c)
        got = read_calibration(path)
        assert got.camera_distortion.size == 0 and got.unit == "mm"
        np.testing.assert_allclose(got.turntable_axis, c.turntable_axis)
        np.testing.assert_allclose(got.turntable_point, c.turntable_point)
    fs = cv2.FileStorage(str(tmp_path / "empty.yml"), cv2.FILE_STORAGE_WRITE)
    for name, value in (("cam_K", c.camera_matrix), ("cam_kc", np.zeros((1, 0))), ("proj_K", c.projector_matrix),
                        ("R", c.rotation), ("T", c.translation)):
        fs.write(name, value)
    fs.release()
    assert read_calibration(tmp_path / "empty.yml").camera_distortion.size == 0


def test_a_turntable_axis_is_recovered_from_turned_points_whichever_way_and_however_far_it_turns():
    """`fit_axis` on a board's corners turned about a tilted axis off the origin: the direction within 0.2 degrees and
    the line within 0.3 mm under 0.05 mm of noise, each view's own turn; recorded angles of the other sense flip the
    direction (they must turn about it right-handed); angles across 360 (350 and 10) and a half turn (180, where a
    single view's rotation axis has no sign) work; views spanning a few degrees are refused."""
    from sssphase_core.capture.turntable_calibration import fit_axis
    from sssphase_core.errors import DataError
    from sssphase_core.processing.triangulation import turned

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(6) * 9.0, np.arange(4) * 9.0, [0.0]), -1).reshape(-1, 3)
    board = grid @ cv2.Rodrigues(np.array([0.3, 0.2, 0.1]))[0].T + [20.0, -15.0, 380.0]
    axis = np.array([0.1, 1.0, -0.05]) / np.linalg.norm([0.1, 1.0, -0.05])
    point = np.array([5.0, 0.0, 400.0])

    def views(angles):
        return {i: turned(board, axis, point, a) + rng.normal(0, 0.05, board.shape) for i, a in enumerate(angles)}

    for angles in ([0, 25, -40, 70], [0, 350, 10, 30], [0, 90, 180]):
        got_axis, got_point, turns = fit_axis(views(angles), dict(enumerate(angles)))
        assert np.degrees(np.arccos(got_axis @ axis)) < 0.2, angles
        offset = got_point - point
        assert np.linalg.norm(offset - axis * (offset @ axis)) < 0.3, angles
        want = [((a - angles[0] + 180) % 360) - 180 for a in angles[1:]]
        np.testing.assert_allclose([abs(t) for t in turns.values()], [abs(w) for w in want], atol=0.2)
    flipped, _, _ = fit_axis(views([0, 25, -40]), {0: 0, 1: -25, 2: 40})
    assert flipped @ axis < -0.999
    with pytest.raises(DataError, match="span 6.0 degrees of the turntable"):
        fit_axis(views([0, 3, 6]), {0: 0, 1: 3, 2: 6})
