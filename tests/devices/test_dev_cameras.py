"""UVC (OpenCV) and OAK (depthai) cameras against fake frame sources, including disconnects."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from dev_fakes import FakeCapture, FakeDepthai

from sssphase_plugins import oak_camera, uvc_camera
from sssphase_plugins.drivers import DeviceError, DeviceInfo, DeviceNotFound


def uvc(captures: list[FakeCapture], **opts):
    info = DeviceInfo("uvc:046d:0825:ABC", "camera", "uvc", "Webcam C270", "ABC")
    provider = uvc_camera.UvcProvider(cameras=lambda: [(info, "/dev/video0")], open_capture=lambda path: captures.pop(0))
    return provider.open(info.id, {"uvc": opts}, {})


def test_uvc_settings_and_linear_rgb_frames():
    cap = FakeCapture()
    cam = uvc([cap], width=32, height=24, fourcc="YUYV", exposure_us=5000, gain=2)
    assert cap.props[21] == 1 and cap.props[15] == 50  # manual exposure, 5000 us in V4L2's 100 us units
    assert cap.props[14] == 2 and cap.props[16] == 1  # gain; colour conversion on
    cam.configure(exposure=2.0)
    assert cap.props[15] == 100
    frame = cam.grab()
    assert frame.data.shape == (24, 32, 3) and frame.data.dtype == np.float32 and frame.exposure == 2.0
    assert cap.reads == 3  # two frames dropped while the new exposure takes effect
    np.testing.assert_allclose(frame.data[0, 0], uvc_camera.srgb_to_linear(np.array([250, 50, 3]) / 255), rtol=1e-6)
    assert cam.grab().sequence == 1 and cam.grab().timestamp_ns > frame.timestamp_ns


def test_uvc_raw_bayer_and_stale_frames_dropped():
    cap = FakeCapture(shape=(24, 32), dtype=np.uint16, stale=3)
    cam = uvc([cap], fourcc="BYR2")
    assert cap.props[16] == 0  # no conversion: the mosaic as delivered
    frame = cam.grab()
    assert frame.data.shape == (24, 32) and frame.data.dtype == np.uint16
    assert cap.reads == 4 and frame.data[0, 0] == 4  # three buffered frames predate the grab
    assert frame.meta["bayer"] == "BGGR"  # V4L2 BYR2 is SBGGR16: the daemon develops it in that layout
    assert "bayer" not in uvc([FakeCapture(shape=(24, 32), dtype=np.uint16)], fourcc="Y16 ").grab().meta  # the rig file says


def test_uvc_refused_exposure_is_an_error():
    with pytest.raises(DeviceError, match="refused exposure"):
        uvc([FakeCapture(refuse={15})])


def test_uvc_disconnect_mid_capture_then_reopen():
    cam = uvc([FakeCapture(fail_after=2), FakeCapture()])
    cam.grab(), cam.grab()
    assert cam.grab().sequence == 2  # one failed read: reopened by its ID, capture goes on
    cam2 = uvc([FakeCapture(fail_after=1), FakeCapture(fail_after=0)])
    cam2.grab()
    with pytest.raises(DeviceError, match="no frame from the camera.*disconnected"):
        cam2.grab()


def test_uvc_sysfs_discovery(tmp_path):
    usb = tmp_path / "devices" / "1-2"
    (usb / "1-2:1.0").mkdir(parents=True)
    for name, value in {"idVendor": "046d", "idProduct": "0825", "serial": "ABC", "product": "C270"}.items():
        (usb / name).write_text(value + "\n")
    root = tmp_path / "video4linux"
    for node, index in (("video0", "0"), ("video1", "1")):
        (root / node).mkdir(parents=True)
        (root / node / "index").write_text(index)
        (root / node / "name").write_text("Webcam C270")
        (root / node / "device").symlink_to(usb / "1-2:1.0")
    ((info, path),) = uvc_camera.list_cameras(root)
    assert (info.id, info.model, path) == ("uvc:046d:0825:ABC", "Webcam C270", "/dev/video0")
    with pytest.raises(DeviceNotFound, match="no device found"):
        uvc_camera.list_cameras(tmp_path / "missing")


def test_oak_manual_exposure_ir_off_and_fresh_frames():
    dai = FakeDepthai()
    dai.stale, dai.lag = 2, 0
    provider = oak_camera.OakProvider(dai=lambda: dai)
    (info,) = provider.discover()
    cam = provider.open(info.id, {"oak": {"exposure_us": 8000, "transfer": "linear"}}, {})
    assert dai.ir == {"dots": 0.0, "flood": 0.0} and (dai.exposure_us, dai.iso) == (8000, 100)
    frame = cam.grab()
    assert frame.data.shape == (8, 16, 3) and frame.data.dtype == np.float32
    assert frame.data[0, 0, 0] == pytest.approx(128 / 255)
    assert frame.meta["device_sequence"] == 3  # two frames exposed before the grab were dropped
    dai.lag = 2
    cam.configure(exposure=0.5, gain=4)
    frame = cam.grab()
    assert (dai.exposure_us, dai.iso) == (4000, 400) and frame.meta["exposure_us"] == pytest.approx(4000)
    assert frame.meta["device_sequence"] == 3  # frames still at the old exposure were dropped


def test_oak_raw10_unpacking():
    # pixels 1023, 0, 512, 3: high bytes FF 00 80 00, low bits 11 00 00 11 -> 0b11000011
    packed = np.array([0xFF, 0x00, 0x80, 0x00, 0b11000011], np.uint8)
    np.testing.assert_array_equal(oak_camera.unpack_raw10(packed, 4, 1, 5), [[1023, 0, 512, 3]])


def test_oak_disconnect_mid_capture():
    dai = FakeDepthai()
    cam = oak_camera.OakProvider(dai=lambda: dai).open("oak:1844301011B546F500", {}, {})
    cam.grab()
    dai.connected = False
    frame = cam.grab()  # X_LINK_ERROR: reopened by ID
    assert dai.opened == 2 and frame.sequence == 1
    dai.connected, dai.ids = False, []
    with pytest.raises(DeviceError, match="lost the camera mid-capture.*not attached"):
        cam.grab()


def test_oak_real_depthai_without_device():
    pytest.importorskip("depthai")
    with pytest.raises(DeviceNotFound, match="no device found: depthai sees no OAK"):
        oak_camera.OakProvider().discover()


def test_depthai_is_imported_with_its_telemetry_off_unless_the_user_set_it(tmp_path):
    """depthai 3 looks up its telemetry server on import (a DNS query): the plugin turns that off first."""
    pytest.importorskip("depthai")
    code = ("import os\nfrom sssphase_plugins import oak_camera\ntry:\n    oak_camera.OakProvider().discover()\n"
            "except Exception:\n    pass\nprint(os.environ['DEPTHAI_TELEMETRY'], os.environ['DEPTHAI_DISABLE_STARTUP_NOTIFICATIONS'])")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DEPTHAI_")} | {"HOME": str(tmp_path)}
    for preset, expected in (({}, ["0", "1"]), ({"DEPTHAI_TELEMETRY": "1"}, ["1", "1"])):
        done = subprocess.run([sys.executable, "-c", code], env=env | preset, capture_output=True, text=True, timeout=120)
        assert done.stdout.split()[-2:] == expected, done.stdout + done.stderr
