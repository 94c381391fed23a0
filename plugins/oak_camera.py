"""Luxonis OAK camera plugin (``oak``), depthai v3 API (extra ``depthai``, imported only when used).

Discovery: ``dai.Device.getAllAvailableDevices()``; IDs are ``oak:<device id>`` (the MX ID / serial).
Opening builds a pipeline with one ``Camera`` node on the chosen socket (``CAM_A``, the colour
camera, by default) at full sensor resolution (``requestFullResolutionOutput``), switches the IR dot
projector and flood light off (OAK-D Pro; they would contaminate the fringes), and sets manual
exposure/ISO through the camera's control queue.

Options (``[options.oak]``): ``socket`` (``"CAM_A"``), ``exposure_us`` (reference exposure, default
10000; ``configure(exposure=r)`` sets ``r * exposure_us``), ``iso`` (default 100; ``configure(gain=g)``
sets ``g * iso``), ``raw`` (RAW10 sensor mosaic unpacked to uint16 ``(H, W)`` instead of ISP
colour), ``fsin`` (external trigger: each rising edge on the FSIN pin captures one frame),
``transfer`` (``"srgb"`` linearises the ISP output, default; ``"linear"``), ``timeout_s`` (5).

``grab`` returns the first frame whose exposure started after the call (older queued frames and
frames still at the previous exposure setting are dropped), so a frame never predates the pattern
shown before it. ``timestamp_ns`` is the start of the frame's exposure, host-synchronised (monotonic
clock). If
the device vanishes mid-capture (XLink error, closed queue) the camera is reopened once by its ID;
if that fails the grab raises a :class:`DeviceError`.
"""

from __future__ import annotations

import datetime
import os
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from sssphase_plugins.drivers import DeviceError, DeviceInfo, Frame
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import check_plugin_options, no_device, optional_import, plugin_options
from sssphase_plugins.uvc_camera import srgb_to_linear

PLUGIN = "oak"
#: ``[options.oak]``: each setting and its kind (``usb_util.OPTION_KINDS``).
OPTIONS = {"socket": "text", "exposure_us": "positive", "iso": "positive", "raw": "bool", "fsin": "bool",
           "transfer": ("srgb", "linear"), "timeout_s": "positive"}
EXPOSURE_TOLERANCE = 0.05


#: Set (unless the user set them) before depthai is imported: its telemetry looks up a server's address on
#: every import (a DNS query seen with strace on depthai 3.12 without an OAK attached; gone with
#: ``DEPTHAI_TELEMETRY=0``), and its start-up notifications are fetched from the web. The daemon makes no
#: connection beyond the rig: discovery still broadcasts on the local network for OAK PoE cameras.
DEPTHAI_OFFLINE = {"DEPTHAI_TELEMETRY": "0", "DEPTHAI_DISABLE_STARTUP_NOTIFICATIONS": "1"}


def _dai():
    for name, value in DEPTHAI_OFFLINE.items():
        os.environ.setdefault(name, value)
    return optional_import("depthai", "depthai", "depthai")


def unpack_raw10(data: np.ndarray, width: int, height: int, stride: int) -> np.ndarray:
    """MIPI CSI-2 RAW10 (4 pixels in 5 bytes: 4 high bytes, then their 2-bit low parts) -> uint16 (H, W)."""
    rows = np.asarray(data, np.uint8).reshape(-1)[:height * stride].reshape(height, stride)[:, :width * 5 // 4]
    groups = rows.reshape(height, width // 4, 5).astype(np.uint16)
    low = (groups[..., 4:5] >> np.arange(0, 8, 2, dtype=np.uint16)) & 3
    return ((groups[..., :4] << 2) | low).reshape(height, width)


def list_oaks(dai: Any) -> list[DeviceInfo]:
    infos = dai.Device.getAllAvailableDevices()
    if not infos:
        raise no_device("depthai sees no OAK device (USB 03e7:*): check the cable (USB 3), the power supply, "
                        "and the udev rules (sss udev install)")
    return [DeviceInfo(f"{PLUGIN}:{i.getDeviceId()}", "camera", PLUGIN, f"Luxonis OAK ({i.name})", i.getDeviceId())
            for i in infos]


class OakCamera:
    def __init__(self, info: DeviceInfo, dai: Any, options: Mapping[str, Any]) -> None:
        self.info, self.dai, self.opts = info, dai, check_plugin_options(options, PLUGIN, OPTIONS, info.id)
        self.base_exposure_us = float(self.opts.get("exposure_us", 10_000))
        self.base_iso = float(self.opts.get("iso", 100))
        self.exposure, self.gain = 1.0, 1.0
        self.raw = self.opts.get("raw", False)
        self.timeout = datetime.timedelta(seconds=float(self.opts.get("timeout_s", 5.0)))
        self.sequence = 0
        self.device: Any = None
        self._start()

    def _start(self) -> None:
        dai = self.dai
        match = [i for i in dai.Device.getAllAvailableDevices() if i.getDeviceId() == self.info.serial]
        if not match:
            raise DeviceError(f"{self.info.id}: not attached, or in use by another process")
        try:
            self.device = dai.Device(match[0])
            self.pipeline = dai.Pipeline(self.device)
            cam = self.pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, str(self.opts.get("socket", "CAM_A"))))
            if self.opts.get("fsin"):
                cam.initialControl.setFrameSyncMode(dai.CameraControl.FrameSyncMode.INPUT)
                cam.initialControl.setExternalTrigger(1, 0)
            out = cam.raw if self.raw else cam.requestFullResolutionOutput(dai.ImgFrame.Type.RGB888i)
            self.queue = out.createOutputQueue(maxSize=4, blocking=False)
            self.control = cam.inputControl.createInputQueue()
            self.pipeline.start()
            self.device.setIrLaserDotProjectorIntensity(0.0)  # False (no-op) on models without IR
            self.device.setIrFloodLightIntensity(0.0)
            self._send_exposure()
        except DeviceError:
            raise
        except Exception as exc:
            self._stop()
            raise DeviceError(f"{self.info.id}: cannot start the camera: {exc}") from None

    def _stop(self) -> None:
        for close in (getattr(getattr(self, "pipeline", None), "stop", None), getattr(self.device, "close", None)):
            try:
                if close is not None:
                    close()
            except Exception:
                pass  # the device may already be gone

    @property
    def exposure_us(self) -> int:
        return int(round(self.base_exposure_us * self.exposure))

    def _send_exposure(self) -> None:
        ctrl = self.dai.CameraControl()
        ctrl.setManualExposure(self.exposure_us, int(round(self.base_iso * self.gain)))
        self.control.send(ctrl)

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure is not None and not exposure > 0:
            raise DeviceError(f"exposure must be positive, got {exposure}")
        before = (self.exposure, self.gain)
        self.exposure = self.exposure if exposure is None else float(exposure)
        self.gain = self.gain if gain is None else float(gain)
        if pixel_format is not None and (pixel_format == "raw10") != self.raw:
            self.raw = pixel_format == "raw10"
            self._stop()
            self._start()
        elif (self.exposure, self.gain) != before:
            self._send_exposure()

    def _next(self, since_s: float) -> Any:
        """The first frame exposed after ``since_s`` (host monotonic seconds) at the requested exposure."""
        for _ in range(64):
            msg = self.queue.get(self.timeout)
            if msg is None:
                raise TimeoutError(f"no frame within {self.timeout.total_seconds():g} s")
            exposure_us = msg.getExposureTime().total_seconds() * 1e6
            started = msg.getTimestamp(self.dai.CameraExposureOffset.START).total_seconds()
            if started >= since_s and abs(exposure_us - self.exposure_us) <= EXPOSURE_TOLERANCE * self.exposure_us:
                return msg
        raise DeviceError(f"{self.info.id}: no frame at the requested exposure {self.exposure_us} us "
                          "(the sensor may not support it)")

    def _convert(self, msg: Any) -> np.ndarray:
        if self.raw:
            return unpack_raw10(msg.getData(), msg.getWidth(), msg.getHeight(), msg.getStride())
        rgb = np.asarray(msg.getFrame(), np.float32) / 255.0
        return srgb_to_linear(rgb) if self.opts.get("transfer", "srgb") == "srgb" else rgb

    def grab(self, timeout_s: float = 5.0) -> Frame:
        since = time.monotonic()
        try:
            msg = self._next(since)
        except DeviceError:
            raise
        except Exception:  # XLink error, closed queue, timeout: reopen once
            self._stop()
            try:
                self._start()
                msg = self._next(since)
            except Exception as exc:
                raise DeviceError(f"{self.info.id}: lost the camera mid-capture and could not reopen it ({exc})") from None
        started_ns = int(msg.getTimestamp(self.dai.CameraExposureOffset.START).total_seconds() * 1e9)
        frame = Frame(self._convert(msg), self.sequence, started_ns, self.exposure,
                      {"device_sequence": int(msg.getSequenceNum()), "iso": int(msg.getSensitivity()), "raw": self.raw,
                       "exposure_us": msg.getExposureTime().total_seconds() * 1e6})
        self.sequence += 1
        return frame

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def wait_frame(self, timeout_s: float = 5.0) -> Frame:
        """The frame of the trigger edge just fired on FSIN (needs ``fsin = true``)."""
        if not self.opts.get("fsin"):
            raise DeviceError(f"{self.info.id}: a rig with a trigger device needs [options.oak] fsin = true")
        return self.grab(timeout_s)

    def close(self) -> None:
        self._stop()


class OakProvider:
    kind = "camera"

    def __init__(self, dai: Callable[[], Any] = _dai) -> None:
        self.dai = dai

    def discover(self) -> list[DeviceInfo]:
        return list_oaks(self.dai())

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> OakCamera:
        info = next((i for i in self.discover() if i.id == device_id), None)
        if info is None:
            raise DeviceError(f"no OAK camera {device_id!r} (see `sss devices`)")
        return OakCamera(info, self.dai(), plugin_options(options, PLUGIN))


@hookimpl
def sssphase_cameras() -> list[OakProvider]:
    return [OakProvider()]
