"""A device that stops answering hangs nothing: the job fails at its deadline naming the device, a cancel takes
effect at once, the rig closes, the session keeps its complete views and `sss daemon stop` ends the daemon."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from sss_process import run_sss

from sssphase_daemon import protocol, security
from sssphase_daemon.client import DaemonClient, DaemonError, spawn_daemon

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]


def _sss(*args: str, env: dict[str, str], timeout: float = 120) -> tuple[subprocess.CompletedProcess[str], float]:
    t0 = time.monotonic()
    res = run_sss([*args], env=env, cwd=REPO, timeout=timeout)
    return res, time.monotonic() - t0


def test_a_stalled_camera_fails_the_capture_at_its_timeout_and_the_daemon_still_stops(tmp_path):
    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "200"}
    rig = tmp_path / "stall.toml"
    rig.write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\nturntable = "sim:turntable0"\n'
                   '[options]\nobject = "star"\nn_views = 2\nstall_at_frame = 30\n'  # view 0 has 26 frames
                   'frame_timeout_s = 10\n')  # the camera's own frame time (30 s by default at this size)
    try:
        started, _ = _sss("daemon", "start", env=env)  # a daemon of its own: the capture leaves it running
        assert started.returncode == 0, started.stdout + started.stderr
        res, _ = _sss("capture", "--rig", str(rig), "--object", "star", "--views", "2", "--timeout", "4", "--out",
                      str(tmp_path / "s"), env=env)
        out = res.stdout + res.stderr
        assert res.returncode != 0 and "Traceback" not in out, out
        # the deadline is the client's --timeout, but no shorter than the sim camera's own frame time
        assert "sim:camera0 (grab" in out and "did not answer within 10 s" in out, out
        from sssphase_core.store.session import Session

        assert Session.open(tmp_path / "s" / "star").status(0) == "complete"  # the complete view is kept
        pid = security.read_state(runtime / "daemon.json").pid
        stopped, seconds = _sss("daemon", "stop", env=env)
        assert stopped.returncode == 0 and f"daemon (pid {pid}) stopped" in stopped.stdout, stopped.stdout
        assert seconds < 10 and not security.is_daemon_process(pid)
    finally:
        _sss("daemon", "stop", env=env)
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_camera_unplugged_mid_capture_is_one_line_and_the_capture_resumes_once_it_is_back(tmp_path):
    """disconnect_at_frame: the sim camera is gone from that frame on (every later grab raises), as an unplugged
    USB camera. The capture fails naming the camera, keeps its complete view, and a --resume with the camera
    back (a rig file without the fault) captures only the missing view."""
    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "200"}
    rigs = {}
    for name, fault in (("unplugged", "disconnect_at_frame = 30\n"), ("back", "")):
        rigs[name] = tmp_path / f"{name}.toml"
        rigs[name].write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\nturntable = "sim:turntable0"\n'
                              f'[options]\nobject = "star"\nn_views = 2\n{fault}')  # view 0 has 26 frames
    try:
        res, _ = _sss("capture", "--rig", str(rigs["unplugged"]), "--object", "star", "--views", "2", "--out",
                      str(tmp_path / "s"), env=env)
        out = res.stdout + res.stderr
        assert res.returncode != 0 and "Traceback" not in out, out
        assert "sim:camera0: the camera is disconnected" in out and "resume" in out, out
        from sssphase_core.store.session import Session

        session = Session.open(tmp_path / "s" / "star")
        assert session.status(0) == "complete" and session.status(1) != "complete"
        res, _ = _sss("capture", "--rig", str(rigs["back"]), "--object", "star", "--views", "2", "--resume", "--out",
                      str(tmp_path / "s"), env=env)
        assert res.returncode == 0, res.stdout + res.stderr
        session = Session.open(tmp_path / "s" / "star")
        assert session.validate(expected_views=2) == []
    finally:
        _sss("daemon", "stop", env=env)
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_cancel_takes_effect_while_a_device_hangs_and_the_rig_still_closes(monkeypatch):
    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))
    proc = spawn_daemon()
    try:
        state = security.read_state()
        with DaemonClient(state.endpoint, state.token, timeout_s=5.0) as client:
            rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0",
                              options={"object": "star", "stall_at_frame": 1})["rig"]
            frames = client.stream(rig, 100, deadline_s=3600)
            next(frames)  # frame 0 out, frame 1 hanging
            (job,) = [j["job"] for j in client.call("status")["jobs"] if j["rig"] == rig]
            time.sleep(0.5)
            t0 = time.monotonic()
            client.call("cancel", job=job)
            while client.call("job", job=job)["state"] == "running" and time.monotonic() - t0 < 5:
                time.sleep(0.05)
            assert client.call("job", job=job)["state"] == "cancelled" and time.monotonic() - t0 < 2
            closed = client.call("close_rig", rig=rig)
            assert closed["closed"] == rig and "in the background" in closed["note"]
            with pytest.raises(DaemonError) as exc:  # and it is gone
                client.call("close_rig", rig=rig)
            assert exc.value.code == protocol.NOT_FOUND
            with pytest.raises(DaemonError, match=r"deadline_s must be a number of seconds"):
                rig2 = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})
                client.call("stream", rig=rig2["rig"], count=1, deadline_s=-1)
            client.call("shutdown")
        assert proc.wait(15) == 0  # the hung device thread does not keep the daemon alive
    finally:
        if proc.poll() is None:
            proc.kill()
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_corrupted_frame_an_unknown_option_and_an_absurd_size_are_one_line_each(daemon):
    """The sim devices corrupt on demand (garbage_at_frame): the job fails naming the camera and the frame;
    an option no sim device reads and a frame no memory holds are refused before anything is allocated."""
    import json

    from sssphase_core.processing.patterns import capture_plan

    _, client = daemon
    frames = json.loads(capture_plan(256, 192, references=("white", "black")).to_json())["frames"][:4]
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0",
                      options={"object": "star", "garbage_at_frame": 2})["rig"]
    got = []
    with pytest.raises(DaemonError, match=r"sim:camera0: frame .* is \(96, 256, 3\) <f4, the job's first frame was "
                                          r"\(192, 256, 3\) <f4: a corrupted transfer") as exc:
        for frame in client.capture(rig, frames):
            got.append(frame.name)
    assert exc.value.code == protocol.DEVICE and len(got) == 2
    client.call("close_rig", rig=rig)
    with pytest.raises(DaemonError, match=r"unknown sim option\(s\) grab_delay, objekt \(known: "):
        client.call("open_rig", camera="sim:camera0", projector="sim:projector0",
                    options={"objekt": "star", "grab_delay": 1, "basler": {"gain": 0}})  # tables: other plugins'
    with pytest.raises(DaemonError, match=r"bench camera shape \(1000000, 1000000\) is not a frame of at most 1024 MiB"):
        client.call("open_rig", camera="sim:bench-camera", options={"shape": [1000000, 1000000]})


STALLED_CLIENT = """
import os, sys
from sssphase_daemon.client import DaemonClient
client = DaemonClient(sys.argv[1], sys.argv[2], timeout_s=30, heartbeat_s=0.1)
rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0",
                  options={"object": "star", "stall_at_frame": 2})["rig"]
frames = client.stream(rig, 100, deadline_s=3600)
next(frames), next(frames)  # frame 2 hangs in the camera
print(rig, flush=True)
os._exit(0)
"""


def test_the_rig_of_a_client_that_died_while_its_camera_hung_is_taken_back_without_stalling_the_daemon(monkeypatch):
    """A crashed client's rig is closed once its job is cancelled; when that job's device call still hangs, the
    close must not hold the daemon's main thread (it serves every request) waiting on the device."""
    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))
    proc = spawn_daemon(extra_args=("--client-timeout", "0.5"))
    try:
        state = security.read_state()
        crashed = subprocess.run([os.sys.executable, "-c", STALLED_CLIENT, state.endpoint, state.token],
                                 capture_output=True, text=True, timeout=120)
        rig = crashed.stdout.strip()
        assert crashed.returncode == 0 and rig, crashed.stderr
        with DaemonClient(state.endpoint, state.token, timeout_s=5.0) as client:
            deadline = time.monotonic() + 10
            while rig in {r["rig"] for r in client.call("status")["rigs"]} and time.monotonic() < deadline:
                time.sleep(0.1)
            assert rig not in {r["rig"] for r in client.call("status")["rigs"]}
            t0 = time.monotonic()
            assert client.ping(timeout_s=2.0) and time.monotonic() - t0 < 1.0
            client.call("shutdown")
        assert proc.wait(15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        shutil.rmtree(runtime, ignore_errors=True)
