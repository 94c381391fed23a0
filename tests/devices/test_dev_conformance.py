"""Device conformance: every driver the project ships or shows (the sim plugin, the example third-party
plugin, each hardware plugin against its fake) behaves as the protocols of ``sssphase_plugins.api`` say.

One suite for all drivers, as python-microscope's device tests do: a new plugin adds a factory to
``DEVICES`` and gets the same checks. Hardware-specific behaviour stays in the per-plugin test files.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable

import numpy as np
import pytest

from sssphase_plugins import api
from sssphase_plugins.conformance import ConformanceError, check_driver

# --- factories: each opens one driver through its provider, as the daemon does -------------------------


def _sim(kind: str, device_id: str) -> Callable[[], object]:
    def make():
        from sssphase_plugins import sim_plugin

        hook = {"camera": sim_plugin.sssphase_cameras, "projector": sim_plugin.sssphase_projectors,
                "turntable": sim_plugin.sssphase_turntables}[kind]
        (provider,) = hook()
        assert device_id in {d.id for d in provider.discover()}
        return provider.open(device_id, {}, {})
    return make


def _example_camera():
    mod = pytest.importorskip("sssphase_example_plugin", reason="the example plugin is not installed")
    (provider,) = mod.sssphase_cameras()
    (info,) = provider.discover()
    return provider.open(info.id, {}, {})


def _uvc_camera():
    from dev_fakes import FakeCapture

    from sssphase_plugins import uvc_camera

    info = api.DeviceInfo("uvc:046d:0825:ABC", "camera", "uvc", "Webcam C270", "ABC")
    provider = uvc_camera.UvcProvider(cameras=lambda: [(info, "/dev/video0")], open_capture=lambda path: FakeCapture())
    return provider.open(info.id, {}, {})


def _oak_camera():
    from dev_fakes import FakeDepthai

    from sssphase_plugins import oak_camera

    dai = FakeDepthai()
    provider = oak_camera.OakProvider(dai=lambda: dai)
    (info,) = provider.discover()
    return provider.open(info.id, {}, {})


def _basler_camera():
    """A real vendor SDK: pypylon's camera emulation (its test image, software-triggered)."""
    pytest.importorskip("pypylon", reason="pypylon (extra basler) is not installed")
    import os

    from sssphase_plugins import basler_camera

    before = os.environ.get("PYLON_CAMEMU")
    os.environ["PYLON_CAMEMU"] = "1"  # read by pylon at each enumeration: only while opening
    try:
        return basler_camera.BaslerProvider().open("basler:0815-0000", {"basler": {"roi": [0, 0, 64, 48]}}, {})
    finally:
        if before is None:
            del os.environ["PYLON_CAMEMU"]
        else:
            os.environ["PYLON_CAMEMU"] = before


def _hdmi_projector():
    pytest.importorskip("pygame")
    import os

    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    from sssphase_plugins import hdmi_projector

    provider = hdmi_projector.HdmiProvider()
    (info,) = provider.discover()
    return provider.open(info.id, {"hdmi": {"latency_s": 0.0}}, {})


def _lightcrafter(mode: str) -> Callable[[], object]:
    def make():
        from dev_fakes import FakeDlpc350Hid, FakeHidApi, FakeWindow

        from sssphase_plugins import lightcrafter

        dev, window = FakeDlpc350Hid(), FakeWindow()
        provider = lightcrafter.LightCrafterProvider(hid_api=lambda: FakeHidApi(dev),
                                                     displays=lambda: [(1920, 1080), (912, 1140)],
                                                     window=lambda display, **kw: window)
        (info,) = provider.discover()
        return provider.open(info.id, {"lcr4500": {"mode": mode, "latency_s": 0}}, {})
    return make


def _serial(kind: str) -> Callable[[], object]:
    def make():
        pytest.importorskip("serial")
        from dev_fakes import FakeBoard

        from sssphase_plugins import serial_devices

        board = FakeBoard()
        provider = serial_devices.SerialProvider(kind, boards=lambda: [("B1", "/dev/ttyACM0", "board")],
                                                 connect=lambda port: board)
        (info,) = provider.discover()
        return provider.open(info.id, {"serial": {"timeout_s": 0.2}}, {})
    return make


DEVICES: dict[str, tuple[str, Callable[[], object]]] = {
    "sim camera": ("camera", _sim("camera", "sim:camera0")),
    "sim projector": ("projector", _sim("projector", "sim:projector0")),
    "sim turntable": ("turntable", _sim("turntable", "sim:turntable0")),
    "example camera": ("camera", _example_camera),
    "uvc camera": ("camera", _uvc_camera),
    "oak camera": ("camera", _oak_camera),
    "basler camera (pylon emulator)": ("camera", _basler_camera),
    "hdmi projector": ("projector", _hdmi_projector),
    "lightcrafter (video mode)": ("projector", _lightcrafter("video")),
    "lightcrafter (pattern mode)": ("projector", _lightcrafter("pattern")),
    "serial trigger": ("trigger", _serial("trigger")),
    "serial turntable": ("turntable", _serial("turntable")),
}
def test_every_kind_has_a_driver_under_test():
    assert {k for k, _ in DEVICES.values()} == set(api.DEVICE_KINDS)


@pytest.mark.parametrize(("kind", "make"), [pytest.param(k, make, id=name) for name, (k, make) in DEVICES.items()])
def test_each_driver_passes_the_public_conformance_checks(kind, make):
    """The checks a third-party plugin runs from its own tests (``sssphase_plugins.conformance``), on every driver
    this project ships or shows: identity, the kind's protocol, closing twice."""
    check_driver(kind, make)


class _Sloppy:
    """A camera a plugin author might write first: exposure 0 accepted, frames as bare arrays."""

    info = api.DeviceInfo("acme:0", "camera", "acme", "first try", "0")

    def configure(self, **kw):
        pass

    def grab(self, timeout_s=5.0):
        return np.zeros((4, 4, 3), np.float32)

    def stream(self, count):
        return [self.grab() for _ in range(count)]

    def close(self):
        pass


def test_a_driver_that_breaks_a_rule_is_told_which():
    with pytest.raises(ConformanceError, match=r"acme:0: configure\(exposure=0\) must raise DeviceError: it raised "
                                               "nothing"):
        check_driver("camera", _Sloppy)
    sloppy = _Sloppy()
    sloppy.configure = lambda exposure=None, **kw: (_ for _ in ()).throw(api.DeviceError("bad")) if exposure <= 0 else None
    with pytest.raises(ConformanceError, match="acme:0: a frame is a ndarray, not a Frame"):
        check_driver("camera", lambda: sloppy)
    for frame, said in ((api.Frame(np.zeros((4, 4), np.float32), 1, 1, 1.0), r"an \(H, W\) frame is a raw Bayer mosaic"),
                        (api.Frame(np.zeros((4, 4, 3)), 1, "y", 1.0), "Frame.timestamp_ns is 'y', not a whole number"),
                        (api.Frame(np.zeros((4, 4, 3)), 1, 1, 1.0, {"h": object()}), r"its meta\['h'\] is of type object")):
        sloppy.grab = lambda timeout_s=5.0, frame=frame: frame  # (each passed the checks, and failed every capture)
        with pytest.raises(ConformanceError, match=said):
            check_driver("camera", lambda: sloppy)
    with pytest.raises(ConformanceError, match="kind must be one of"):
        check_driver("camra", _Sloppy)


def test_the_example_plugin_uses_only_the_public_api():
    spec = importlib.util.find_spec("sssphase_example_plugin")
    if spec is None:
        pytest.skip("the example plugin is not installed")
    source = open(spec.origin).read()
    assert "from sssphase_plugins.api import" in source
    assert "sssphase_plugins.drivers" not in source and "sssphase_plugins.hookspecs" not in source
