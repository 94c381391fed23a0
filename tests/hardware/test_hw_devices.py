"""Tests against real devices (marked ``hardware``): each skips unless its device is attached.

Run on a bench with ``python -m pytest tests/hardware -m hardware -v``; see HARDWARE.md for the
checklist these tests support (what to look at while they run).
"""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_plugins.drivers import DeviceError

pytestmark = pytest.mark.hardware


def first_device(provider):
    try:
        devices = provider.discover()
    except DeviceError as exc:
        pytest.skip(str(exc))
    return devices[0]


def test_uvc_camera_grabs_frames_with_manual_exposure():
    from sssphase_plugins.uvc_camera import UvcProvider

    provider = UvcProvider()
    info = first_device(provider)
    cam = provider.open(info.id, {"uvc": {"exposure_us": 10_000}}, {})
    try:
        dark = cam.grab().data.mean()
        cam.configure(exposure=4.0)
        bright = cam.grab().data.mean()
        frames = [cam.grab() for _ in range(5)]
    finally:
        cam.close()
    assert bright >= dark  # longer exposure is not darker (manual exposure took effect)
    assert all(b.timestamp_ns > a.timestamp_ns for a, b in zip(frames, frames[1:], strict=False))


def test_oak_camera_full_resolution_and_ir_off():
    from sssphase_plugins.oak_camera import OakProvider

    provider = OakProvider()
    info = first_device(provider)
    cam = provider.open(info.id, {"oak": {"exposure_us": 8000}}, {})
    try:
        frame = cam.grab()
    finally:
        cam.close()
    assert frame.data.ndim == 3 and frame.data.shape[1] >= 1920
    assert abs(frame.meta["exposure_us"] - 8000) <= 400


def test_lightcrafter_pattern_mode_status():
    from sssphase_plugins.lightcrafter import NATIVE_RESOLUTION, LightCrafterProvider

    provider = LightCrafterProvider()
    info = first_device(provider)
    proj = provider.open(info.id, {"lcr4500": {"mode": "pattern"}}, {})
    try:
        status = proj.status()
        assert status["init_done"] and not status["errors"] and status["sequencer_running"]
        w, h = NATIVE_RESOLUTION
        for value in (0.0, 1.0, 0.5):
            proj.show(np.full((h, w), value, np.float32))
    finally:
        proj.close()


def test_hdmi_projector_show_roundtrip():
    from sssphase_plugins.hdmi_projector import HdmiProvider

    provider = HdmiProvider()
    info = first_device(provider)
    proj = provider.open(info.id, {"hdmi": {"verify": True}}, {})
    try:
        w, h = proj.resolution
        receipts = [proj.show(np.full((h, w), i % 2, np.float32), tag=str(i)) for i in range(30)]
    finally:
        proj.close()
    assert proj.window.vsync  # tear-free flips on a real display
    assert [r.tag for r in receipts] == [str(i) for i in range(30)]
    assert all(b.on_screen_ns > a.on_screen_ns for a, b in zip(receipts, receipts[1:], strict=False))


def test_serial_board_identifies_and_fires():
    from sssphase_plugins.serial_devices import SerialProvider

    provider = SerialProvider("trigger")
    info = first_device(provider)
    trigger = provider.open(info.id, {}, {})
    try:
        t0, t1 = trigger.fire(), trigger.fire()
    finally:
        trigger.close()
    assert t1 > t0
