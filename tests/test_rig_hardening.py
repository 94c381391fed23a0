"""Rig files and sim rig options that had been taken without a word (a session named apple holding an orange,
a misspelt table ignored, "false" read as true) or broken by `sss calibrate projector`, now refused or kept."""

from __future__ import annotations

import tomllib

import pytest

from sssphase_core.capture.calibration import (
    RAMP_LEVELS,
    CalibrationRequest,
    ProjectorResponse,
    rig_file_with_response,
    write_rig_response,
)
from sssphase_core.capture.engine import check_brackets, run_capture
from sssphase_core.capture.plan import CaptureRequest, RigSpec
from sssphase_core.errors import InputError
from sssphase_core.store.session import rig_problem

DEVICES = '[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\nturntable = "sim:turntable0"\n'
FIT = ProjectorResponse(2.4, 0.003, (2.38, 2.4, 2.42), (0.003, 0.003, 0.003), RAMP_LEVELS,
                        tuple(tuple(v ** 2.4 for v in RAMP_LEVELS) for _ in range(3)), 0.004, 1000)


class _NoDaemon:
    def call(self, *args, **kwargs):
        raise AssertionError("the daemon was asked before the rig file was checked")


@pytest.mark.parametrize(("options", "said"), [
    ('object = "orange"\n', "object = 'orange' (the capture's --object gives 'apple')"),
    ("seed = 7\n", "seed = 7 (the capture's --seed gives 0)"),
    ("n_views = 2\n", "n_views = 2 (the capture's --views gives 3)"),
    ("view = 1\n", "view (the turntable sets it)"),
])
def test_rig_options_may_not_change_what_the_capture_sets(tmp_path, options, said):
    (tmp_path / "rig.toml").write_text(DEVICES + "[options]\n" + options)
    rig = RigSpec.from_toml(tmp_path / "rig.toml")
    with pytest.raises(InputError, match="the rig file's \\[options\\] set") as err:
        run_capture(_NoDaemon(), CaptureRequest("apple", views=3, out=tmp_path / "s"), rig)
    assert said in str(err.value) and not (tmp_path / "s").exists()


def test_rig_options_may_repeat_what_the_capture_sets(tmp_path):
    (tmp_path / "rig.toml").write_text(DEVICES + '[options]\nobject = "apple"\nn_views = 3\n')
    with pytest.raises(AssertionError, match="the daemon was asked"):  # past the check, to the daemon
        run_capture(_NoDaemon(), CaptureRequest("apple", views=3, out=tmp_path / "s"), RigSpec.from_toml(tmp_path / "rig.toml"))


@pytest.mark.parametrize(("text", "message"), [
    (DEVICES + "[projecter]\ngamma = 2.6\n", r"unknown rig file tables \[projecter\]"),
    (DEVICES + "[wat]\nx = 1\n", r"unknown rig file tables \[wat\]"),
    (DEVICES + "[projector]\nfoo = 3\n", r"unknown \[projector\] keys foo"),
    (DEVICES + '[projector]\ngamma_rgb = "x"\n', r"\[projector\] gamma_rgb must be three numbers in \[0.3, 5\]"),
    (DEVICES + "[projector]\nblack_rgb = [0.1, 0.2]\n", r"\[projector\] black_rgb must be three numbers"),
    # the fit's record (it went into every session's manifest whatever it held)
    (DEVICES + "[projector]\nlevels = [0, 0.5, 0.2]\n", r"\[projector\] levels must be the ramp's grey levels, increasing"),
    (DEVICES + "[projector]\nlevels = [0, 1]\nresponse_rgb = [[0, 1], [0, 1], [0]]\n",
     r"\[projector\] response_rgb must be three lists of finite numbers, one per level"),
    (DEVICES + "[projector]\nrms = inf\n", r"\[projector\] rms must be a finite number >= 0, got inf"),
    (DEVICES + '[projector]\npixels = "all"\n', r"\[projector\] pixels must be a whole number >= 0, got 'all'"),
])
def test_misspelt_or_mistyped_rig_tables_are_refused(tmp_path, text, message):
    (tmp_path / "rig.toml").write_text(text)
    with pytest.raises(InputError, match=message):
        RigSpec.from_toml(tmp_path / "rig.toml")


def test_per_colour_gammas_without_their_mean_give_it(tmp_path):
    (tmp_path / "rig.toml").write_text(DEVICES + "[projector]\ngamma_rgb = [2.5, 2.6, 2.7]\nblack_rgb = [0.01, 0.02, 0.03]\n")
    rig = RigSpec.from_toml(tmp_path / "rig.toml")
    assert rig.gamma == pytest.approx(2.6) and rig.projector_black == pytest.approx(0.02)


@pytest.mark.parametrize("text", [
    DEVICES + '# keep\n["projector"]\ngamma = 2.3\n',  # a quoted header: the old table was kept beside the new one
    'projector.gamma = 2.3\n' + DEVICES,  # a dotted key
    DEVICES + '# keep\n[projector]\ngamma = 2.3\n[[extra]]\nname = "keepme"\n[options]\nread_noise = 3\n',  # [[arrays]]
])
def test_calibration_leaves_a_valid_rig_file_with_every_other_table(text):
    before = tomllib.loads(text)
    after = tomllib.loads(rig_file_with_response(text, FIT))  # was: "Cannot declare ('projector',) twice", or [[extra]] lost
    assert after["projector"]["gamma"] == 2.4 and after["devices"] == before["devices"]
    assert {k: v for k, v in after.items() if k != "projector"} == {k: v for k, v in before.items() if k != "projector"}


def test_calibration_into_a_new_file_copies_the_whole_rig(tmp_path):
    (tmp_path / "a.toml").write_text(DEVICES + "# my rig\n[options]\nread_noise = 3\n[processing]\nmedian = false\n")
    req = CalibrationRequest(rig=tmp_path / "a.toml", out=tmp_path / "new.toml")
    write_rig_response(req, FIT)
    text = (tmp_path / "new.toml").read_text()
    rig = RigSpec.from_toml(tmp_path / "new.toml")  # was: only [projector], "[devices] needs camera and projector ids"
    assert rig.camera == "sim:camera0" and rig.options == {"read_noise": 3} and rig.median is False
    assert rig.gamma == 2.4 and "# my rig" in text


@pytest.mark.parametrize(("options", "message"), [
    ({"raw": "false"}, "sim option raw must be true or false, got 'false'"),
    ({"realtime": "no"}, "sim option realtime must be true or false"),
    ({"fail_at_frame": "x"}, "sim option fail_at_frame must be an integer, got 'x'"),
    ({"grab_delay_s": float("nan")}, r"sim option grab_delay_s must be in \[0, 3600\]"),
    ({"grab_delay_s": -1}, r"sim option grab_delay_s must be in \[0, 3600\]"),
    ({"seed": -5}, r"sim option seed must be in \[0, 9,223,372,036,854,775,807\], got -5"),
    ({"shape": [100000, 100000]}, "sim option shape is the sim:bench-camera's: sim:camera0 renders"),  # was recorded
    ({"dtype": "complex64"}, "sim option dtype is the sim:bench-camera's"),
])
def test_sim_options_of_the_wrong_type_are_one_line_naming_the_option(options, message):
    from sssphase_plugins import sim_plugin

    with pytest.raises(InputError, match=message):
        bench = sim_plugin.SimRigState({"object": "apple", **options})
        sim_plugin.SimCamera(bench, options)


def test_hdr_brackets_the_daemon_would_refuse_are_refused_before_the_session_is_begun():
    with pytest.raises(InputError, match=r"in \[0.001, 256\], got 2: 1e-09, 1"):
        check_brackets((1e-9, 1.0))
    check_brackets((0.001, 1.0))


def test_a_sim_rig_record_the_simulator_cannot_rebuild_is_a_damaged_manifest():
    rig = {"camera": "sim:camera0", "projector": "sim:projector0", "options": {"preset": "nope"}}
    assert rig_problem(rig) == "rig.options: unknown rig preset 'nope'; choose one of cpu, paper"
    assert rig_problem({**rig, "options": {"preset": "cpu"}}) is None
    assert rig_problem({**rig, "camera": "uvc:0"}) is None  # another plugin's options are its own


def test_the_gap_bench_on_a_view_without_references_is_one_line():
    from types import SimpleNamespace

    from sssphase_core.bench.gap_bench import decompose

    with pytest.raises(InputError, match="apple view 0 has no reference captures"):  # was "need at least one array"
        decompose(SimpleNamespace(object="apple", view=0, references={}), "analytic", None)


def test_a_demo_or_repro_whose_sessions_failed_does_not_end_as_a_success(tmp_path):
    from types import SimpleNamespace

    from sssphase_core.errors import DataError
    from sssphase_core.reporting.demo import USERS_PATH, Demo

    done = {"status": "done"}
    run = SimpleNamespace(results={n: done for n in USERS_PATH})
    Demo.raise_unless_done(run, USERS_PATH, tmp_path / "report.md")
    run.results["train_sessions"] = {"status": "not available", "reason": "did not answer within 0 s"}
    with pytest.raises(DataError, match="steps train_sessions did not run"):
        Demo.raise_unless_done(run, USERS_PATH, tmp_path / "report.md")


def test_a_failed_daemon_bench_ends_its_daemon(monkeypatch):
    from sssphase_daemon import bench

    started = []

    def spawn(**kwargs):
        started.append(spawned(**kwargs))
        return started[-1]

    def broken(client, n):
        raise RuntimeError("the run failed")

    spawned = bench.spawn_daemon
    monkeypatch.setattr(bench, "spawn_daemon", spawn)
    monkeypatch.setattr(bench, "through_daemon", broken)
    monkeypatch.setenv("SSS_RUNTIME_DIR", "/tmp")  # run_bench sets its own; restored after the test
    with pytest.raises(RuntimeError, match="the run failed"):
        bench.run_bench(5)
    assert len(started) == 1 and started[0].poll() is not None  # was left running under init, out of `sss daemon stop`'s reach


def test_calibration_never_writes_one_rig_s_fit_into_another_rig_s_file(tmp_path, monkeypatch):
    """`sss calibrate projector` (the sim rig) in a folder holding a real rig's rig.toml replaced that rig's measured
    gamma and black with the simulator's, exit 0; `--rig sim.toml --out real.toml` did the same."""
    monkeypatch.chdir(tmp_path)
    real = '[devices]\ncamera = "oak:18443010D1D5E41200"\nprojector = "lcr4500:LCR00123"\n[projector]\ngamma = 2.31\n'
    (tmp_path / "rig.toml").write_text(real)
    (tmp_path / "sim.toml").write_text(DEVICES)
    for req in ({}, {"rig": tmp_path / "sim.toml", "out": tmp_path / "rig.toml"}):
        with pytest.raises(InputError, match=r"rig.toml is the rig file of other devices \(camera oak:18443010D1D5E41200"
                                             r".*pass --rig .*rig.toml to calibrate that rig"):
            CalibrationRequest(**req)
    assert (tmp_path / "rig.toml").read_text() == real
    req = CalibrationRequest(rig=tmp_path / "rig.toml")  # the rig itself, calibrated in place
    assert req.target == tmp_path / "rig.toml"


def test_calibrating_through_a_link_rewrites_the_file_it_names_and_keeps_its_mode(tmp_path):
    """`--rig link.toml` replaced the link by a new file (mode 644): the rig file it named kept the old response
    and captures with it went on with the old gamma; a private (600) rig file became world-readable."""
    private = tmp_path / "priv.toml"
    private.write_text(DEVICES)
    private.chmod(0o600)
    (tmp_path / "link.toml").symlink_to(private)
    write_rig_response(CalibrationRequest(rig=tmp_path / "link.toml"), FIT)
    assert (tmp_path / "link.toml").is_symlink() and RigSpec.from_toml(private).gamma == 2.4
    assert private.stat().st_mode & 0o777 == 0o600


def test_new_keys_replace_links_in_the_key_folder_instead_of_writing_through_them(tmp_path):
    """`sss daemon keys --overwrite` with server.key_secret a link to another file wrote the CURVE secret key into
    that file (its contents gone)."""
    from sssphase_daemon import security

    keys = tmp_path / "k"
    keys.mkdir(mode=0o700)
    precious = tmp_path / "precious.txt"
    precious.write_text("hello\n")
    for name in ("server.key_secret", "client.key", "client.key_secret", "server.key"):
        (keys / name).symlink_to(precious)
    security.generate_keys(keys, overwrite=True)
    assert precious.read_text() == "hello\n"
    assert not any(p.is_symlink() for p in keys.iterdir()) and "secret-key" in (keys / "server.key_secret").read_text()


@pytest.mark.parametrize("shape", ["abc", 5, [2, "x"], [2.5, 3], [True, 2]])
def test_a_bench_camera_shape_that_is_not_a_list_of_integers_is_one_line(shape):
    """`shape = "abc"` in a rig file was "daemon: ValueError: invalid literal for int()" (5: "TypeError")."""
    from sssphase_plugins import sim_plugin

    with pytest.raises(InputError, match="bench camera shape must be a list of 1 to 3 integers"):
        sim_plugin.BenchCamera({"shape": shape})


def test_a_bench_camera_seed_out_of_range_is_one_line_and_its_float16_frames_are_finite():
    """``seed: -1`` was a device error with a traceback in the daemon's log; ``dtype: float16`` opened, and its frames
    (codes up to 65535, above float16's largest 65504) held inf, so every job on it failed as a corrupted transfer."""
    import numpy as np

    from sssphase_plugins import sim_plugin

    with pytest.raises(InputError, match=r"sim option seed must be in \[0, "):
        sim_plugin.BenchCamera({"seed": -1})
    frame = sim_plugin.BenchCamera({"shape": [256, 256, 3], "dtype": "float16"}).data
    assert np.isfinite(frame).all() and frame.max() > 6e4
