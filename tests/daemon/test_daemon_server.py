"""The daemon process: fuzzing, authentication, dead clients, device failures, concurrent clients."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq

from sssphase_core.processing.patterns import capture_plan
from sssphase_daemon import protocol, security
from sssphase_daemon.client import DaemonClient, DaemonError


def _drain(sock: zmq.Socket, wait_ms: int = 50) -> list[dict]:
    out = []
    while sock.poll(wait_ms):
        out.append(msgpack.unpackb(sock.recv_multipart()[-1], raw=False))
    return out


def _fuzz_messages(token: str, n: int, rng: np.random.Generator) -> list[list[bytes]]:
    good = protocol.request(1, "ping", token)
    variants = [
        lambda: [rng.bytes(int(rng.integers(0, 200)))],  # random bytes
        lambda: [good[: int(rng.integers(0, len(good)))]],  # truncated
        lambda: [msgpack.packb({"v": int(rng.integers(2, 99)), "id": 1, "op": "ping", "token": token})],  # version
        lambda: [msgpack.packb({"v": 1, "id": 1, "op": "ping", "token": "x" * int(rng.integers(0, 50))})],  # auth
        lambda: [msgpack.packb({"v": 1, "id": 1, "op": "ping"})],  # no token
        lambda: [msgpack.packb({"v": 1, "id": [1], "op": 3, "token": token})],  # wrong types
        lambda: [msgpack.packb({"v": 1, "id": 2, "op": "rm -rf", "token": token})],  # unknown op
        lambda: [msgpack.packb({"v": 1, "id": 3, "op": "capture", "token": token, "args": {"rig": "nope", "frames": 5}})],
        lambda: [msgpack.packb({"v": 1, "id": 4, "op": "stream", "token": token, "args": {"rig": {"a": 1}, "count": -1}})],
        lambda: [msgpack.packb({"v": 1, "id": 5, "op": "open_rig", "token": token, "args": {"camera": 7}})],
        lambda: [msgpack.packb([1, 2, 3])],  # not a map
        lambda: [b"\xc1"],  # reserved msgpack byte
        lambda: [b"x", b"y", good],  # non-empty delimiter frames
        lambda: [b"", b"", good[:-1]],
        lambda: [b"\x91" * 5000],  # deeply nested arrays
    ]
    return [variants[int(rng.integers(0, len(variants)))]() for _ in range(n)]


def test_an_error_reply_carries_the_requests_id_where_it_had_one():
    """PROTOCOL.md says replies carry the request's id; an unknown op or version was answered with id None."""
    for msg, code in (({"v": 1, "id": 7, "op": "fly", "token": "t"}, protocol.UNKNOWN_OP),
                      ({"v": 2, "id": "a", "op": "ping", "token": "t"}, protocol.BAD_VERSION),
                      ({"v": 1, "id": 9, "op": "ping", "token": b"t"}, protocol.BAD_MESSAGE)):
        with pytest.raises(protocol.ProtocolError) as exc:
            protocol.parse_request(protocol.pack(msg))
        assert exc.value.code == code and exc.value.rid == msg["id"]  # type: ignore[attr-defined]


def test_fuzzing_10000_messages_leaves_the_daemon_serving(daemon):
    proc, client = daemon
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(client.endpoint)
    rng = np.random.default_rng(7)
    replies: list[dict] = []
    for _batch in range(10):
        for parts in _fuzz_messages(client.token, 1000, rng):
            sock.send_multipart(parts)
        replies += _drain(sock, 200)
    assert proc.poll() is None
    assert len(replies) > 8000 and all(r["ok"] is False for r in replies)
    codes = {r["error"]["code"] for r in replies}
    assert {protocol.BAD_MESSAGE, protocol.BAD_VERSION, protocol.UNAUTHENTICATED, protocol.UNKNOWN_OP,
            protocol.NOT_FOUND} <= codes
    # oversized: ZeroMQ drops the connection at the transport (limit 1 MiB); the daemon lives on
    big = zmq.Context.instance().socket(zmq.DEALER)
    big.linger = 0
    big.connect(client.endpoint)
    big.send(b"\x00" * (3 * 2**20))
    assert not big.poll(300)
    big.close()
    assert client.call("ping")["time"] > 0
    sock.close()


def test_wrong_token_is_refused(daemon):
    _, client = daemon
    intruder = DaemonClient(client.endpoint, "not-the-token", timeout_s=3)
    with pytest.raises(DaemonError, match="token") as exc:
        intruder.call("devices")
    assert exc.value.code == protocol.UNAUTHENTICATED
    intruder.close()


def test_off_loopback_bind_needs_curve_keys_and_refuses_plain_clients(runtime_dir, tmp_path):
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime_dir)}
    refused = subprocess.run([sys.executable, "-m", "sssphase_daemon", "--endpoint", "tcp://0.0.0.0:*",
                              "--state-file", str(tmp_path / "s.json")], capture_output=True, text=True, env=env, timeout=30)
    assert refused.returncode == 2 and "CURVE" in refused.stderr
    keys = security.generate_keys(tmp_path / "curve")
    state_file = tmp_path / "curve.json"
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_daemon", "--endpoint", "tcp://0.0.0.0:*",
                             "--curve-dir", str(keys), "--state-file", str(state_file)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 20
        while (state := security.read_state(state_file)) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        port = state.endpoint.rsplit(":", 1)[1]
        endpoint = f"tcp://127.0.0.1:{port}"
        plain = DaemonClient(endpoint, state.token, timeout_s=1.0)  # right token, no CURVE handshake
        assert not plain.ping(timeout_s=1.0)
        plain.close()
        with DaemonClient(endpoint, state.token, curve_dir=keys, timeout_s=5.0) as good:
            assert good.call("hello")["protocol"] == protocol.PROTOCOL_VERSION
            rig = good.call("open_rig", camera="sim:bench-camera", options={"shape": [8, 8, 3]})["rig"]
            assert len(list(good.stream(rig, 2))) == 2  # the job's stream, over CURVE too
        secret = keys / "client.key_secret"
        secret.write_text("garbage")  # a damaged key: one line, not "internal error: ValueError"
        with pytest.raises(security.KeyFileError, match="client.key_secret: not a readable CURVE key file"):
            DaemonClient(endpoint, state.token, curve_dir=keys, timeout_s=1.0)
    finally:
        proc.terminate()
        proc.wait(10)
    # a stream bound on every interface is reached where the client reached the daemon (a remote client was
    # handed tcp://0.0.0.0:PORT, its own machine, and waited for frames for ever)
    assert security.reachable_stream("tcp://0.0.0.0:5000", "tcp://192.168.1.5:56150") == "tcp://192.168.1.5:5000"
    assert security.reachable_stream("tcp://[::]:5000", "tcp://[fe80::1]:56150") == "tcp://[fe80::1]:5000"
    assert security.reachable_stream("tcp://10.0.0.2:5000", "tcp://192.168.1.5:1") == "tcp://10.0.0.2:5000"
    assert security.reachable_stream("ipc:///run/a.sock", "ipc:///run/c.sock") == "ipc:///run/a.sock"


CLIENT_SCRIPT = """
import sys
from sssphase_daemon.client import DaemonClient
client = DaemonClient(sys.argv[1], sys.argv[2], heartbeat_s=0.2)
rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": [512, 512, 3]})["rig"]
for i, frame in enumerate(client.stream(rig, 100000)):
    if i == 3:
        print("streaming", flush=True)
"""


def test_client_killed_mid_stream_does_not_stall_the_daemon(daemon):
    proc, client = daemon
    victim = subprocess.Popen([sys.executable, "-c", CLIENT_SCRIPT, client.endpoint, client.token],
                              stdout=subprocess.PIPE, text=True)
    assert victim.stdout.readline().strip() == "streaming"
    victim.kill()
    victim.wait()
    jobs = []
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        jobs = [j for j in client.call("status")["jobs"] if j["total"] == 100000]
        if jobs and jobs[-1]["state"] == "cancelled":
            break
        time.sleep(0.2)
    assert jobs and jobs[-1]["state"] == "cancelled" and jobs[-1]["sent"] < 100000
    assert jobs[-1]["error"]["code"] == protocol.CLIENT_TIMEOUT  # (a client that was only slow is told why)
    assert re.match(r"the daemon cancelled the capture: no heartbeat from its client for \d+\.\d s \(the daemon's "
                    r"--client-timeout is 4 s\)$", jobs[-1]["error"]["message"])
    # the dead client's rig goes with its job (it stayed open for five minutes: sixteen such filled the daemon)
    deadline = time.monotonic() + 5
    while jobs[-1]["rig"] in {r["rig"] for r in client.call("status")["rigs"]} and time.monotonic() < deadline:
        time.sleep(0.1)
    assert jobs[-1]["rig"] not in {r["rig"] for r in client.call("status")["rigs"]}
    rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": [64, 64, 3]})["rig"]
    assert len(list(client.stream(rig, 20))) == 20


def test_device_failure_mid_view_is_reported_and_the_daemon_keeps_serving(daemon):
    proc, client = daemon
    plan = capture_plan(256, 192, references=("white", "black"))
    frames = json.loads(plan.to_json())["frames"]
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0",
                      options={"object": "star", "fail_at_frame": 4})["rig"]
    got = []
    with pytest.raises(DaemonError, match="simulated sensor failure at frame 4") as exc:
        for frame in client.capture(rig, frames[:8]):
            got.append(frame.name)
    assert exc.value.code == protocol.DEVICE and got == [f["name"] for f in frames[:4]]
    failed = [j for j in client.call("status")["jobs"] if j["rig"] == rig]
    assert failed[-1]["state"] == "failed"
    ok_rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})["rig"]
    names = [f.name for f in client.capture(ok_rig, frames[:3])]
    assert names == [f["name"] for f in frames[:3]]
    assert client.call("status")["heavy_modules"] == []  # a sim-only daemon loads no torch, no hardware library


def test_a_frame_may_set_the_camera_gain_and_an_absurd_one_is_bad_args(daemon):
    """`sss view` sets the gain with each frame: the driver gets it with the exposure (the sim camera says
    which gain a frame had); a gain out of range is refused with the request."""
    _, client = daemon
    plan = capture_plan(256, 192, references=("white", "black"))
    white = next(f for f in json.loads(plan.to_json())["frames"] if f["kind"] == "white")
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})["rig"]
    (frame,) = client.capture(rig, [{**white, "gain": 2.5}])
    (plain,) = client.capture(rig, [white])
    assert frame.header["meta"]["gain"] == 2.5 and plain.header["meta"]["gain"] == 2.5  # kept until set again
    for bad in (-1, 1e9, "loud", True):
        with pytest.raises(DaemonError, match="gain must be a number in") as exc:
            list(client.capture(rig, [{**white, "gain": bad}]))
        assert exc.value.code == protocol.BAD_ARGS
    client.call("close_rig", rig=rig)


def test_a_pattern_of_another_size_than_the_projector_is_bad_args_before_it_is_rendered(daemon):
    """A 16384 x 16384 white was rendered in the job before the projector refused it, and the daemon kept the
    gigabyte: the request is refused, naming both sizes, and nothing runs."""
    _, client = daemon
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})["rig"]
    jobs = len(client.call("status")["jobs"])
    big = {"name": "big", "kind": "white", "params": {"width": 16384, "height": 16384}}
    image = {"name": "img", "kind": "image", "image": {"dtype": "<f4", "shape": [4, 4], "data": bytes(64)}}
    for frame, size in ((big, "16384x16384"), (image, "4x4")):
        with pytest.raises(DaemonError, match=rf"frame '{frame['name']}' is {size}, but the projector sim:projector0 "
                                               r"shows 256x192") as exc:
            client.call("capture", rig=rig, frames=[frame])
        assert exc.value.code == protocol.BAD_ARGS
    assert len(client.call("status")["jobs"]) == jobs
    # an image of NaN or of values above the projector's white failed in the job as the camera's fault
    for values in (np.full((192, 256), np.nan, np.float32), np.full((192, 256), 7.0, np.float32)):
        bad = {"name": "img", "kind": "image", "image": {"dtype": "<f4", "shape": [192, 256], "data": values.tobytes()}}
        with pytest.raises(DaemonError, match=r"the image must hold light in \[0, 1\]") as exc:
            client.call("capture", rig=rig, frames=[bad])
        assert exc.value.code == protocol.BAD_ARGS
    client.call("close_rig", rig=rig)


def test_devices_of_the_wrong_kind_absurd_exposures_and_angles_are_bad_args_and_hold_no_rig(daemon):
    """A projector id given as the camera opened a rig that then failed with an AttributeError (an
    `internal` error, a traceback in the log) and kept its slot: 16 such tries locked captures out."""
    proc, client = daemon
    rigs_before = len(client.call("status")["rigs"])  # the module's daemon serves earlier tests' rigs too
    for _ in range(3):
        with pytest.raises(DaemonError, match="sim:projector0 is a projector, not a camera") as exc:
            client.call("open_rig", camera="sim:projector0", projector="sim:camera0", options={})
        assert exc.value.code == protocol.NOT_FOUND
    with pytest.raises(DaemonError, match="is a camera, not a turntable"):
        client.call("open_rig", camera="sim:camera0", turntable="sim:camera0", options={})
    assert len(client.call("status")["rigs"]) == rigs_before
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", turntable="sim:turntable0",
                      options={"object": "star"})["rig"]
    for exposure in (float("inf"), float("nan"), 1e300, 1e-300, True, 0):
        frame = {"name": "w", "kind": "white", "params": {}, "exposure": exposure}
        with pytest.raises(DaemonError, match="bad frame spec .*: exposure must be a number from 1e-06 to 1e"
                                              "[+]06, got") as exc:
            client.call("capture", rig=rig, frames=[frame])
        assert exc.value.code == protocol.BAD_ARGS
    for frame, said in (({"name": 3, "kind": "white"}, "name must be text"),
                        ({"name": "w", "kind": "grey"}, "kind must be one of psp, white, black, level, dots, ref, "
                                                        "image, got 'grey'"),
                        ({"name": "w", "kind": "image"}, "needs image: {dtype, shape, data}")):
        with pytest.raises(DaemonError, match=re.escape(said)):  # (it was "bad frame spec {...}" alone)
            client.call("capture", rig=rig, frames=[frame])
    for count in (10**12, 0, True, 2.5):  # 10**12 was "needs a positive frame count"
        with pytest.raises(DaemonError, match=f"a whole number from 1 to 10,000,000, got {count}"):
            client.call("stream", rig=rig, count=count)
    for angle in (1e308, -1e308, float("nan"), float("inf")):
        with pytest.raises(DaemonError, match="within ±3600") as exc:
            client.call("move", rig=rig, angle=angle)
    assert client.call("move", rig=rig, angle=90.0)["angle"] == pytest.approx(90.0)


def test_several_clients_at_once(daemon):
    _, first = daemon
    results: dict[int, list[int]] = {}
    errors: list[BaseException] = []

    def work(i: int) -> None:
        try:
            with DaemonClient(first.endpoint, first.token, timeout_s=10) as c:
                rig = c.call("open_rig", camera="sim:bench-camera", options={"shape": [256, 256, 3], "seed": i})["rig"]
                seqs = []
                for f in c.stream(rig, 60):
                    seqs.append(f.seq)
                    assert f.data.shape == (256, 256, 3)
                    c.call("status") if f.seq % 20 == 0 else None
                results[i] = seqs
        except BaseException as exc:  # surfaced in the main thread
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    assert all(results[i] == list(range(60)) for i in range(4))


def test_daemon_sigterm_exits_cleanly_and_removes_its_socket(fresh_daemon):
    proc, client, runtime = fresh_daemon
    sock_path = client.endpoint[len("ipc://"):]
    assert os.path.exists(sock_path)
    second = subprocess.run([sys.executable, "-m", "sssphase_daemon"], capture_output=True, text=True, timeout=30,
                            env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    assert second.returncode == 2 and f"another daemon (pid {proc.pid})" in second.stderr
    assert client.ping()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
    assert not os.path.exists(sock_path) and security.read_state(runtime / "daemon.json") is None


def test_preview_publishes_subsampled_frames_without_slowing_the_stream(daemon_factory):
    _, client, runtime = daemon_factory("--preview", "ipc://{runtime}/preview.sock")
    endpoint = client.call("hello")["preview"]
    assert endpoint.startswith("ipc://")
    subs = []
    for password in (client.token, "wrong"):  # subscribers log in like job streams (PLAIN, the token)
        sub = zmq.Context.instance().socket(zmq.SUB)
        sub.linger = 0
        sub.plain_username, sub.plain_password = security.STREAM_USER.encode(), password.encode()
        sub.subscribe(b"preview")
        sub.connect(endpoint)
        subs.append(sub)
    time.sleep(0.3)  # let the subscription reach the publisher
    rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": [64, 96, 3]})["rig"]
    frames = list(client.stream(rig, 50))
    assert [f.seq for f in frames] == list(range(50))  # the lossless stream is complete
    previews = []
    while subs[0].poll(200):
        _, header, data = subs[0].recv_multipart()
        previews.append(protocol.decode_frame(msgpack.unpackb(header), data))
    assert not subs[1].poll(100)  # without the token nothing arrives
    for sub in subs:
        sub.close()
    assert 0 < len(previews) <= 50  # the preview may drop frames
    assert np.array_equal(previews[0], frames[0].data[::4, ::4])  # the bench camera repeats one frame


def test_a_daemon_started_for_one_capture_is_left_running_while_another_client_uses_it(tmp_path, monkeypatch):
    """The first `sss capture` stopped the daemon it had started while a second capture, which had found
    it running, was mid-view: the second one failed with 'did not answer within 10 s'."""
    from sssphase_daemon.client import local_client

    runtime = Path(tempfile.mkdtemp(prefix="sssl", dir="/tmp"))  # ipc paths must stay short
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))
    events: list[str] = []
    try:
        with local_client(on_start=lambda pid: events.append("start"), on_stop=lambda pid: events.append("stop"),
                          on_left=lambda pid: events.append("left")) as first:
            pid = first.call("status")["pid"]
            second = DaemonClient.from_state(timeout_s=5.0)
            rig = second.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})["rig"]
        assert events == ["start", "left"]
        assert second.call("status")["pid"] == pid  # still serving the second client
        second.call("close_rig", rig=rig)
        with local_client(on_stop=lambda pid: events.append("stop"), on_left=lambda pid: events.append("left")):
            pass  # it did not start this one: it leaves it alone
        assert events == ["start", "left"]
        second.call("shutdown", timeout_s=2.0)
        second.close()
    finally:
        shutil.rmtree(runtime, ignore_errors=True)


EXITING_PLUGIN = '''
import sys
from sssphase_plugins.api import DeviceInfo, hookimpl

__version__ = "1.0"


class Camera:
    def __init__(self, device_id):
        self.info = DeviceInfo(device_id, "camera", "exiting", "exits", device_id)

    def configure(self, **kw):
        pass

    def grab(self, timeout_s=5.0):
        if self.info.id == "exiting:cancel":  # an asyncio driver's error: a BaseException, not an Exception
            import asyncio

            raise asyncio.CancelledError()
        if self.info.id == "exiting:raise":
            raise RuntimeError("grab exploded")
        if self.info.id == "exiting:abort":  # a driver's C library that aborts: the daemon dies with it
            import os

            os.abort()
        sys.exit(4)

    def stream(self, count):
        return (self.grab() for _ in range(count))

    def close(self):
        pass


class Provider:
    kind = "camera"

    def discover(self):
        return [DeviceInfo(f"exiting:{n}", "camera", "exiting", n, n)
                for n in ("open", "grab", "junk", "cancel", "raise", "openraise", "abort")]

    def open(self, device_id, options, shared):
        if device_id == "exiting:open":
            sys.exit(3)
        if device_id == "exiting:openraise":
            raise RuntimeError("open exploded")
        return 7 if device_id == "exiting:junk" else Camera(device_id)


@hookimpl
def sssphase_cameras():
    return [Provider()]

'''


def test_a_plugin_that_exits_or_returns_no_driver_fails_its_request_not_the_daemon(daemon_factory, tmp_path, monkeypatch):
    """sys.exit() in a plugin's open() ended the daemon without a line in its log, in grab() it left the job
    "running" for ever (the client hung); an int from open() was "internal: AttributeError ... 'close'"."""
    from sssphase_daemon.client import DaemonError

    (tmp_path / "exiting_plugin.py").write_text(EXITING_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "exiting_plugin")
    proc, client, _ = daemon_factory()
    with pytest.raises(DaemonError, match=r"exiting:open \(open\): a device plugin called sys.exit\(3\)"):
        client.call("open_rig", camera="exiting:open")  # (the plugin was not named)
    with pytest.raises(DaemonError, match="open.. of the plugin of exiting:junk returned int, not a camera driver"):
        client.call("open_rig", camera="exiting:junk")
    rig = client.call("open_rig", camera="exiting:grab")["rig"]
    with pytest.raises(DaemonError, match=r"exiting:grab \(stream\): a device plugin called sys.exit\(4\)"):
        list(client.stream(rig, 2))
    # a driver's own errors name the device and the call (they said "RuntimeError: open exploded" alone), and a
    # BaseException that is no Exception (asyncio's CancelledError) ended the job's thread: the client waited for
    # ever and the daemon could not be stopped
    with pytest.raises(DaemonError, match=r"exiting:openraise \(open\): RuntimeError: open exploded"):
        client.call("open_rig", camera="exiting:openraise")
    for name, said in (("raise", "RuntimeError: grab exploded"), ("cancel", "CancelledError: \\(no message\\)")):
        rig = client.call("open_rig", camera=f"exiting:{name}")["rig"]
        with pytest.raises(DaemonError, match=f"exiting:{name} \\(stream\\): {said}"):
            list(client.stream(rig, 2))
    assert proc.poll() is None and client.ping(timeout_s=2.0)


QUIRKY_PLUGIN = '''
import datetime
from pathlib import Path

import numpy as np
from sssphase_plugins.api import DeviceInfo, hookimpl
from sssphase_plugins.drivers import Frame, ShowReceipt


class Camera:
    def __init__(self, device_id):
        self.info = DeviceInfo(device_id, "camera", "quirky", "quirky", device_id)
        self.n = 0

    def configure(self, **kw):
        pass

    def grab(self, timeout_s=5.0):
        self.n += 1
        data = np.full((8, 8, 3), 0.5, np.float32)
        if self.info.id == "quirky:ndarray":
            return data
        meta = {"temperature": np.float32(41.5), "gain_db": np.int64(6), "taken": datetime.datetime(2026, 12, 5, 11),
                "file": Path("/tmp/x.raw"), "roi": (np.uint16(0), np.uint16(8)), "hist": np.arange(4)}
        if self.info.id == "quirky:object":
            meta["sensor"] = {"handle": object()}
        if self.info.id == "quirky:stale":
            return Frame(data, 7, 7000, 1.0, {})
        if self.info.id == "quirky:textstamp":
            return Frame(data, self.n, "y", 1.0, {})
        return Frame(data, np.int64(self.n), np.uint64(1000 * self.n), np.float32(1.0), meta)

    def stream(self, count):
        return (self.grab() for _ in range(count))

    def close(self):
        pass


class Provider:
    kind = "camera"

    def discover(self):
        return [DeviceInfo(f"quirky:{n}", "camera", "quirky", n, n)
                for n in ("numpy", "object", "ndarray", "stale", "textstamp", "alias")]

    def open(self, device_id, options, shared):
        return Camera("quirky:numpy" if device_id == "quirky:alias" else device_id)


@hookimpl
def sssphase_cameras():
    return [Provider()]


class Projector:
    def __init__(self, device_id):
        self.info = DeviceInfo(device_id, "projector", "quirky", "quirky", device_id)
        self.resolution = (8, 8)
        self.last = "none yet"

    def show(self, image, *, tag="", confirm=True):
        shown, self.last = self.last, tag
        if self.info.id == "quirky:noreceipt":
            return None
        return ShowReceipt(1, shown if self.info.id == "quirky:lagging" else tag, 1)

    def close(self):
        pass


class Projectors:
    kind = "projector"

    def discover(self):
        return [DeviceInfo(f"quirky:{n}", "projector", "quirky", n, n) for n in ("noreceipt", "lagging", "good")]

    def open(self, device_id, options, shared):
        return Projector(device_id)


@hookimpl
def sssphase_projectors():
    return [Projectors()]
'''


def test_numpy_values_in_a_frames_meta_arrive_as_numbers_and_an_object_is_named_by_its_key(daemon_factory, tmp_path,
                                                                                           monkeypatch):
    """A numpy float in Frame.meta failed the job with msgpack's bare "can not serialize 'numpy.float32' object";
    a driver returning the bare array was "not an image array (memoryview ...)"."""
    from sssphase_daemon.client import DaemonError

    (tmp_path / "quirky_plugin.py").write_text(QUIRKY_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "quirky_plugin")
    proc, client, _ = daemon_factory()
    rig = client.call("open_rig", camera="quirky:numpy")["rig"]
    frames = list(client.stream(rig, 2))
    client.call("close_rig", rig=rig)  # (its camera serves the projectors' captures below)
    assert len(frames) == 2 and frames[1].header["meta"] == {
        "temperature": 41.5, "gain_db": 6, "taken": "2026-12-05T11:00:00", "file": "/tmp/x.raw", "roi": [0, 8],
        "hist": [0, 1, 2, 3]}
    rig = client.call("open_rig", camera="quirky:object")["rig"]
    with pytest.raises(DaemonError, match=r"quirky:object: frame 'stream/1': its meta\['sensor.handle'\] is of type object, "
                                          "which a frame's header cannot carry"):
        list(client.stream(rig, 2))
    rig = client.call("open_rig", camera="quirky:stale")["rig"]  # (a stuck buffer passed as a session of one image)
    with pytest.raises(DaemonError, match=r"quirky:stale: frame 'stream/7' repeats the previous frame's sequence 7 and "
                                          r"timestamp 7000: a stale buffer"):
        list(client.stream(rig, 3))
    rig = client.call("open_rig", camera="quirky:textstamp")["rig"]  # (blamed on the next frame's grab)
    with pytest.raises(DaemonError, match=r"quirky:textstamp: frame 'stream/1' has timestamp_ns 'y' of type str: a "
                                          "whole number"):
        list(client.stream(rig, 2))
    rig = client.call("open_rig", camera="quirky:ndarray")["rig"]
    with pytest.raises(DaemonError, match=r"quirky:ndarray: frame 'stream/\d+' came back as numpy.ndarray, not a "
                                          r"sssphase_plugins.api.Frame"):
        list(client.stream(rig, 1))
    # a projector's show() answered with None, or with the receipt of the pattern before: the camera was exposed
    # whatever was on screen, and the capture went on
    frames = [f for f in json.loads(capture_plan(8, 8, references=("white", "black")).to_json())["frames"]
              if f["kind"] in ("white", "black")]
    rig = client.call("open_rig", camera="quirky:numpy", projector="quirky:good")["rig"]
    assert [f.name for f in client.capture(rig, frames)] == [f["name"] for f in frames]
    client.call("close_rig", rig=rig)
    rig = client.call("open_rig", camera="quirky:numpy", projector="quirky:noreceipt")["rig"]
    with pytest.raises(DaemonError, match=r"quirky:noreceipt: show\(\) of pattern '\w+' came back as NoneType, not a "
                                          r"sssphase_plugins.api.ShowReceipt"):
        list(client.capture(rig, frames))
    client.call("close_rig", rig=rig)
    rig = client.call("open_rig", camera="quirky:numpy", projector="quirky:lagging")["rig"]
    with pytest.raises(DaemonError, match=r"quirky:lagging: show\(\) of pattern '\w+' confirmed pattern 'none yet'"):
        list(client.capture(rig, frames))
    # a driver that calls itself another device: held under that id, its own was not refused to a second client
    with pytest.raises(DaemonError, match=r"open\(\) of quirky:alias returned a driver whose info.id is 'quirky:numpy'"):
        client.call("open_rig", camera="quirky:alias")
    assert proc.poll() is None and client.ping(timeout_s=2.0)


NUMPY_PLUGIN = '''
import os
import threading

import numpy as np
from sssphase_plugins.api import DeviceInfo, ShowReceipt, check_pattern, hookimpl

STUCK = threading.Event()


class Projector:
    def __init__(self, device_id, resolution):
        self.info = DeviceInfo(device_id, "projector", "npdev", "np", device_id)
        self.resolution = resolution
        self.n = 0

    def show(self, image, *, tag="", confirm=True):
        self.n += 1
        check_pattern(image, (256, 192), self.info.id)
        return ShowReceipt(self.n, tag, self.n)

    def close(self):
        pass


class Projectors:
    kind = "projector"

    def discover(self):
        return [DeviceInfo("npdev:numpy", "projector", "npdev", "np", "1"),
                DeviceInfo("npdev:text", "projector", "npdev", "np", "2")]

    def open(self, device_id, options, shared):
        return Projector(device_id, (np.int64(256), np.int64(192)) if device_id == "npdev:numpy" else ("256", "192"))


class Cameras:
    kind = "camera"

    def discover(self):
        if os.environ.get("NPDEV_CAMERAS") == "hang":
            STUCK.wait()
        return [DeviceInfo("npdev:cam", "camera", "npdev", "np", np.int64(42))]

    def open(self, device_id, options, shared):
        raise NotImplementedError


@hookimpl
def sssphase_projectors():
    return [Projectors()]


@hookimpl
def sssphase_cameras():
    return [Cameras()]
'''


def test_numpy_values_in_a_drivers_description_and_a_hung_discovery_hold_no_rig_and_no_daemon(daemon_factory, tmp_path,
                                                                                              monkeypatch):
    """A projector's resolution of numpy integers failed the open_rig reply after the rig was held (its camera then
    "in use by rig ... of another client"); a numpy serial in discovery hung `devices` for 40 s; a discover() that
    hangs held the daemon's discovery lock in open_rig for ever ("restart the daemon")."""
    from sssphase_daemon.client import DaemonError

    (tmp_path / "npdev_plugin.py").write_text(NUMPY_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "npdev_plugin")
    monkeypatch.setenv("SSS_DISCOVERY_TIMEOUT_S", "1")
    monkeypatch.setenv("NPDEV_CAMERAS", "hang")
    proc, client, _ = daemon_factory()
    opened = client.call("open_rig", camera="sim:camera0", projector="npdev:numpy", options={"object": "star"})
    assert opened["projector_size"] == [256, 192]
    client.call("close_rig", rig=opened["rig"])
    with pytest.raises(DaemonError, match=r"npdev:text: its resolution must be \(width, height\) in whole pixels, got "
                                          r"\('256', '192'\)"):
        client.call("open_rig", camera="sim:camera0", projector="npdev:text", options={"object": "star"})
    t0 = time.monotonic()
    with pytest.raises(DaemonError, match=r"npdev:cam was not found, and plugin npdev_plugin's discovery of cameras (did "
                                          r"not return within 1 s|has not returned for \d+ s) \(the plugin hangs\)"):
        client.call("open_rig", camera="npdev:cam", timeout_s=20.0)
    assert time.monotonic() - t0 < 5.0
    rig = client.call("open_rig", camera="sim:camera0", projector="sim:projector0", options={"object": "star"})["rig"]
    assert client.call("close_rig", rig=rig)  # the daemon keeps serving the other devices
    listed = client.call("devices", timeout_s=20.0)
    assert "has not returned for" in listed["errors"]["npdev_plugin"], listed["errors"]
    assert client.call("status")["rigs"] == [] and proc.poll() is None


SLOW_PLUGIN = """
import time
from sssphase_plugins.api import DeviceInfo, hookimpl


class Provider:
    kind = "camera"

    def discover(self):
        time.sleep(3.0)  # a USB bus that takes seconds to enumerate
        return [DeviceInfo("slow:cam", "camera", "slow", "slow", "1")]

    def open(self, device_id, options, shared):
        raise NotImplementedError


@hookimpl
def sssphase_cameras():
    return [Provider()]
"""


def test_a_slow_plugin_discovery_does_not_hold_the_daemon(daemon_factory, tmp_path, monkeypatch):
    """Discovery ran on the control thread: while a plugin enumerated its bus, nothing was answered, not even
    the heartbeats of a running capture (cancelled as if its client had died)."""
    import threading

    from sssphase_daemon.client import DaemonClient

    (tmp_path / "slow_plugin.py").write_text(SLOW_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "slow_plugin")
    proc, client, _ = daemon_factory()
    found: dict = {}
    asker = threading.Thread(target=lambda: found.update(client.call("devices", timeout_s=20.0)))
    asker.start()
    time.sleep(0.5)  # the discovery is under way
    with DaemonClient(client.endpoint, client.token, timeout_s=5.0) as other:
        t0 = time.monotonic()
        assert other.ping(timeout_s=2.0) and time.monotonic() - t0 < 1.0  # answered while the plugin enumerates
        both = other.call("devices", timeout_s=20.0)  # a second request shares the discovery under way
    asker.join(timeout=20)
    assert time.monotonic() - t0 < 5.0 and {d["id"] for d in both["devices"]} == {d["id"] for d in found["devices"]}
    assert "slow:cam" in {d["id"] for d in found["devices"]} and proc.poll() is None


def test_a_client_cannot_start_more_jobs_or_open_more_rigs_than_the_daemon_holds(daemon_factory):
    """3,000 one-frame jobs never read took the daemon to 1,025 threads and ZeroMQ's socket limit: every
    later capture then failed with "Too many open files", and shutting down took a minute."""
    from sssphase_daemon.client import DaemonError
    from sssphase_daemon.server import MAX_OPEN_RIGS, MAX_RUNNING_JOBS

    proc, client, _ = daemon_factory()
    rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})["rig"]
    for _ in range(MAX_RUNNING_JOBS):
        client.call("stream", rig=rig, count=1_000_000)  # never read: each job stays running
    with pytest.raises(DaemonError, match=f"{MAX_RUNNING_JOBS} capture jobs are running"):
        client.call("stream", rig=rig, count=1)
    for _ in range(MAX_OPEN_RIGS - 1):
        client.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})
    with pytest.raises(DaemonError, match=f"{MAX_OPEN_RIGS} rigs are open"):
        client.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})
    assert client.ping(timeout_s=2.0)


def test_a_rig_or_job_id_of_the_wrong_type_is_refused_naming_it(daemon):
    """A list as ``job`` or ``rig`` was answered "bad_args: TypeError: unhashable type: 'list'"."""
    _, client = daemon
    for op, name in (("heartbeat", "job"), ("job", "job"), ("cancel", "job"), ("close_rig", "rig"), ("stream", "rig")):
        with pytest.raises(DaemonError, match=rf"{name} must be a {name} id \(a string\), not list") as err:
            client.call(op, **{name: [1, 2]}, count=1)
        assert err.value.code == protocol.BAD_ARGS
    assert client.ping()


def test_rigs_of_clients_gone_silent_make_room_for_new_ones_and_their_clients_are_told_why(daemon_factory):
    """Sixteen clients that opened a rig and then died between captures (no job running) held every rig slot for
    five minutes: every later `sss capture` was refused with "16 rigs are open: close one first", which no user could
    do. At the limit, the rig of the client silent longest is taken back; that client, back, is told why."""
    from sssphase_daemon.server import MAX_OPEN_RIGS

    proc, client, _ = daemon_factory("--client-timeout", "0.5")
    gone = []
    for _ in range(MAX_OPEN_RIGS):
        with DaemonClient(client.endpoint, client.token, timeout_s=5.0) as dead:
            gone.append(dead.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})["rig"])
    time.sleep(1.0)  # silent for longer than the client timeout
    new = client.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})["rig"]
    rigs = {r["rig"] for r in client.call("status")["rigs"]}
    assert new in rigs and gone[0] not in rigs and set(gone[1:]) <= rigs  # only the oldest taken back
    with pytest.raises(DaemonError, match=r"the daemon closed it \(16 rigs were open and its client had been silent "
                                          r"for \d+ s\); open the rig again"):
        client.call("close_rig", rig=gone[0])
    with pytest.raises(DaemonError, match=r"no open rig 'nosuchrig'$"):  # (a rig it never had: no reason made up)
        client.call("close_rig", rig="nosuchrig")


def test_sss_bench_soak_shows_a_daemon_ending_idle_where_it_started(tmp_path):
    """Clients that crashed mid-stream (a notebook killed) left their rigs open for five minutes; the sixteenth
    filled the daemon and every later client was refused. Through `sss bench soak`: streaming clients, crashing
    ones, malformed requests and a capture; no client meets an error and the idle daemon after the cycles holds no
    rig, job, descriptor or thread more than after the warm-up."""
    from sss_process import run_sss

    out = tmp_path / "soak.json"
    res = run_sss(["bench", "soak", "--cycles", "20", "--capture-every", "10", "--frames", "5", "--out", str(out)],
                  timeout=300)
    assert res.returncode == 0, res.stderr
    r = json.loads(out.read_text())
    assert r["errors"] == [] and r["captures"] == 2 and r["streamed_frames"] == 20 * 5
    assert all(s["malformed_answered"] for s in r["samples"])
    warm, after = r["idle_warm"], r["idle_after"]
    assert after["rigs"] == after["jobs_running"] == 0 and after["waited_s"] < 10
    assert after["fds"] <= warm["fds"] + 2 and after["threads"] <= warm["threads"] + 1  # (20 leaked would show)
    assert "| open rigs | 0 | 0 | +0 |" in (tmp_path / "soak.md").read_text()


def test_an_interrupt_while_a_local_daemon_starts_stops_it(runtime_dir, monkeypatch):
    """Ctrl-C while `sss capture` waited for the daemon it had started left that daemon running, detached,
    and later captures reused it without ever stopping it."""
    from sssphase_daemon import client as client_module

    started: list[subprocess.Popen] = []
    popen = subprocess.Popen

    def recording(*args, **kwargs):
        started.append(popen(*args, **kwargs))
        return started[-1]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(client_module.subprocess, "Popen", recording)
    monkeypatch.setattr(client_module.security, "read_state", interrupted)
    with pytest.raises(KeyboardInterrupt):
        client_module.spawn_daemon()
    assert len(started) == 1 and started[0].poll() is not None  # stopped, not left running


def test_clients_started_together_with_no_daemon_all_get_the_same_one(monkeypatch):
    """Four front ends (`sss capture`, `sss view`) started at once with no daemon running: one starts it, the
    others attach to it; none fails with "the daemon exited with status 2"."""
    runtime = Path(tempfile.mkdtemp(prefix="sssr", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime)}
    code = ("import time\nfrom sssphase_daemon import security\nfrom sssphase_daemon.client import local_client\n"
            "with local_client() as c:\n"
            "    rig = c.call('open_rig', camera='sim:bench-camera', options={'shape': [8, 8, 3]})['rig']\n"
            "    print(security.read_state().pid, flush=True)\n"
            "    time.sleep(1.5)\n"
            "    c.call('close_rig', rig=rig)\n")
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=env) for _ in range(4)]
    try:
        results = [p.communicate(timeout=120) for p in procs]
        assert all(p.returncode == 0 for p in procs), [r[1][-500:] for r in results]
        pids = {out.split()[0] for out, _ in results}
        assert len(pids) == 1, pids  # one daemon served them all
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        subprocess.run([sys.executable, "-m", "sssphase_cli.main", "daemon", "stop", "--force"], env=env, capture_output=True,
                       timeout=60)
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_daemon_started_for_a_capture_exits_once_unused(daemon_factory):
    """An interrupted or killed `sss capture` could leave the daemon it started running for ever: the daemon it
    starts (`--exit-when-idle`) now ends itself once no rig, job or client has been seen for that long."""
    proc, client, path = daemon_factory("--exit-when-idle", "1")
    rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": [4, 4, 3]})["rig"]
    time.sleep(2.0)  # an open rig keeps it (the rig's owner may be at the "turn the object" prompt)
    assert proc.poll() is None
    client.call("close_rig", rig=rig)
    deadline = time.monotonic() + 10
    while proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.returncode == 0 and not (path / "daemon.json").exists()


def test_the_daemon_a_capture_starts_for_itself_is_told_to_exit_when_unused(tmp_path, monkeypatch):
    from sssphase_daemon import client as client_module

    asked: list[tuple[str, ...]] = []

    def spawn(*, extra_args=(), **kwargs):
        asked.append(tuple(extra_args))
        raise KeyboardInterrupt  # (nothing is started here)

    monkeypatch.setenv("SSS_RUNTIME_DIR", str(tmp_path))  # no daemon runs there
    monkeypatch.setattr(client_module, "spawn_daemon", spawn)
    with pytest.raises(KeyboardInterrupt), client_module.local_client():
        pass
    assert asked == [("--exit-when-idle", str(client_module.LOCAL_DAEMON_IDLE_S))]


def test_a_job_found_ended_in_a_quiet_stream_is_reported_in_the_daemon_s_words(monkeypatch):
    """The client's check of a quiet stream and the daemon's device deadline fired together (2 runs in 8): the
    user read "the job ended (failed) but its stream did not finish" where the daemon named the stalled device."""
    from sssphase_daemon.client import DaemonClient, DaemonError

    client = DaemonClient("ipc:///nonexistent/sss.sock", "token", timeout_s=1.0)
    said = "cam0 (grab psp/x/p18/s0) did not answer within 5 s (stalled or disconnected)"
    monkeypatch.setattr(client, "call", lambda *a, **k: {"state": "failed", "error": {"code": "device", "message": said}})
    with pytest.raises(DaemonError, match=re.escape(said)):
        client._check_job("j1")
    monkeypatch.setattr(client, "call", lambda *a, **k: {"state": "failed", "error": None})
    with pytest.raises(DaemonError, match=r"the job ended \(failed\) but its stream did not finish"):
        client._check_job("j1")


HANGING_PLUGIN = """
import os, time
from sssphase_plugins.api import hookimpl


@hookimpl
def sssphase_cameras():
    while os.path.exists(os.environ["SSS_TEST_HANG_FLAG"]):  # a driver stuck in a USB call
        time.sleep(0.05)
    return []
"""


def test_a_plugin_hung_in_its_hook_holds_only_its_own_request(daemon_factory, tmp_path, monkeypatch):
    """A plugin hook that never returned held the daemon's main thread: no client was answered, `sss daemon
    stop --force` sent SIGTERM and left it running for ever. open_rig is now answered from a thread, with a
    deadline (SSS_OPEN_TIMEOUT_S) that names what hangs; the daemon keeps answering and stops."""
    from sss_process import run_sss

    from sssphase_daemon.client import DaemonError

    flag = tmp_path / "hang"
    (tmp_path / "hanging_plugin.py").write_text(HANGING_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "hanging_plugin")
    monkeypatch.setenv("SSS_TEST_HANG_FLAG", str(flag))
    monkeypatch.setenv("SSS_OPEN_TIMEOUT_S", "1.5")
    proc, client, runtime = daemon_factory()
    flag.touch()
    with pytest.raises(DaemonError, match=r"the plugins' hooks or discover\(\) \(finding sim:camera0\) did not return within 1.5 s"):
        client.call("open_rig", camera="sim:camera0", timeout_s=5.0)
    assert client.ping(timeout_s=2.0)  # the daemon answers meanwhile
    with pytest.raises(DaemonError, match=r"finding sim:camera0: another request's device discovery has not returned"):
        client.call("open_rig", camera="sim:camera0", timeout_s=5.0)
    res = run_sss(["daemon", "stop", "--force"], env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    assert proc.wait(10) is not None and "stopped" in res.stdout, res.stdout + res.stderr


def test_stop_force_kills_a_daemon_that_ignores_sigterm(tmp_path, monkeypatch):
    """A daemon that SIGTERM does not end (a device call no signal interrupts) was left running for ever."""
    import subprocess
    import sys

    from sssphase_cli import cmd_daemon
    from sssphase_daemon import security

    proc = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                             "print('ready', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    monkeypatch.setattr(security, "is_daemon_process", lambda pid: proc.poll() is None)
    monkeypatch.setattr(security, "state_path", lambda: tmp_path / "daemon.json")
    os.kill(proc.pid, signal.SIGTERM)  # ignored
    assert cmd_daemon._wait_or_kill(proc.pid, False, 0.3) is False and proc.poll() is None
    assert cmd_daemon._wait_or_kill(proc.pid, True, 0.3) is False
    assert proc.wait(5) == -signal.SIGKILL


def test_a_device_is_held_by_one_rig_at_a_time(daemon_factory):
    """Two captures opened the same (emulated Basler) camera in two rigs and drove its exposure and grabs
    together; a second rig now waits for the first to close, and a rig whose client is gone is taken over."""
    from sssphase_daemon.client import DaemonClient, DaemonError

    proc, first, runtime = daemon_factory()
    held = first.call("open_rig", camera="example:testpattern0")["rig"]
    with DaemonClient(first.endpoint, first.token, timeout_s=5.0) as second:
        with pytest.raises(DaemonError, match=rf"example:testpattern0 is in use by rig {held} of another client"):
            second.call("open_rig", camera="example:testpattern0")
        assert second.call("open_rig", camera="sim:camera0")["rig"]  # simulated devices are shared
        assert second.call("open_rig", camera="sim:camera0")["rig"]
        first.call("close_rig", rig=held)
        assert second.call("open_rig", camera="example:testpattern0")["rig"] != held


def test_a_daemon_that_a_plugin_crashed_is_said_to_have_exited(daemon_factory, tmp_path, monkeypatch):
    """A plugin that called abort() took the daemon down mid-capture; the client said only that it "stopped
    answering mid-stream"."""
    from sssphase_daemon.client import DaemonUnavailable

    (tmp_path / "exiting_plugin.py").write_text(EXITING_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "exiting_plugin")
    proc, client, runtime = daemon_factory()
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))  # where the client finds the daemon's state file
    rig = client.call("open_rig", camera="exiting:abort")["rig"]
    client.timeout_s = 30.0  # (said when the process is gone, not after this long without a frame: the live view
    started = time.monotonic()  # showed "no frame for 14 s (waiting for the rig)" after a daemon was killed)
    with pytest.raises(DaemonUnavailable, match=rf"the daemon \(pid {proc.pid}\) at .* has exited \(killed, or "
                                                 "crashed by a device plugin: its log is"):
        list(client.stream(rig, 2))
    assert time.monotonic() - started < 10
    assert proc.wait(5) == -signal.SIGABRT


CLOSE_HANGING_PLUGIN = '''
import os, time
import numpy as np
from sssphase_plugins.api import DeviceInfo, Frame, hookimpl


class Camera:
    def __init__(self, device_id):
        self.info = DeviceInfo(device_id, "camera", "closehang", "hangs in close", device_id)

    def configure(self, **kw):
        pass

    def grab(self, timeout_s=5.0):
        return Frame(np.zeros((4, 4, 3), np.float32), 0, time.monotonic_ns(), 1.0, {})

    def stream(self, count):
        return (self.grab() for _ in range(count))

    def close(self):
        while os.path.exists(os.environ["SSS_TEST_HANG_FLAG"]):  # a driver stuck in a USB call
            time.sleep(0.05)


class Provider:
    kind = "camera"

    def discover(self):
        return [DeviceInfo("closehang:cam", "camera", "closehang", "hangs in close", "cam")]

    def open(self, device_id, options, shared):
        return Camera(device_id)


@hookimpl
def sssphase_cameras():
    return [Provider()]
'''


def test_a_device_whose_close_hangs_holds_neither_the_daemon_nor_its_clients(daemon_factory, tmp_path, monkeypatch):
    """close_rig ran the plugin's close() on the daemon's main thread: one that never returned left the daemon
    answering no one ("runs but does not answer"). The close now runs in a thread of its own: close_rig is answered
    within CLOSE_REPLY_S naming the device, other clients meanwhile, and the device cannot be opened again (busy,
    named) until its close returns."""
    flag = tmp_path / "hang"
    (tmp_path / "closehang_plugin.py").write_text(CLOSE_HANGING_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "closehang_plugin")
    monkeypatch.setenv("SSS_TEST_HANG_FLAG", str(flag))
    monkeypatch.setenv("SSS_OPEN_TIMEOUT_S", "2")  # open_rig waits for a closing device for half of it
    proc, client, runtime = daemon_factory()
    rig = client.call("open_rig", camera="closehang:cam")["rig"]
    flag.touch()
    pings: list[float] = []

    def ping_meanwhile() -> None:
        with DaemonClient(client.endpoint, client.token, timeout_s=3.0) as other:
            time.sleep(0.3)  # while close_rig waits for the close
            t0 = time.monotonic()
            other.call("ping", timeout_s=3.0)
            pings.append(time.monotonic() - t0)

    pinger = threading.Thread(target=ping_meanwhile)
    pinger.start()
    t0 = time.monotonic()
    closed = client.call("close_rig", timeout_s=5.0, rig=rig)
    assert time.monotonic() - t0 < 3.0
    assert closed["closed"] == rig and "closehang:cam did not close within" in closed["note"], closed
    pinger.join(10)
    assert pings and pings[0] < 1.0, pings
    t0 = time.monotonic()
    assert client.ping(timeout_s=2.0) and time.monotonic() - t0 < 1.0
    assert rig not in {r["rig"] for r in client.call("status")["rigs"]}
    with pytest.raises(DaemonError, match=r"closehang:cam is still closing: the close\(\) of closehang:cam has not "
                                          r"returned for \d+ s \(its plugin hangs\)") as exc:
        client.call("open_rig", camera="closehang:cam", timeout_s=5.0)
    assert exc.value.code == protocol.BUSY
    assert client.call("open_rig", camera="sim:camera0")["rig"]  # other devices open meanwhile
    flag.unlink()  # the close returns: the device can be opened again
    assert client.call("open_rig", camera="closehang:cam", timeout_s=5.0)["rig"]


SLOW_GRAB_PLUGIN = '''
import os, threading, time
import numpy as np
from sssphase_plugins.api import DeviceInfo, Frame, hookimpl


class Camera:
    """A grab takes 0.4 s (an exposure); close() notes whether a grab was under way (a vendor SDK aborts then)."""

    def __init__(self, device_id):
        self.info = DeviceInfo(device_id, "camera", "slowgrab", "slow grabs", device_id)
        self.grabbing = threading.Event()

    def configure(self, **kw):
        pass

    def grab(self, timeout_s=5.0):
        self.grabbing.set()
        time.sleep(0.4)
        self.grabbing.clear()
        return Frame(np.zeros((4, 4, 3), np.float32), 0, time.monotonic_ns(), 1.0, {})

    def stream(self, count):
        return (self.grab() for _ in range(count))

    def close(self):
        with open(os.environ["SSS_TEST_CLOSE_LOG"], "a") as log:
            log.write("closed during a grab\\n" if self.grabbing.is_set() else "closed\\n")


class Provider:
    kind = "camera"

    def discover(self):
        return [DeviceInfo("slowgrab:cam", "camera", "slowgrab", "slow grabs", "cam")]

    def open(self, device_id, options, shared):
        return Camera(device_id)


@hookimpl
def sssphase_cameras():
    return [Provider()]
'''


def test_sigterm_while_streaming_closes_the_camera_after_its_grab_under_way(daemon_factory, tmp_path, monkeypatch):
    """At SIGTERM the daemon closed its rigs while a cancelled stream's grab was still in the driver: pylon then
    aborted the daemon (exit -6 instead of 0). The close now waits for the device call under way."""
    closes = tmp_path / "closes.txt"
    (tmp_path / "slowgrab_plugin.py").write_text(SLOW_GRAB_PLUGIN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("SSS_PLUGINS", "slowgrab_plugin")
    monkeypatch.setenv("SSS_TEST_CLOSE_LOG", str(closes))
    proc, client, runtime = daemon_factory()
    rig = client.call("open_rig", camera="slowgrab:cam")["rig"]
    frames = client.stream(rig, 100)
    next(frames)  # the next grab is under way
    time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0
    assert closes.read_text() == "closed\n"


def test_open_rig_refuses_options_no_plugin_reads(daemon):
    """A misspelt plugin table was handed to the plugins, none of which read it: the rig opened with defaults."""
    _, client = daemon
    before = len(client.call("status")["rigs"])
    with pytest.raises(DaemonError, match=r"rig options \[options.basle\]: no installed device plugin has that name") as exc:
        client.call("open_rig", camera="sim:camera0", options={"object": "star", "basle": {"gain": 0}})
    assert exc.value.code == protocol.BAD_ARGS
    with pytest.raises(DaemonError, match=r"rig options exposure_us are outside every plugin's table"):
        client.call("open_rig", camera="example:testpattern0", options={"exposure_us": 1000})
    assert len(client.call("status")["rigs"]) == before  # nothing was opened


def test_a_daemon_does_not_start_beside_another_of_the_same_state_file():
    """Each daemon checked that no other one served, then (later) wrote its state file: two started together both
    found none, both served, and the state file named only one; the other ran invisibly, holding devices. The state
    file's lock is now held from that check until the daemon has removed its state file."""
    from sssphase_daemon.server import Daemon

    folder = Path(tempfile.mkdtemp(prefix="sssl", dir="/tmp"))
    state = folder / "daemon.json"
    try:
        first = Daemon(f"ipc://{folder}/a.sock", token="t" * 32, state_file=state)  # starting: no state file yet
        with pytest.raises(PermissionError, match=rf"another daemon is starting \(its state file: {state}\): stop it first"):
            Daemon(f"ipc://{folder}/b.sock", token="t" * 32, state_file=state)
        first.write_state()
        with pytest.raises(PermissionError, match=rf"another daemon \(pid {os.getpid()}\) is serving ipc://{folder}/a.sock"):
            Daemon(f"ipc://{folder}/b.sock", token="t" * 32, state_file=state)
        assert security.read_state(state).endpoint == f"ipc://{folder}/a.sock"  # the second wrote nothing
        first.close()
        second = Daemon(f"ipc://{folder}/b.sock", token="t" * 32, state_file=state)  # once the first is gone
        second.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_two_daemon_starts_at_once_start_one_daemon(tmp_path):
    """`sss daemon start` and `sss daemon start --endpoint tcp://...` run together both said "daemon started"."""
    import socket

    from sss_process import run_sss

    runtime = Path(tempfile.mkdtemp(prefix="ssst", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime)}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    results: list[subprocess.CompletedProcess] = []
    starts = [threading.Thread(target=lambda a=args: results.append(run_sss(["daemon", "start", *a], env=env)))
              for args in ((), ("--endpoint", f"tcp://127.0.0.1:{port}"))]
    try:
        for t in starts:
            t.start()
        for t in starts:
            t.join(120)
        said = sorted((r.returncode, (r.stdout + r.stderr).strip()) for r in results)
        assert [rc for rc, _ in said] == [0, 2], said
        assert said[0][1].startswith("daemon started") and said[1][1] == "error: a daemon is already running " \
                                                                          "(`sss daemon status`)", said
        pid = security.read_state(runtime / "daemon.json").pid
        assert f"(pid {pid})" in said[0][1]
    finally:
        run_sss(["daemon", "stop", "--force"], env=env)
        shutil.rmtree(runtime, ignore_errors=True)


def test_keys_are_not_replaced_under_a_daemon_that_uses_them(tmp_path, monkeypatch):
    """`sss daemon keys --overwrite` while a CURVE daemon ran replaced its keys: every later local command said the
    daemon "runs but does not answer". It is refused, naming the daemon; other keys may still be replaced."""
    from sssphase_cli import cmd_daemon
    from sssphase_core.errors import InputError

    keys = security.generate_keys(tmp_path / "curve")
    secret = (keys / "server.key_secret").read_bytes()
    monkeypatch.setattr(security, "state_path", lambda: tmp_path / "daemon.json")
    security.write_state(security.DaemonState("tcp://127.0.0.1:5599", "t" * 32, 4242, "0", time.time(),
                                              curve_dir=str(keys)), tmp_path / "daemon.json")
    monkeypatch.setattr(security, "is_daemon_process", lambda pid, started=None: pid == 4242)
    with pytest.raises(InputError, match=rf"the daemon \(pid 4242\) serving tcp://127.0.0.1:5599 uses the CURVE keys "
                                         rf"in {keys}: stop it first \(`sss daemon stop`\), then replace them"):
        cmd_daemon.daemon_keys(directory=tmp_path / "curve", overwrite=True)
    assert (keys / "server.key_secret").read_bytes() == secret
    cmd_daemon.daemon_keys(directory=tmp_path / "other", overwrite=True)  # keys no daemon uses
    monkeypatch.setattr(security, "is_daemon_process", lambda pid, started=None: False)  # the daemon is gone
    cmd_daemon.daemon_keys(directory=tmp_path / "curve", overwrite=True)
    assert (keys / "server.key_secret").read_bytes() != secret
