"""`sss calibrate projector`: the projector's response is recovered from a grey ramp captured through the
daemon, and patterns made for it bring the correspondence error back to the nominal figure."""

from __future__ import annotations

import os
import re
import tomllib

import numpy as np
import pytest
from sss_process import run_sss

from sssphase_core.capture.calibration import RAMP_LEVELS, fit_response, rig_file_with_response
from sssphase_core.errors import DataError, InputError


def _ramp(gammas, black, *, noise=0.0, seed=0, levels=RAMP_LEVELS):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 0.9, size=(40, 50, 3))
    v = np.asarray(levels)[:, None, None, None]
    light = black + (1 - black) * v ** np.asarray(gammas)
    return albedo * light + rng.normal(0, noise, size=(len(levels), 40, 50, 3))


@pytest.mark.parametrize(("gammas", "black"), [((2.2, 2.2, 2.2), 0.002), ((1.8, 2.2, 2.6), 0.01), ((1.0, 1.0, 1.0), 0.0)])
def test_the_fit_recovers_gamma_and_black_per_colour(gammas, black):
    fit = fit_response(RAMP_LEVELS, _ramp(gammas, black, noise=1e-3))
    np.testing.assert_allclose(fit.gamma_rgb, gammas, atol=0.02)
    np.testing.assert_allclose(fit.black_rgb, black, atol=2e-3)
    assert fit.rms < 0.01 and fit.gamma == pytest.approx(np.mean(gammas), abs=0.02)


def test_a_response_that_is_no_power_law_shows_in_the_rms():
    images = _ramp((2.2, 2.2, 2.2), 0.0)
    v = np.asarray(RAMP_LEVELS)[:, None, None, None]
    s_curve = np.where(v < 0.5, 2 * v**2, 1 - 2 * (1 - v) ** 2)  # not v**gamma
    fit = fit_response(RAMP_LEVELS, images / (v ** 2.2 + 1e-12) * s_curve)
    assert fit.rms > 0.02


def test_a_dark_or_clipped_view_is_one_clear_error():
    with pytest.raises(DataError, match="well exposed"):
        fit_response(RAMP_LEVELS, _ramp((2.2,) * 3, 0.0) * 10)  # every white pixel clipped



def test_a_ramp_the_camera_does_not_see_is_refused_and_nothing_is_written(tmp_path, monkeypatch):
    """A camera that did not see the projector (the Basler emulator's own test image) fitted gamma 1.000 and black
    0.5000, the clip limit, and the rig file written with them was refused by `sss capture` (black must be < 0.5)."""
    from sssphase_core.capture import calibration

    unseen = 0.5 + 0.1 * _ramp((1.0,) * 3, 0.0)  # a bright scene that drifts a little from frame to frame
    with pytest.raises(DataError, match=r"the ramp's black frame reads 0\.\d\d of its white frame .* the camera does "
                                        r"not see the projector's ramp, or ambient light outweighs it"):
        fit_response(RAMP_LEVELS, unseen)
    with pytest.raises(DataError, match=r"the fitted gamma 7\.00 \(R\) is outside \[0\.3, 5\]"):
        fit_response(RAMP_LEVELS, _ramp((7.0,) * 3, 0.0))
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "uvc:0"\nprojector = "hdmi:1"\n')
    monkeypatch.setattr(calibration, "capture_ramp", lambda *a, **k: unseen)
    with pytest.raises(DataError, match="does not see the projector's ramp"):
        calibration.calibrate_projector(None, calibration.CalibrationRequest(rig=rig))
    assert rig.read_text() == '[devices]\ncamera = "uvc:0"\nprojector = "hdmi:1"\n'  # nothing written


@pytest.mark.parametrize("black", [0.2, 0.45, 0.49, 0.4999999, 0.6])
def test_a_high_black_is_either_refused_or_written_as_capture_reads_it(black, tmp_path):
    """Whatever the projector's black (ambient light adds to it), the fit never writes a rig file that `sss capture`
    refuses: it is refused by the fit, with one line, or read back as fitted."""
    from sssphase_core.capture.plan import RigSpec

    try:
        fit = fit_response(RAMP_LEVELS, _ramp((2.2,) * 3, black))
    except DataError as exc:
        assert black >= 0.49 and "does not see the projector's ramp" in str(exc)
        return
    rig = tmp_path / "rig.toml"
    rig.write_text(rig_file_with_response('[devices]\ncamera = "uvc:0"\nprojector = "hdmi:1"\n', fit))
    assert RigSpec.from_toml(rig).projector_black == pytest.approx(black, abs=1e-3)


def test_the_rig_file_keeps_its_comments_and_gets_one_projector_table():
    text = "# my rig\n[devices]\ncamera = \"uvc:0\"  # the left camera\nprojector = \"hdmi:1\"\n\n[projector]\ngamma = 9\n\n[processing]\npatch = 48\n"
    fit = fit_response(RAMP_LEVELS, _ramp((1.9,) * 3, 0.003))
    once = rig_file_with_response(text, fit)
    twice = rig_file_with_response(once, fit)
    assert "# the left camera" in twice and twice.count("[projector]") == 1
    cfg = tomllib.loads(twice)
    assert cfg["processing"]["patch"] == 48 and cfg["projector"]["gamma"] == pytest.approx(1.9, abs=0.02)


@pytest.mark.slow
def test_calibrating_a_linear_projector_restores_the_nominal_correspondence_error(sim_daemon, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text("# a DLP projector in linear mode\n[devices]\ncamera = \"sim:camera0\"\nprojector = \"sim:projector0\"\n\n"
                   "[options]\nprojector_gamma = 1.0\nprojector_black = 0.004\n")
    res = run_sss(["calibrate", "projector", "--rig", str(rig), "--check"], timeout=600, env={**os.environ, "COLUMNS": "200"})
    assert res.returncode == 0, res.stdout + res.stderr
    cfg = tomllib.loads(rig.read_text())
    assert cfg["projector"]["gamma"] == pytest.approx(1.0, abs=0.02) and cfg["projector"]["black"] == pytest.approx(0.004, abs=1e-3)
    assert cfg["options"]["projector_gamma"] == 1.0 and "# a DLP projector" in rig.read_text()
    errors = [float(e) for e in re.findall(r"median ([0-9.]+) projector px", res.stdout)]
    wrong, fitted, nominal = errors
    assert wrong > fitted + 0.02 and abs(fitted - nominal) < 0.01, res.stdout
    from sssphase_core.capture import CaptureRequest, RigSpec, run_capture

    session = run_capture(sim_daemon, CaptureRequest("leaf", views=1, out=tmp_path / "s"), RigSpec.from_toml(rig))
    assert session.manifest["plan"]["gamma"] == pytest.approx(cfg["projector"]["gamma"])


# --- `sss calibrate stereo`: the camera and the projector as a stereo pair, from a session of a checkerboard ---------


@pytest.fixture(scope="module")
def board_session(sim_daemon, tmp_path_factory):
    """The simulated checkerboard in its 12 hand-held poses, captured through the daemon (the user's path)."""
    from sssphase_core.capture import CaptureRequest, run_capture

    return run_capture(sim_daemon, CaptureRequest("calibration_board", views=12, out=tmp_path_factory.mktemp("board")))


def test_a_checkerboard_session_calibrates_the_rig_and_its_points_land_on_the_surface(board_session, tmp_path):
    """`sss calibrate stereo` recovers the simulated rig's focal lengths to 2%, principal points to 5 px, the
    projector's pose to half a degree and its baseline to 3%, and `sss geometry --calibration` with the file it wrote
    puts the board's points within 2% of their distance from the exact surface."""
    import cv2

    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.sim import rig_preset, stereo_calibration

    out = tmp_path / "calibration.yml"
    res = run_sss(["calibrate", "stereo", str(board_session.path), "--board", "6x4", "--square", "9", "--out", str(out)],
                  timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "calibrated from 12 views" in res.stdout and f"wrote {out}" in res.stdout
    assert "against the simulated rig's exact calibration: camera focal length" in res.stdout
    rms = [float(v) for v in re.findall(r"(\d+\.\d+) px", res.stdout)[:3]]
    assert all(0 < v < 1 for v in rms), res.stdout  # camera, projector, the pair
    got, exact = read_calibration(out), stereo_calibration(rig_preset("cpu"))
    assert got.unit == "mm" and "baseline 149" in res.stdout and re.search(r"baseline \d+\.\d mm", res.stdout)
    for k_got, k_exact in ((got.camera_matrix, exact.camera_matrix), (got.projector_matrix, exact.projector_matrix)):
        assert k_got[0, 0] == pytest.approx(k_exact[0, 0], rel=0.02) and k_got[0, 0] == pytest.approx(k_got[1, 1])
        assert np.abs(k_got[:2, 2] - k_exact[:2, 2]).max() < 5
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(got.rotation @ exact.rotation.T)[0])) < 0.5
    assert got.baseline == pytest.approx(exact.baseline, rel=0.03)
    res = run_sss(["geometry", str(board_session.path), "--views", "0", "--calibration", str(out), "--out",
                   str(tmp_path / "g")], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    error, bias = (float(v) for v in re.search(r"for geometry (\d+\.\d+) \(depth bias ([-+]\d+\.\d+)\) mm", res.stdout).groups())
    assert error < 8 and abs(bias) < 8, res.stdout  # mm at 400 mm: the calibration's own error, not the decoding's
    assert "the calibration's unit" not in res.stdout  # the file says mm


@pytest.mark.parametrize(("args", "expected"), [
    (["--board", "9x6", "--square", "9"], r"found in 0 view\(s\) where a calibration needs at least 3 \(no 9x6 board "
                                          r"found in the white capture: views 0, 1, 2, .*\); check --board"),
    (["--board", "6x4", "--square", "9", "--views", "0,1"], "found in 2 view.* needs at least 3: capture more poses"),
    (["--board", "6", "--square", "9"], "--board must be COLSxROWS inner corners"),
    (["--board", "6x4", "--square", "0"], "--square must be the board's square side, a positive length"),
    (["--board", "6x4", "--square", "nan"], "--square must be the board's square side, a positive length"),
    (["--board", "6x4", "--square", "1e300"], r"a positive length in --unit \(mm\), from 1e-06 to 1e\+06, got 1e\+300"),
    (["--board", "6x4", "--square", "9", "--out", "calibration.txt"], "name a .yml, .yaml, .xml or .json file"),
    (["--board", "6x4", "--square", "9", "--unit", "m m"], "--unit must be a length unit's short name"),
    (["--board", "6x4", "--square", "9", "--unit", "px"], r"--unit must be one of mm, cm, m, in, um, µm \(the unit of "
                                                         r"--square\), got 'px'"),
    (["--board", "6x4", "--square", "9", "--lens", "fisheye"], "--lens must be one of k1, radial, full"),
])
def test_a_stereo_calibration_that_cannot_be_made_is_one_line_and_writes_nothing(board_session, tmp_path, args, expected):
    out = ["--out", str(tmp_path / "c.yml")] if "--out" not in args else []
    res = run_sss(["calibrate", "stereo", str(board_session.path), *args, *out], cwd=tmp_path, timeout=120)
    assert res.returncode != 0 and re.search(expected, res.stderr), res.stderr
    assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


def test_a_calibration_is_never_written_over_a_session_or_a_file_it_is_not(exact_stereo_file, tmp_path):
    """`sss calibrate stereo --out SESSION/manifest.json` replaced the session's manifest (the session was lost), and
    `--out notes.yml` a user's notes, without a word (`calibrate turntable --out` too); a calibration it wrote before
    is replaced as ever."""
    import shutil

    from sssphase_core.capture.stereo_calibration import check_calibration_out
    from sssphase_core.store.session import Session

    session = Session.create(tmp_path / "s", "board")
    with pytest.raises(InputError, match=r"--out .*manifest.json would write into the session"):
        check_calibration_out(session.path / "manifest.json")
    notes = tmp_path / "notes.yml"
    notes.write_text('my_notes: "precious"\n')
    with pytest.raises(InputError, match=r"--out .*notes.yml exists and is not a calibration file"):
        check_calibration_out(notes)
    theirs = tmp_path / "theirs.yml"
    shutil.copy(exact_stereo_file, theirs)
    with open(theirs, "a") as f:
        f.write("image_width: 256\n")
    with pytest.raises(InputError, match=r"holds entries sss does not write \(image_width\), which would be lost"):
        check_calibration_out(theirs, "--calibration")
    check_calibration_out(exact_stereo_file)  # one of ours: replaced
    check_calibration_out(tmp_path / "new.json")
    res = run_sss(["calibrate", "turntable", str(session.path), "--board", "6x4", "--calibration",
                   str(exact_stereo_file), "--out", str(notes)], timeout=120)
    assert res.returncode == 2 and "notes.yml exists and is not a calibration file" in res.stderr, res.stderr
    assert notes.read_text() == 'my_notes: "precious"\n'


def test_a_calibration_in_another_unit_is_compared_with_the_simulated_rig_in_that_unit(board_session):
    """A correct calibration made with `--unit cm` was reported "baseline -90.1%" and its axis "359.52 mm from the true
    one": the simulated rig's lengths (mm) were compared with its numbers as they stood."""
    from dataclasses import replace

    from sssphase_core.capture.stereo_calibration import against_simulated_rig
    from sssphase_core.capture.turntable_calibration import against_simulated_turntable
    from sssphase_core.sim import session_rig_calibration

    exact = session_rig_calibration(board_session.manifest["rig"])
    for unit, per_mm in (("mm", 1.0), ("cm", 0.1), ("m", 1e-3), ("in", 1 / 25.4)):
        mine = replace(exact, translation=exact.translation * per_mm, turntable_point=exact.turntable_point * per_mm,
                       unit=unit)
        assert "its baseline +0.0%" in against_simulated_rig(board_session, mine), unit
        assert "passing 0.00 mm from the true one" in against_simulated_turntable(board_session, mine), unit
    odd = replace(exact, unit="parsecs")
    assert "its baseline not compared (the unit 'parsecs' is none of mm, cm, m, in" in against_simulated_rig(board_session, odd)


def test_each_corners_projector_point_is_read_to_a_tenth_of_a_pixel(board_session):
    """The local homographies give each camera corner's projector point within a tenth of a projector pixel of the
    simulator's exact one (interpolated at the corner), where the nearest decoded pixel is off by up to half a pixel's
    worth of projector coordinates."""
    import cv2

    from sssphase_core.capture.stereo_calibration import board_corners, projector_corners

    s = board_session
    white, mask = np.asarray(s.load(0, "white"), np.float32), np.asarray(s.load(0, "corr/mask")).astype(bool)
    xp, yp = (np.asarray(s.load(0, name), np.float32) for name in ("corr/xp", "corr/yp"))
    camera = board_corners(white, mask, (6, 4))
    assert camera is not None and camera.shape == (24, 2)
    got = projector_corners(camera, xp, yp, mask, 6)
    assert not isinstance(got, str), got
    gt = np.asarray(s.load(0, "gt/proj_xy"), np.float32)
    exact = np.array([[cv2.getRectSubPix(np.ascontiguousarray(gt[..., k]), (1, 1), (float(u), float(v)))[0, 0]
                       for k in (0, 1)] for u, v in camera])
    assert np.median(np.linalg.norm(got - exact, axis=1)) < 0.1
    nearest = np.column_stack([xp[np.round(camera[:, 1]).astype(int), np.round(camera[:, 0]).astype(int)],
                               yp[np.round(camera[:, 1]).astype(int), np.round(camera[:, 0]).astype(int)]])
    assert np.median(np.linalg.norm(nearest - exact, axis=1)) > 2 * np.median(np.linalg.norm(got - exact, axis=1))


def test_poses_that_do_not_pin_the_lenses_down_are_warned_about_or_refused(board_session, tmp_path):
    """Three mild poses calibrate with a warning naming the uncertainty (the focal length came out 6% off here);
    one pose three times gives a focal length no lens has, refused with nothing written."""
    from sssphase_core.capture.stereo_calibration import calibrate_stereo
    from sssphase_core.errors import DataError
    from sssphase_core.processing.triangulation import read_calibration

    res = run_sss(["calibrate", "stereo", str(board_session.path), "--board", "6x4", "--square", "9", "--views", "0,1,2",
                   "--out", str(tmp_path / "c.json")], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert re.search(r"warning: the poses leave the calibration uncertain \(camera: focal length \+-\d+\.\d%", res.stdout)
    assert "tilted and turned by 30 to 45 degrees" in res.stdout
    assert (tmp_path / "c.json").read_text().lstrip().startswith("{")  # the format its suffix names
    assert read_calibration(tmp_path / "c.json").camera_matrix[0, 0] > 0
    with pytest.raises(DataError, match="a field of view no lens of a 256x192 camera has"):
        calibrate_stereo(board_session, (6, 4), 9.0, [0, 0, 0])


def test_the_lens_model_frees_the_terms_it_names_and_more_terms_cost_accuracy_on_a_small_board(board_session):
    """`--lens radial` estimates k1, k2, k3 and keeps square pixels and no tangential terms; `--lens full` frees all
    five and the focal lengths apart. The simulated lenses have no distortion, so every freed term only adds
    variance: on its 12 small poses radial stays within 2% and 5 px, full lets the projector's principal point go
    tens of pixels astray (what docs/benchmarks/calibration.md reports)."""
    from sssphase_core.capture.stereo_calibration import calibrate_stereo
    from sssphase_core.sim import rig_preset, stereo_calibration

    exact = stereo_calibration(rig_preset("cpu"))
    got = {lens: calibrate_stereo(board_session, (6, 4), 9.0, lens=lens).calibration for lens in ("k1", "radial", "full")}
    for lens, c in got.items():
        d = c.projector_distortion
        assert (d[1] != 0) == (lens != "k1") and (d[2:4] != 0).any() == (lens == "full") and (d[4] != 0) == (lens != "k1"), (lens, d)
        assert (c.camera_matrix[0, 0] == c.camera_matrix[1, 1]) == (lens != "full")
    for lens in ("k1", "radial"):
        k = got[lens].projector_matrix
        assert k[1, 1] == pytest.approx(exact.projector_matrix[1, 1], rel=0.02) and np.abs(k[:2, 2] - exact.projector_matrix[:2, 2]).max() < 5
    assert np.abs(got["full"].projector_matrix[:2, 2] - exact.projector_matrix[:2, 2]).max() > 10


@pytest.fixture(scope="module")
def turntable_session(sim_daemon, tmp_path_factory):
    """The simulated checkerboard standing on the turntable, 12 steps of 30 degrees (the board is seen in 3)."""
    from sssphase_core.capture import CaptureRequest, run_capture

    return run_capture(sim_daemon, CaptureRequest("turntable_board", views=12, out=tmp_path_factory.mktemp("turntable")))


@pytest.fixture(scope="module")
def exact_stereo_file(tmp_path_factory):
    """The simulated rig's exact camera-projector calibration as a file, without its turntable."""
    from dataclasses import replace

    from sssphase_core.capture.stereo_calibration import write_calibration
    from sssphase_core.sim import rig_preset, stereo_calibration

    exact = replace(stereo_calibration(rig_preset("cpu")), turntable_axis=None, turntable_point=None)
    return write_calibration(tmp_path_factory.mktemp("exact") / "exact.yml", exact, {"stereo_error": 0.25})


def test_the_turntable_axis_is_found_from_a_board_standing_on_it_and_added_to_the_calibration(turntable_session,
                                                                                             exact_stereo_file, tmp_path):
    """With the rig's exact stereo calibration the axis comes out within 0.3 degrees and 0.5 mm of the simulator's,
    the board's turns within 0.5 degrees of the recorded angles and its squares within 1% of 9 mm; the file written
    keeps the calibration and its recorded errors and reads back with the axis."""
    from sssphase_core.capture.stereo_calibration import calibration_entries
    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.sim import rig_preset, stereo_calibration

    out = tmp_path / "with_turntable.yml"
    res = run_sss(["calibrate", "turntable", str(turntable_session.path), "--board", "6x4", "--square", "9",
                   "--calibration", str(exact_stereo_file), "--out", str(out)], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert re.search(r"left out: views [\d, ]+: no 6x4 board found in the white capture", res.stdout)
    assert "turntable axis from 3 views (0, 1, 11)" in res.stdout and "warning" not in res.stdout, res.stdout
    turn = float(re.search(r"differ from the recorded angles by at most (\d+\.\d+) degrees", res.stdout).group(1))
    side = float(re.search(r"the board's squares measure (\d+\.\d+) mm", res.stdout).group(1))
    assert turn < 0.5 and side == pytest.approx(9, rel=0.01), res.stdout
    got, exact = read_calibration(out), stereo_calibration(rig_preset("cpu"))
    assert np.degrees(np.arccos(abs(got.turntable_axis @ exact.turntable_axis))) < 0.3
    offset = exact.turntable_point - got.turntable_point
    assert np.linalg.norm(offset - exact.turntable_axis * (offset @ exact.turntable_axis)) < 0.5
    np.testing.assert_allclose(got.camera_matrix, exact.camera_matrix)
    assert got.unit == "mm" and calibration_entries(out)[0] == {"stereo_error": 0.25}
    assert read_calibration(exact_stereo_file).turntable_axis is None  # --out: the given file as it was


def test_a_board_that_does_not_turn_about_one_axis_is_warned_of_and_too_few_views_refused(board_session,
                                                                                        turntable_session,
                                                                                        exact_stereo_file, tmp_path):
    """The hand-held board's poses (recorded at the angles 30 degrees apart a turntable would have) are no turns
    about one axis: the command says so; two views are refused with nothing written."""
    out = tmp_path / "t.yml"
    res = run_sss(["calibrate", "turntable", str(board_session.path), "--board", "6x4", "--calibration",
                   str(exact_stereo_file), "--out", str(out)], timeout=120)
    assert res.returncode == 0 and "warning: a view's board turned" in res.stdout, res.stdout + res.stderr
    res = run_sss(["calibrate", "turntable", str(turntable_session.path), "--board", "6x4", "--views", "0,1",
                   "--calibration", str(exact_stereo_file), "--out", str(tmp_path / "u.yml")], timeout=120)
    assert res.returncode != 0 and "found in 2 view(s) where a calibration needs at least 3" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "u.yml").exists()


@pytest.fixture(scope="module")
def soap_turntable(sim_daemon, tmp_path_factory):
    """The soap on the turntable, four views 90 degrees apart."""
    from sssphase_core.capture import CaptureRequest, run_capture

    return run_capture(sim_daemon, CaptureRequest("soap", views=4, out=tmp_path_factory.mktemp("soap")))


def test_geometry_merges_a_turntable_sessions_views_into_one_cloud(soap_turntable, exact_stereo_file, tmp_path):
    """Two views of the soap, 180 degrees apart, turned back by the simulated turntable's axis: one cloud whose views
    lie on the exact surface of the turntable at 0 degrees, cropped to a cylinder about the axis with --crop-radius;
    a calibration without an axis keeps the views apart and says how to get one."""
    import trimesh

    s = soap_turntable
    res = run_sss(["geometry", str(s.path), "--backend", "exact", "--views", "0,2", "--out", str(tmp_path / "g"),
                   "--mesh"], timeout=180)
    assert res.returncode == 0, res.stdout + res.stderr
    mesh = trimesh.load(tmp_path / "g" / "soap" / "view_000" / "mesh.ply", process=False)  # each view's points joined
    faces = int(re.search(r"mesh\.ply: (\d+) triangles joining neighbouring pixels", res.stdout).group(1))
    assert len(mesh.faces) == faces > 1000 and (np.einsum("fc,fc->f", mesh.face_normals, mesh.triangles_center) < 0).all()
    both = trimesh.load(tmp_path / "g" / "soap" / "mesh_merged.ply", process=False)  # the views' meshes turned into one
    view_2 = trimesh.load(tmp_path / "g" / "soap" / "view_002" / "mesh.ply", process=False)
    assert len(both.faces) == len(mesh.faces) + len(view_2.faces) and f"mesh_merged.ply: their meshes, {len(both.faces)} triangles" in res.stdout
    m = re.search(r"wrote (\S+points_merged\.ply): (\d+) points of views 0, 2 turned into the frame of the turntable "
                  r"at 0 degrees \(mm\).*against the exact surface: median (\d+\.\d+) mm", res.stdout)
    assert m and float(m.group(3)) < 0.2, res.stdout
    cloud = trimesh.load(m.group(1))
    singles = [trimesh.load(tmp_path / "g" / "soap" / f"view_00{v}" / "points.ply") for v in (0, 2)]
    assert len(cloud.vertices) == int(m.group(2)) == sum(len(c.vertices) for c in singles)
    # view 2 (180 degrees) turned back: its points face the other way, on the far side of the axis from view 0's
    centre = np.array([0.0, 0.0, 400.0])
    assert (np.median(singles[1].vertices[:, 2]) < 400) and np.median(cloud.vertices[len(singles[0].vertices):, 2]) > 400
    assert np.median(np.asarray(cloud.vertices[: len(singles[0].vertices)]), 0) == pytest.approx(
        np.median(singles[0].vertices, 0), abs=1e-3)  # view 0 is where it was
    assert np.linalg.norm(np.median(cloud.vertices, 0)[[0, 2]] - centre[[0, 2]]) < 15  # around the axis
    # cropped to 30 mm about the axis, and a calibration without an axis: the merge's own functions, in process
    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.relight.merged_points import merge_note, merge_views, merged_line, recorded_angles
    from sssphase_core.sim import session_rig_calibration

    exact = session_rig_calibration(s.manifest["rig"])
    clouds = {v: (np.load(tmp_path / "g" / "soap" / f"view_00{v}" / "correspondence_for_geometry.npz")["points"],
                  np.asarray(s.load(v, "white"))) for v in (0, 2)}
    cropped = merge_views(s, clouds, exact, tmp_path / "c", crop_radius=30.0)
    assert "(mm, within 30 of its axis)" in merged_line(cropped, "mm")
    kept = np.asarray(trimesh.load(cropped.path).vertices)
    assert 0 < len(kept) == cropped.n_points < len(cloud.vertices) and np.hypot(kept[:, 0], kept[:, 2] - 400).max() <= 30 + 1e-3
    no_axis = read_calibration(exact_stereo_file)
    assert "the calibration has no turntable axis (`sss calibrate turntable` adds one" in merge_note(
        no_axis, [0, 2], recorded_angles(s, [0, 2]))
    assert merge_views(s, clouds, no_axis, tmp_path / "h") is None and not (tmp_path / "h").exists()


def test_the_views_3d_points_merge_a_turntable_session_and_crop_about_its_axis(soap_turntable):
    """`sss view`'s 3D points of a turntable session: every view's decoded points turned into the frame of the
    turntable at 0 degrees about the simulated rig's axis (the merged cloud lies around the axis, not in front of the
    camera), and with a crop radius only those within it; a radius without a turntable axis is one line."""
    pytest.importorskip("starlette")
    import base64
    from dataclasses import replace

    from sssphase_core.sim import session_rig_calibration
    from sssphase_view.app import ViewState, session_points
    from sssphase_view.live import LiveRig

    s = soap_turntable
    state = ViewState(token="t", out=s.path.parent / "view_out", sessions=s.path.parent, live=LiveRig())
    whole = session_points(state, s.name, 1)
    xyz = np.frombuffer(base64.b64decode(whole["xyz"]), np.float32).reshape(-1, 3)
    assert whole["views"] == [0, 1, 2, 3] and "views 0, 1, 2, 3 merged by the turntable's axis" in whole["which"]
    around = np.hypot(xyz[:, 0], xyz[:, 2] - 400)  # the simulated turntable turns about x = 0, z = 400 mm
    assert np.median(around) < 40 and np.median(xyz[:, 2]) == pytest.approx(400, abs=10)
    cropped = session_points(state, s.name, 1, radius=20.0)
    kept = np.frombuffer(base64.b64decode(cropped["xyz"]), np.float32).reshape(-1, 3)
    assert 0 < cropped["count"] < whole["count"] and np.hypot(kept[:, 0], kept[:, 2] - 400).max() <= 20 + 1e-3
    assert "within 20 of its axis" in cropped["which"]
    with pytest.raises(InputError, match="the crop radius must be a positive distance"):
        session_points(state, s.name, 1, radius=-5.0)
    state.calibration = replace(session_rig_calibration(s.manifest["rig"]), turntable_axis=None, turntable_point=None)
    with pytest.raises(InputError, match="a crop radius needs the calibration's turntable axis"):
        session_points(state, s.name, 1, radius=20.0)


def test_geometry_refines_an_axis_that_is_off_from_the_views_overlaps(soap_turntable, tmp_path):
    """The soap's views 90 degrees apart, merged about an axis turned 3 degrees and moved 8 mm: --refine-axis brings
    the merge back onto the exact surface and writes the calibration with the refined axis (its recorded errors kept);
    without it, one line says the views agree poorly. Views half a turn apart do not pin an axis down: it is kept."""
    from dataclasses import replace

    import cv2

    from sssphase_core.capture.stereo_calibration import calibration_entries, write_calibration
    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.relight.merged_points import merge_views, refinement_lines
    from sssphase_core.sim import session_rig_calibration

    s = soap_turntable
    exact = session_rig_calibration(s.manifest["rig"])
    axis = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(3.0)]))[0] @ exact.turntable_axis
    wrong = write_calibration(tmp_path / "wrong.yml", replace(exact, turntable_axis=axis,
                              turntable_point=exact.turntable_point + [8.0, 0.0, 0.0]), {"stereo_error": 0.25})
    res = run_sss(["geometry", str(s.path), "--backend", "exact", "--views", "0,1,2", "--calibration", str(wrong),
                   "--out", str(tmp_path / "g"), "--refine-axis"], timeout=180)
    assert res.returncode == 0, res.stdout + res.stderr
    assert re.search(r"axis refined from the views' overlaps \(\d+ point pairs, \d+ rounds\): turned 3\.\d+ degrees "
                     r"and moved 8\.\d+ mm from the calibration's", res.stdout), res.stdout
    near = float(re.search(r"against the exact surface: median (\d+\.\d+) mm", res.stdout).group(1))
    clouds = {v: (np.load(tmp_path / "g" / "soap" / f"view_00{v}" / "correspondence_for_geometry.npz")["points"],
                  np.asarray(s.load(v, "white"))) for v in (0, 1, 2)}
    plain = merge_views(s, clouds, read_calibration(wrong), tmp_path / "p", exact)  # not refined: said, and off
    assert "--refine-axis fits it to the views' overlaps" in " ".join(refinement_lines(plain, "mm"))
    assert np.median(list(plain.exact.values())) > 5 and near < 0.5, (plain.exact, near)
    metres = replace(exact, turntable_point=exact.turntable_point / 1000)  # the point in metres, in a file of mm
    apart = merge_views(s, clouds, metres, tmp_path / "m")  # four copies of the soap far apart: merged without a word
    assert "warning: no two neighbouring views overlap" in " ".join(refinement_lines(apart, "mm"))
    with pytest.raises(InputError, match=r"--crop-radius 0.001: no point lies within it of the turntable's axis \(the "
                                         r"nearest is \d+\.?\d* mm from it\)"):  # (an empty cloud, "median nan", exit 0)
        merge_views(s, clouds, exact, tmp_path / "c", crop_radius=0.001)
    written = tmp_path / "g" / "soap" / "calibration_refined.yml"
    refined = read_calibration(written)
    assert np.degrees(np.arccos(abs(refined.turntable_axis @ exact.turntable_axis))) < 0.2
    assert calibration_entries(written)[0] == {"stereo_error": 0.25} and np.allclose(refined.rotation, exact.rotation)
    # views 0 and 2 (half a turn apart) overlap only at their silhouettes: the axis is not taken, nor written
    opposite = merge_views(s, {v: clouds[v] for v in (0, 2)}, read_calibration(wrong), tmp_path / "o", refine=True)
    assert "the calibration's axis was kept" in " ".join(refinement_lines(opposite, "mm"))
    assert opposite.refined_calibration is None and not (tmp_path / "o" / "soap" / "calibration_refined.yml").exists()
    (tmp_path / "g" / "soap" / "calibration_refined.yml").rename(tmp_path / "o" / "soap" / "calibration_refined.yml")
    merge_views(s, {v: clouds[v] for v in (0, 2)}, read_calibration(wrong), tmp_path / "o", refine=True)
    assert not (tmp_path / "o" / "soap" / "calibration_refined.yml").exists()  # an earlier run's axis is not this one's
    # ... unless it is the calibration this run was given, as the line that wrote it suggests: never deleted
    given = write_calibration(tmp_path / "o" / "soap" / "calibration_refined.yml", read_calibration(wrong))
    merge_views(s, {v: clouds[v] for v in (0, 2)}, read_calibration(given), tmp_path / "o", refine=True,
                calibration=given)
    assert given.is_file()


def test_bench_axis_scores_the_refinement_against_the_axis_as_given(soap_turntable, tmp_path):
    """`sss bench axis`: the merge about the rig's own axis and about one turned and moved, each without and with the
    refinement, against the exact surface; the axis gone astray is brought back to a tenth of a millimetre."""
    from sssphase_core.bench import axis_bench

    result = axis_bench.run([soap_turntable], tmp_path / "axis.json", tilt=3.0, move=8.0, backends=("exact",), views="0,1,2")
    own, astray = result["rows"]
    assert own["axis_given"] == "the rig's own" and astray["axis_given"] == "turned 3 deg, moved 8"
    assert astray["given_mm"] > 5 and astray["taken"] and astray["refined_mm"] < 0.2 and astray["refined_shift"] < 0.2
    assert own["given_mm"] < 0.1 and own["refined_mm"] < 0.2  # an axis already right stays near it
    assert (tmp_path / "axis.md").read_text().count("| soap | exact |") == 2
    with pytest.raises(InputError, match="--tilt must be 0 to 30 degrees"):
        axis_bench.run([soap_turntable], tmp_path / "x.json", tilt=float("nan"))


def test_another_tools_calibration_file_is_not_rewritten_in_place(turntable_session, tmp_path):
    """A file with entries `sss` does not write (another tool's K1/K2 names, an image size) would lose them if the
    axis were added in place: refused in one line, the file as it was; with --out the axis goes to the new file."""
    import cv2

    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.sim import rig_preset, stereo_calibration

    c = stereo_calibration(rig_preset("cpu"))
    theirs = tmp_path / "theirs.yml"
    fs = cv2.FileStorage(str(theirs), cv2.FILE_STORAGE_WRITE)
    for name, value in (("K1", c.camera_matrix), ("K2", c.projector_matrix), ("R", c.rotation), ("T", c.translation)):
        fs.write(name, value)
    fs.write("image_width", 256)
    fs.release()
    before = theirs.read_bytes()
    res = run_sss(["calibrate", "turntable", str(turntable_session.path), "--board", "6x4", "--calibration", str(theirs)],
                  timeout=120)
    assert res.returncode == 2 and "holds entries sss does not write (K1, K2, image_width): give --out" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and theirs.read_bytes() == before
    res = run_sss(["calibrate", "turntable", str(turntable_session.path), "--board", "6x4", "--calibration", str(theirs),
                   "--out", str(tmp_path / "ours.yml")], timeout=120)
    assert res.returncode == 0 and read_calibration(tmp_path / "ours.yml").turntable_axis is not None, res.stdout + res.stderr
    assert theirs.read_bytes() == before
