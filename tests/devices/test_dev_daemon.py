"""Device plugins inside a running daemon: a camera unplugged mid-capture, and the third-party example plugin."""

from __future__ import annotations

import importlib.util
import threading

import pytest
from dev_fakes import FakeCapture

from sssphase_daemon.client import DaemonClient, DaemonError
from sssphase_daemon.server import Daemon
from sssphase_plugins import manager, uvc_camera
from sssphase_plugins.drivers import DeviceInfo
from sssphase_plugins.hookspecs import hookimpl

CAMERA = DeviceInfo("uvc:046d:0825:ABC", "camera", "uvc", "Webcam C270", "ABC")


class FlakyUvcPlugin:
    """The real UVC driver over fake OpenCV captures: the first one dies after three frames."""

    def __init__(self) -> None:
        self.captures = [FakeCapture(fail_after=3), FakeCapture(fail_after=0), FakeCapture()]
        self.provider = uvc_camera.UvcProvider(cameras=lambda: [(CAMERA, "/dev/video0")],
                                               open_capture=lambda path: self.captures.pop(0))

    @hookimpl
    def sssphase_cameras(self) -> list:
        return [self.provider]


@pytest.fixture
def daemon_with(tmp_path):
    """Start an in-process daemon whose plugin manager also holds ``plugins``; yields a client."""
    started = []

    def start(**plugins):
        daemon = Daemon(f"ipc://{tmp_path}/control.sock", token="t" * 32)
        daemon.pm = manager.build_plugin_manager()
        for name, plugin in plugins.items():
            daemon.pm.register(plugin, name=name)
        thread = threading.Thread(target=daemon.serve_forever, daemon=True)
        thread.start()
        client = DaemonClient(daemon.endpoint, daemon.token, timeout_s=10.0)
        started.append((daemon, thread, client))
        return client

    yield start
    for daemon, thread, client in started:
        client.close()
        daemon.running = False
        thread.join(timeout=10)


def white_frames(size: list[int], n: int, start: int = 0) -> list[dict]:
    return [{"name": f"white/{i}", "kind": "white", "params": {"width": size[0], "height": size[1]}}
            for i in range(start, start + n)]


def test_camera_unplugged_mid_capture_daemon_stays_up_and_session_resumes(daemon_with):
    client = daemon_with(flaky=FlakyUvcPlugin())
    rig = client.call("open_rig", camera=CAMERA.id, projector="sim:projector0", options={})
    size = rig["projector_size"]
    received = []
    with pytest.raises(DaemonError, match=r"capture failed after 3 frames: uvc:046d:0825:ABC: no frame from the camera"):
        for frame in client.capture(rig["rig"], white_frames(size, 6)):
            received.append(frame.name)
    assert received == ["white/0", "white/1", "white/2"]
    assert client.ping()  # the daemon keeps serving
    # replugged: the same rig resumes at the first missing frame (the driver reopens the camera by its ID)
    rest = [f.name for f in client.capture(rig["rig"], white_frames(size, 3, start=3))]
    assert rest == ["white/3", "white/4", "white/5"]


class FakeTriggerBoard:
    """The real serial-board driver over a scripted board (``dev_fakes.FakeBoard``) as a trigger plugin."""

    def __init__(self) -> None:
        from dev_fakes import FakeBoard

        from sssphase_plugins import serial_devices

        self.board = FakeBoard(caps="TRIG", serial_number="T1")
        self.provider = serial_devices.SerialProvider(
            "trigger", boards=lambda: [("T1", "/dev/ttyACM0", "trigger board")], connect=lambda port: self.board)

    @hookimpl
    def sssphase_triggers(self) -> list:
        return [self.provider]


def test_a_hardware_trigger_exposes_every_capture_frame(daemon_with):
    plugin = FakeTriggerBoard()
    client = daemon_with(trigger_board=plugin)
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", trigger="serial:T1",
                      options={"serial": {"timeout_s": 0.5}})
    assert rig["devices"]["trigger"]["id"] == "serial:T1"
    frames = list(client.capture(rig["rig"], white_frames(rig["projector_size"], 3)))
    assert [f.name for f in frames] == ["white/0", "white/1", "white/2"]
    assert plugin.board.fired == 3 and plugin.board.log.count("FIRE") == 3  # one pulse per frame, none repeated
    fired = [f.header["meta"]["trigger_ns"] for f in frames]
    assert fired == sorted(fired) and len(set(fired)) == 3  # the board clock at each pulse, with its frame


@pytest.mark.slow
def test_a_rig_file_with_a_trigger_captures_a_session_one_pulse_per_frame(daemon_with, tmp_path):
    from sssphase_core.capture import CaptureRequest, RigSpec, run_capture

    plugin = FakeTriggerBoard()
    client = daemon_with(trigger_board=plugin)
    (tmp_path / "rig.toml").write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n'
                                       'turntable = "sim:turntable0"\ntrigger = "serial:T1"\n'
                                       '[options.serial]\ntimeout_s = 0.5\n')
    rig = RigSpec.from_toml(tmp_path / "rig.toml")
    session = run_capture(client, CaptureRequest("soap", views=1, out=tmp_path / "s"), rig)
    assert session.validate() == [] and session.manifest["devices"]["trigger"]["id"] == "serial:T1"
    assert plugin.board.fired == session.manifest["views"]["0"]["frames"] > 20
    (tmp_path / "bad.toml").write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\ntrigger = 3\n')
    with pytest.raises(Exception, match="trigger device ids"):
        RigSpec.from_toml(tmp_path / "bad.toml")


def test_a_camera_that_cannot_be_triggered_is_refused_with_the_trigger(daemon_with):
    plugin = FakeTriggerBoard()
    client = daemon_with(flaky=FlakyUvcPlugin(), trigger_board=plugin)
    with pytest.raises(DaemonError, match=r"camera uvc:046d:0825:ABC cannot expose on a hardware trigger"):
        client.call("open_rig", camera=CAMERA.id, projector="sim:projector0", trigger="serial:T1", options={})
    assert plugin.board.fired == 0 and client.ping()


example_installed = importlib.util.find_spec("sssphase_example_plugin") is not None
needs_example = pytest.mark.skipif(not example_installed, reason="the example plugin is not installed "
                                   "(pip install -e examples/sssphase-example-plugin)")


@needs_example
def test_example_plugin_is_listed_and_captures(daemon_with):
    records = {r.name: r for r in manager.plugin_records(manager.build_plugin_manager())}
    assert records["example"].ok and records["example"].kind == "device"
    assert records["example"].source == "sssphase-example-plugin"
    client = daemon_with()
    assert "example:testpattern0" in [d["id"] for d in client.call("devices")["devices"]]
    assert "example" in [p["name"] for p in client.call("plugins")["plugins"]]
    rig = client.call("open_rig", camera="example:testpattern0", projector="sim:projector0",
                      options={"example": {"width": 64, "height": 48}})
    frames = list(client.capture(rig["rig"], white_frames(rig["projector_size"], 2)))
    assert [f.data.shape for f in frames] == [(48, 64, 3)] * 2
    assert frames[0].data.max() <= 1.0 and frames[0].data[:, :8].std() > 0  # gradient over colour bars


@needs_example
def test_sss_plugins_lists_example():
    from typer.testing import CliRunner

    from sssphase_cli.main import app

    result = CliRunner().invoke(app, ["plugins"])
    assert result.exit_code == 0 and "example" in result.output


def test_plugins_without_devices_do_not_block_opening_others():
    from sssphase_plugins import hookspecs, oak_camera, sim_plugin

    pm = manager.PluginManager()
    pm.add_hookspecs(hookspecs)
    pm.register(oak_camera, name="oak")  # registered first, like an entry point sorted before "sim"
    pm.register(sim_plugin, name="sim")
    assert manager.find_provider("sim:camera0", pm).kind == "camera"


PRINTING_PLUGIN = '''
from sssphase_plugins.api import DeviceInfo, hookimpl

class Provider:
    kind = "camera"

    def discover(self):
        print("chatty: scanning the bus")  # what plugins and their native libraries (depthai) do
        return [DeviceInfo("chatty:0", "camera", "chatty", "a chatty camera", "0")]

    def open(self, device_id, options, shared):
        raise RuntimeError("not for opening")

@hookimpl
def sssphase_cameras():
    return [Provider()]
'''


def test_sss_devices_json_is_json_whatever_plugins_print(tmp_path):
    """A plugin's print (and depthai's "USB protocol not available" warning) went into `sss devices --json`, which
    no JSON reader could then read."""
    import json
    import os
    import tempfile

    from sss_process import run_sss

    (tmp_path / "chatty.py").write_text(PRINTING_PLUGIN)
    runtime = tempfile.mkdtemp(prefix="sssj", dir="/tmp")
    env = {**os.environ, "SSS_PLUGINS": "chatty", "SSS_RUNTIME_DIR": runtime,
           "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    res = run_sss(["devices", "--json"], env=env, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    found = json.loads(res.stdout)  # (no daemon: local discovery)
    assert "chatty:0" in [d["id"] for d in found["devices"]]
    assert "chatty: scanning the bus" in res.stderr
