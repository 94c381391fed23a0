"""The Basler plugin against a real vendor SDK: pypylon's camera emulation (``PYLON_CAMEMU``), which
implements the GenICam feature tree, grab engine, buffers and trigger model of Basler's cameras, and
streams image files a test writes. Then a whole ``sss capture`` through the daemon and the SDK, checked
against the sim camera's own capture of the same object and seed."""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
from sss_process import run_sss

pylon = pytest.importorskip("pypylon.pylon", reason="pypylon (extra basler) is not installed")
cv2 = pytest.importorskip("cv2")

from sssphase_plugins import basler_camera  # noqa: E402
from sssphase_plugins.drivers import DeviceError, DeviceNotFound  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


@pytest.fixture
def emulator(monkeypatch):
    """Two emulated cameras (pylon reads PYLON_CAMEMU at each enumeration)."""
    monkeypatch.setenv("PYLON_CAMEMU", "2")


def open_camera(device_id: str = "basler:0815-0000", **options):
    return basler_camera.BaslerProvider().open(device_id, {"basler": {"roi": [0, 0, 64, 48], **options}}, {})


def write_mosaic(path: Path, mosaic: np.ndarray, bits: int = 12) -> None:
    """What the emulator streams: 16-bit PNG, ``v << (16 - bits)`` gives the value ``v``."""
    assert cv2.imwrite(str(path), (mosaic.astype(np.uint16) << np.uint16(16 - bits)))


def test_discovery_lists_the_emulated_cameras_by_serial(emulator, monkeypatch):
    ids = [d.id for d in basler_camera.BaslerProvider().discover()]
    assert ids == ["basler:0815-0000", "basler:0815-0001"]
    monkeypatch.setenv("PYLON_CAMEMU", "0")
    with pytest.raises(DeviceNotFound, match="no device found: pylon sees no Basler camera"):
        basler_camera.BaslerProvider().discover()


def test_sss_devices_lists_both_emulated_cameras(tmp_path):
    env = {**os.environ, "PYLON_CAMEMU": "2", "SSS_RUNTIME_DIR": str(tmp_path)}  # no daemon there: local discovery
    res = run_sss(["devices", "--json"], env=env, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "basler:0815-0000" in res.stdout and "basler:0815-0001" in res.stdout


def test_raw_bayer_frames_arrive_exactly_with_their_layout_and_depth(emulator, tmp_path):
    rng = np.random.default_rng(0)
    first, second = (rng.integers(0, 4096, (48, 64)).astype(np.uint16) for _ in range(2))
    feed = tmp_path / "feed.png"
    write_mosaic(feed, first)
    cam = open_camera(pixel_format="BayerRG12", image_file=str(feed))
    try:
        a = cam.grab()
        write_mosaic(feed, second)  # rewritten between grabs: read afresh
        b = cam.grab()
    finally:
        cam.close()
    np.testing.assert_array_equal(a.data, first)
    np.testing.assert_array_equal(b.data, second)
    assert a.data.dtype == np.uint16 and a.meta["raw"] and a.meta["bayer"] == "RGGB" and a.meta["bit_depth"] == 12
    assert a.meta["pixel_format"] == "BayerRG12" and "black_level" in a.meta
    assert (a.sequence, b.sequence) == (0, 1) and b.timestamp_ns > a.timestamp_ns


@pytest.mark.parametrize(("asked", "expected"), [("auto", "BayerGR12"), ("BayerBG8", "BayerBG8"), ("Mono12", "Mono12"),
                                                 ("RGB8Packed", "RGB8Packed")])
def test_pixel_formats(emulator, asked, expected):
    cam = open_camera(pixel_format=asked)
    try:
        frame = cam.grab()
    finally:
        cam.close()
    fmt = basler_camera.parse_format(expected)
    assert frame.meta["pixel_format"] == expected
    if fmt.raw:
        assert frame.data.shape == (48, 64) and frame.meta["bayer"] == fmt.layout and frame.meta["bit_depth"] == fmt.bits
    else:  # colour and mono: linear float RGB in [0, 1]
        assert frame.data.shape == (48, 64, 3) and frame.data.dtype == np.float32 and "bayer" not in frame.meta
        assert 0 <= frame.data.min() and frame.data.max() <= 1 and frame.data.max() > 0
        if fmt.kind == "mono":
            assert (frame.data[..., 0] == frame.data[..., 2]).all()


def test_refusals_are_one_line_naming_the_problem(emulator):
    with pytest.raises(DeviceError, match=r"pixel format 'YUV422Packed': this camera does not offer it; use one of Mono8"):
        open_camera(pixel_format="YUV422Packed")
    with pytest.raises(DeviceError, match=r"roi must be \[offset_x, offset_y, width, height\]"):
        open_camera(roi=[0, 0, 64])
    with pytest.raises(DeviceError, match="trigger must be one of software, Line1"):
        open_camera(trigger="Line9")
    with pytest.raises(DeviceError, match="unknown \\[options.basler\\] setting\\(s\\) exposure"):
        open_camera(exposure=2)
    with pytest.raises(DeviceError, match=r"no Basler camera 'basler:nope' \(attached: basler:0815-0000, basler:0815-0001"):
        open_camera("basler:nope")
    cam = open_camera()
    try:
        with pytest.raises(DeviceError, match=r"ExposureTime = 1e\+13 is out of the camera's range"):
            cam.configure(exposure=1e9)
        assert cam.cam.ExposureTime.Value == 10_000  # unchanged, and the camera still works
        cam.configure(exposure=2.0)
        assert cam.cam.ExposureTime.Value == 20_000 and cam.grab().exposure == 2.0
        with pytest.raises(DeviceError, match="must be positive"):
            cam.configure(exposure=0)
    finally:
        cam.close()


def test_a_camera_open_elsewhere_is_one_line(emulator, monkeypatch):
    """pylon refuses a camera another program holds (the emulator shares its cameras, so its refusal is raised
    where pylon raises it)."""
    def refuse(self):
        raise pylon.RuntimeException("Failed to open device: the device is controlled by another application.")

    monkeypatch.setattr(pylon.InstantCamera, "Open", refuse)
    with pytest.raises(DeviceError, match="cannot open the camera: it is open in another program"):
        open_camera()



class _Recording:
    """A pylon camera that records the waits it is asked for (the emulator does not take an exposure's time)."""

    def __init__(self, cam, waits, frames=True):
        self._cam, self._waits, self._frames = cam, waits, frames

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def WaitForFrameTriggerReady(self, ms, handling):  # noqa: N802 (pylon's name)
        self._waits.append(("ready", ms))
        return self._cam.WaitForFrameTriggerReady(ms, handling)

    def RetrieveResult(self, ms, handling):  # noqa: N802
        if ms:  # (0: the drain of frames already waiting)
            self._waits.append(("frame", ms))
            if not self._frames:
                return None
        return self._cam.RetrieveResult(ms, handling)


def test_a_grab_waits_for_the_exposure_and_the_timeout(emulator):
    """The wait for a frame was timeout_s (5 s) whatever the exposure: an 8 s exposure failed with "no frame within
    5 s". It is now the exposure under way plus timeout_s."""
    cam = open_camera(exposure_us=8_000_000, timeout_s=5)
    waits: list[tuple[str, int]] = []
    try:
        cam.cam = _Recording(cam.cam, waits)
        cam.grab()
        assert waits == [("ready", 13_000), ("frame", 13_000)]
        waits.clear()
        cam.configure(exposure=0.25)  # a short HDR bracket: 2 s
        cam.grab(timeout_s=1.0)
        assert waits == [("ready", 3_000), ("frame", 3_000)]
        cam.cam = _Recording(cam.cam._cam, waits, frames=False)
        with pytest.raises(DeviceError, match=r"no frame within 7 s \(the 2 s exposure and 5 s more\): the camera sent "
                                              r"nothing"):
            cam.grab()
    finally:
        cam.cam = getattr(cam.cam, "_cam", cam.cam)
        cam.close()


def test_buffers_go_back_to_pylon(emulator):
    """Each result is released once its pixels are copied: 25 times more frames than buffers never stall."""
    cam = open_camera(buffers=2, pixel_format="BayerRG8")
    try:
        frames = [cam.grab() for _ in range(50)]
        assert cam.cam.NumQueuedBuffers.Value + cam.cam.NumReadyBuffers.Value == 2  # both back in the queue
    finally:
        cam.close()
    assert [f.sequence for f in frames] == list(range(50)) and frames[-1].meta["dropped_frames"] == 0
    assert [f.meta["block_id"] for f in frames] == list(range(50))


def test_a_gap_in_the_camera_frame_counter_counts_as_dropped(emulator):
    cam = open_camera()
    try:
        cam.grab()
        frame = cam._frame(np.zeros((48, 64), np.uint16), block=5, stamp=0)  # the camera skipped blocks 1-4
    finally:
        cam.close()
    assert frame.meta["dropped_frames"] == 4


def test_a_hardware_trigger_that_never_comes_is_a_timeout_naming_the_line(emulator):
    cam = open_camera(trigger="Line1", timeout_s=0.3)
    try:
        assert cam.cam.TriggerSource.Value == "Line1" and cam.cam.TriggerActivation.Value == "RisingEdge"
        with pytest.raises(DeviceError, match=r"no frame within 0.31 s \(the 0.01 s exposure and 0.3 s more\): the trigger never came: is the projector's "
                                              r"trigger output wired to Line1"):
            cam.wait_frame()
    finally:
        cam.close()
    soft = open_camera()
    try:
        with pytest.raises(DeviceError, match="a rig with a trigger device needs \\[options.basler\\] trigger"):
            soft.wait_frame()
    finally:
        soft.close()


def test_a_camera_gone_mid_capture_is_one_line_and_close_stays_harmless(emulator):
    cam = open_camera()
    cam.grab()
    cam.cam.DestroyDevice()  # as an unplugged camera: pylon's device is gone under the driver
    with pytest.raises(DeviceError, match="the camera is gone while grabbing a frame .* --resume"):
        cam.grab()
    cam.close()
    cam.close()


def test_raw_frames_develop_with_the_camera_levels_unless_the_rig_file_gives_its_own():
    from sssphase_core.capture.plan import RigSpec
    from sssphase_core.capture.processing import develop_frame, raw_levels
    from sssphase_core.errors import DataError

    meta = {"bayer": "RGGB", "bit_depth": 12, "black_level": 64.0}
    assert raw_levels(RigSpec(), meta) == (64.0, 4095.0 - 64.0)  # linear 1.0: the sensor's full scale
    assert raw_levels(RigSpec(black_level=256, white_scale=1000), meta) == (256.0, 1000.0)
    full = develop_frame(np.full((8, 8), 4095, np.uint16), RigSpec(median=False), 1.0, "RGGB", meta)
    np.testing.assert_allclose(full, 1.0, rtol=1e-6)
    with pytest.raises(DataError, match="set \\[processing\\] black_level and white_scale"):
        raw_levels(RigSpec(), {"bayer": "RGGB"})


# --- end to end: sss capture through the daemon, the plugin and pylon's grab engine ---------------------

RIG = """[devices]
camera = "basler:0815-0000"
projector = "feed:projector0"
turntable = "sim:turntable0"

[options]
object = "star"
seed = 3
n_views = 2

[options.feed]
image_file = "{feed}"

[options.basler]
pixel_format = "BayerRG12"
roi = [0, 0, {width}, {height}]
image_file = "{feed}"

[processing]
black_level = {black}
white_scale = {white}
median = false
"""


def _sss(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return run_sss([*args], env=env, cwd=REPO, timeout=300)


@pytest.mark.slow
def test_sss_capture_through_the_emulated_basler_matches_the_sim_camera(tmp_path):
    from sssphase_core.sim import rig_preset
    from sssphase_core.store.session import Session

    preset = rig_preset("cpu")
    runtime = Path(tempfile.mkdtemp(prefix="sssb", dir="/tmp"))
    env = {**os.environ, "PYLON_CAMEMU": "1", "SSS_PLUGINS": "emulator_feed", "SSS_RUNTIME_DIR": str(runtime),
           "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    rig = dict(feed=tmp_path / "feed.png", width=preset.camera.width, height=preset.camera.height,
               black=preset.sensor.black_level, white=preset.sensor.dn_per_unit(1.0))
    try:
        # a frame lost on the way (the emulator finds no image for it) in view 1: one line, view 0 kept
        (tmp_path / "rig.toml").write_text(RIG.format(**rig))
        res = _sss("capture", "--rig", str(tmp_path / "rig.toml"), "--object", "star", "--views", "2",
                   "--out", str(tmp_path / "basler"), env={**env, "SSS_FEED_LOSE_FRAME_AT": "40"})
        out = res.stdout + res.stderr
        assert res.returncode != 0 and "Traceback" not in out, out
        assert "basler:0815-0000: the frame was lost: Failed to load image file" in out, out
        assert Session.open(tmp_path / "basler" / "star").status(0) == "complete"
        _sss("daemon", "stop", env=env)  # the next one starts without the fault
        res = _sss("capture", "--rig", str(tmp_path / "rig.toml"), "--object", "star", "--views", "2", "--resume",
                   "--out", str(tmp_path / "basler"), env=env)
        assert res.returncode == 0, res.stdout + res.stderr
        res = _sss("capture", "--object", "star", "--views", "2", "--seed", "3", "--out", str(tmp_path / "sim"), env=env)
        assert res.returncode == 0, res.stdout + res.stderr
    finally:
        _sss("daemon", "stop", env=env)
    basler, sim = Session.open(tmp_path / "basler" / "star"), Session.open(tmp_path / "sim" / "star")
    assert basler.manifest["devices"]["camera"]["id"] == "basler:0815-0000"
    assert basler.manifest["devices"]["camera"]["plugin"] == "basler"
    for view in (0, 1):
        isp = basler.manifest["views"][str(view)]["camera_isp"]
        assert isp["bayer"] == "RGGB" and isp["bit_depth"] == 12 and isp["black_level"] == preset.sensor.black_level
        mask, ref = basler.load(view, "corr/mask").astype(bool), sim.load(view, "corr/mask").astype(bool)
        assert abs(int(mask.sum()) - int(ref.sum())) <= 0.005 * ref.sum() and mask.sum() > 1000
        both = mask & ref
        for key in ("corr/xp", "corr/yp"):
            assert np.median(np.abs(basler.load(view, key) - sim.load(view, key))[both]) <= 0.01


@pytest.mark.slow
def test_bench_and_sigterm_through_a_daemon(tmp_path, monkeypatch):
    """`sss bench basler`'s runs count every frame on both sides; a daemon streaming from the camera ends
    cleanly on SIGTERM (pylon's grab threads do not hold the process)."""
    import signal

    from sssphase_daemon import camera_bench, security
    from sssphase_daemon.client import DaemonClient, spawn_daemon

    monkeypatch.setenv("PYLON_CAMEMU", "1")
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(tmp_path / "rt"))
    result, table = camera_bench.run_bench(12)
    assert os.environ["SSS_RUNTIME_DIR"] == str(tmp_path / "rt")  # the bench's own daemon dir is not left set
    assert result["daemon"]["frames"] == result["pypylon_triggered"]["frames"] == 12 and result["daemon"]["lost"] == 0
    assert result["daemon"]["shape"] == [1040, 1024] and result["daemon"]["dtype"] == "<u2"
    assert result["ratio"] > 0 and "through the daemon" in table
    proc = spawn_daemon()
    state = security.read_state()
    with DaemonClient(state.endpoint, state.token) as client:
        rig = client.call("open_rig", camera="basler:0815-0000", options={"basler": {"roi": [0, 0, 64, 48]}})["rig"]
        frames = client.stream(rig, 1000)
        next(frames)  # the camera is acquiring
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0


def test_bench_basler_names_the_cameras_pylon_sees_when_the_serial_is_not_one(monkeypatch):
    """`sss bench basler --serial 9999` was an "internal error: RuntimeError" telling to set PYLON_CAMEMU=1 with the
    emulator on, and with PYLON_CAMEMU=0 it looked for the emulator's serial."""
    from sssphase_core.errors import InputError
    from sssphase_daemon import camera_bench

    monkeypatch.setenv("PYLON_CAMEMU", "2")
    assert camera_bench.choose_serial(None) == "0815-0000"
    assert camera_bench.choose_serial("0815-0001") == "0815-0001"
    with pytest.raises(InputError, match=r"^pylon sees no camera 9999: it sees 0815-0000, 0815-0001$"):
        camera_bench.choose_serial("9999")
    res = run_sss(["bench", "basler", "--serial", "9999", "--out", "/nonexistent/b.json"], env={**os.environ})
    assert res.returncode != 0 and "internal error" not in res.stdout + res.stderr
    assert "pylon sees no camera 9999: it sees 0815-0000, 0815-0001" in res.stdout + res.stderr
