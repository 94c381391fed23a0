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
PROTOCOLS = {"camera": api.Camera, "projector": api.Projector, "trigger": api.Trigger, "turntable": api.Turntable}


def _of_kind(kind: str) -> list:
    return [pytest.param(make, id=name) for name, (k, make) in DEVICES.items() if k == kind]


@pytest.fixture
def opened(request):
    driver = request.param()
    yield driver
    driver.close()


def _identity(driver, kind: str) -> None:
    assert isinstance(driver, PROTOCOLS[kind])
    info = driver.info
    assert isinstance(info, api.DeviceInfo) and info.kind == kind
    assert info.id.startswith(info.plugin + ":") and info.model


def test_every_kind_has_a_driver_under_test():
    assert {k for k, _ in DEVICES.values()} == set(api.DEVICE_KINDS)


@pytest.mark.parametrize("opened", _of_kind("camera"), indirect=True)
def test_camera(opened):
    _identity(opened, "camera")
    with pytest.raises(api.DeviceError):
        opened.configure(exposure=0.0)
    with pytest.raises(api.DeviceError):
        opened.configure(exposure=-1.0)
    opened.configure(exposure=1.0)
    frames = [opened.grab()] + list(opened.stream(2))
    for f in frames:
        assert isinstance(f, api.Frame) and f.exposure > 0
        assert f.data.ndim == 2 or (f.data.ndim == 3 and f.data.shape[2] == 3), f.data.shape
        assert f.data.size and np.isfinite(f.data.astype(np.float64)).all()
    assert [f.sequence for f in frames] == sorted({f.sequence for f in frames})  # distinct, rising
    assert [f.timestamp_ns for f in frames] == sorted(f.timestamp_ns for f in frames)
    assert {f.data.shape for f in frames} == {frames[0].data.shape}


@pytest.mark.parametrize("opened", _of_kind("projector"), indirect=True)
def test_projector(opened):
    _identity(opened, "projector")
    w, h = opened.resolution
    assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
    ramp = np.broadcast_to(np.linspace(0, 1, w, dtype=np.float32), (h, w))
    first = opened.show(ramp, tag="grey")
    second = opened.show(np.zeros((h, w, 3), np.float32), tag="rgb")
    assert isinstance(first, api.ShowReceipt) and (first.tag, second.tag) == ("grey", "rgb")
    assert second.frame_id > first.frame_id and second.on_screen_ns >= first.on_screen_ns
    for wrong in (np.zeros((h + 1, w), np.float32), np.zeros((h, w, 4), np.float32), np.zeros(w, np.float32)):
        with pytest.raises(api.DeviceError):
            opened.show(wrong)
    if isinstance(opened, api.PreloadingProjector):
        opened.preload([("a", lambda: np.ones((h, w), np.float32))])
        assert opened.show(np.ones((h, w), np.float32), tag="a").tag == "a"


@pytest.mark.parametrize("opened", _of_kind("trigger"), indirect=True)
def test_trigger(opened):
    _identity(opened, "trigger")
    stamps = [opened.fire() for _ in range(3)]
    assert all(isinstance(t, int) for t in stamps) and stamps == sorted(set(stamps))


@pytest.mark.parametrize("opened", _of_kind("turntable"), indirect=True)
def test_turntable(opened):
    _identity(opened, "turntable")
    assert opened.move_to(90.0) == pytest.approx(90.0, abs=0.01)
    assert opened.angle == pytest.approx(90.0, abs=0.01)
    assert opened.move_to(450.0) % 360 == pytest.approx(90.0, abs=0.01)  # angles are taken modulo a turn


@pytest.mark.parametrize("make", [pytest.param(make, id=name) for name, (_k, make) in DEVICES.items()])
def test_close_twice_is_harmless(make):
    driver = make()
    driver.close()
    driver.close()


def test_the_example_plugin_uses_only_the_public_api():
    spec = importlib.util.find_spec("sssphase_example_plugin")
    if spec is None:
        pytest.skip("the example plugin is not installed")
    source = open(spec.origin).read()
    assert "from sssphase_plugins.api import" in source
    assert "sssphase_plugins.drivers" not in source and "sssphase_plugins.hookspecs" not in source
