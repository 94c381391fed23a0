"""Every built-in hardware plugin declares the settings of its ``[options.<plugin>]`` table and their types
(``usb_util.check_plugin_options``): a misspelt setting was ignored (the device ran with its default),
``verify = "false"`` was read as true by ``bool()``, ``buffers = 0.5`` became 0 by ``int()`` and ``gain = "high"``
said only "ValueError: could not convert string to float". Each is now refused when the device opens, by name."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from typing import Any

import pytest

from sssphase_plugins import (
    basler_camera,
    hdmi_projector,
    lightcrafter,
    oak_camera,
    serial_devices,
    uvc_camera,
)
from sssphase_plugins.api import DeviceError, DeviceInfo, check_plugin_options


def _uvc(table: dict[str, Any]) -> object:
    from dev_fakes import FakeCapture

    info = DeviceInfo("uvc:046d:0825:ABC", "camera", "uvc", "Webcam C270", "ABC")
    provider = uvc_camera.UvcProvider(cameras=lambda: [(info, "/dev/video0")], open_capture=lambda path: FakeCapture())
    return provider.open(info.id, {"uvc": table}, {})


def _oak(table: dict[str, Any]) -> object:
    from dev_fakes import FakeDepthai

    dai = FakeDepthai()
    provider = oak_camera.OakProvider(dai=lambda: dai)
    (info,) = provider.discover()
    return provider.open(info.id, {"oak": table}, {})


def _hdmi(table: dict[str, Any]) -> object:
    from dev_fakes import FakeWindow

    provider = hdmi_projector.HdmiProvider(displays=lambda: [(640, 480)], window=FakeWindow)
    return provider.open("hdmi:display0", {"hdmi": table}, {})


def _lcr(table: dict[str, Any]) -> object:
    from dev_fakes import FakeDlpc350Hid, FakeHidApi, FakeWindow

    dev, window = FakeDlpc350Hid(), FakeWindow()
    provider = lightcrafter.LightCrafterProvider(hid_api=lambda: FakeHidApi(dev), displays=lambda: [(912, 1140)],
                                                 window=lambda display, **kw: window)
    (info,) = provider.discover()
    return provider.open(info.id, {"lcr4500": table}, {})


def _serial(table: dict[str, Any]) -> object:
    pytest.importorskip("serial")
    from dev_fakes import FakeBoard

    board = FakeBoard()
    provider = serial_devices.SerialProvider("trigger", boards=lambda: [("B1", "/dev/ttyACM0", "board")],
                                             connect=lambda port: board)
    (info,) = provider.discover()
    return provider.open(info.id, {"serial": table}, {})


def _basler(table: dict[str, Any]) -> object:
    pytest.importorskip("pypylon", reason="pypylon (extra basler) is not installed")
    before = os.environ.get("PYLON_CAMEMU")
    os.environ["PYLON_CAMEMU"] = "1"
    try:
        return basler_camera.BaslerProvider().open("basler:0815-0000", {"basler": {"roi": [0, 0, 64, 48], **table}}, {})
    finally:
        if before is None:
            del os.environ["PYLON_CAMEMU"]
        else:
            os.environ["PYLON_CAMEMU"] = before


OPEN: dict[str, Callable[[dict[str, Any]], object]] = {"uvc": _uvc, "oak": _oak, "hdmi": _hdmi, "lcr4500": _lcr,
                                                       "serial": _serial, "basler": _basler}
MODULES = {"uvc": uvc_camera, "oak": oak_camera, "hdmi": hdmi_projector, "lcr4500": lightcrafter,
           "serial": serial_devices, "basler": basler_camera}
REFUSED = [  # (plugin, its table, what it says)
    ("hdmi", {"latency": 0.1}, r"hdmi:display0: unknown \[options.hdmi\] setting\(s\) latency \(known: latency_s, "),
    ("hdmi", {"latency_s": "fast"}, r"\[options.hdmi\] latency_s must be a number of seconds >= 0, got 'fast'"),
    ("hdmi", {"verify": "false"}, r"\[options.hdmi\] verify must be true or false \(no quotes\), got 'false'"),
    ("hdmi", {"settle_frames": 1.5}, r"\[options.hdmi\] settle_frames must be a whole number >= 0, got 1.5"),
    ("oak", {"fsin": "false"}, r"\[options.oak\] fsin must be true or false \(no quotes\), got 'false'"),
    ("oak", {"raw": "false"}, r"\[options.oak\] raw must be true or false"),
    ("oak", {"transfer": "sRGB"}, r"\[options.oak\] transfer must be one of srgb, linear, got 'sRGB'"),
    ("oak", {"exposure": 8000}, r"unknown \[options.oak\] setting\(s\) exposure \(known: exposure_us, fsin, iso, "),
    ("uvc", {"gain": "high"}, r"uvc:046d:0825:ABC: \[options.uvc\] gain must be a number, got 'high'"),
    ("uvc", {"width": 640.5}, r"\[options.uvc\] width must be a whole number >= 1, got 640.5"),
    ("uvc", {"fourcc": "MJPEG"}, r"\[options.uvc\] fourcc must be 4 characters"),
    ("lcr4500", {"mode": "patern"}, r"\[options.lcr4500\] mode must be one of video, pattern, got 'patern'"),
    ("lcr4500", {"display": "1"}, r"\[options.lcr4500\] display must be a whole number >= 0, got '1'"),
    ("serial", {"baudrate": 115200.5}, r"\[options.serial\] baudrate must be a whole number >= 1, got 115200.5"),
    ("serial", {"baud": 9600}, r"unknown \[options.serial\] setting\(s\) baud \(known: baudrate, move_timeout_s, "),
    ("basler", {"gain": "high"}, r"basler:0815-0000: \[options.basler\] gain must be a number, got 'high'"),
    ("basler", {"black_level": "x"}, r"\[options.basler\] black_level must be a number, got 'x'"),
    ("basler", {"buffers": 0.5}, r"\[options.basler\] buffers must be a whole number >= 1, got 0.5"),
]


@pytest.mark.parametrize(("plugin", "table", "said"), REFUSED, ids=[f"{p}-{next(iter(t))}" for p, t, _ in REFUSED])
def test_an_unknown_setting_or_a_wrong_type_is_refused_by_name(plugin, table, said):
    with pytest.raises(DeviceError, match=said):
        OPEN[plugin](table)


@pytest.mark.parametrize("plugin", sorted(OPEN))
def test_each_plugin_opens_with_its_settings_as_documented(plugin):
    """The settings a plugin declares are the ones its docstring documents, and a table of valid ones opens."""
    module = MODULES[plugin]
    documented = set(re.findall(r"``([a-z_]+)``", module.__doc__ or ""))
    assert set(module.OPTIONS) <= documented, sorted(set(module.OPTIONS) - documented)
    valid = {"uvc": {"gain": 2, "transfer": "linear", "exposure_settle_frames": 0},
             "oak": {"fsin": False, "raw": False, "iso": 200}, "hdmi": {"verify": False, "latency_s": 0},
             "lcr4500": {"mode": "video", "latency_s": 0}, "serial": {"timeout_s": 0.2, "baudrate": 9600},
             "basler": {"gain": 0, "buffers": 4}}[plugin]
    driver = OPEN[plugin](valid)
    driver.close()


def test_the_shared_check_names_the_device_and_keeps_the_table():
    known = {"n": "count", "on": "bool", "kind": ("a", "b")}
    assert check_plugin_options({"n": 3, "on": True, "kind": "a"}, "acme", known) == {"n": 3, "on": True, "kind": "a"}
    with pytest.raises(DeviceError, match=r"^acme:1: \[options.acme\] on must be true or false \(no quotes\), got 1$"):
        check_plugin_options({"on": 1}, "acme", known, "acme:1")
    with pytest.raises(DeviceError, match=r"^acme: \[options.acme\] n must be a whole number >= 1, got True$"):
        check_plugin_options({"n": True}, "acme", known)
    with pytest.raises(DeviceError, match=r"^acme: \[options.acme\] kind must be one of a, b, got 1$"):
        check_plugin_options({"kind": 1}, "acme", known)
