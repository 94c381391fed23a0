"""UVC camera plugin (``uvc``): USB video-class cameras through OpenCV's V4L2 backend.

Discovery reads ``/sys/class/video4linux`` (no device is opened, no library is loaded): every
primary capture node of a USB camera becomes ``uvc:<vid>:<pid>:<serial or bus port>``, an ID that
survives a replug, which may renumber ``/dev/videoN``. OpenCV is imported only when a camera is
opened. OAK devices (VID 03e7) are left to the ``oak`` plugin.

Options (``[options.uvc]``): ``width``, ``height``, ``fps``, ``fourcc`` (e.g. ``"MJPG"``, ``"YUYV"``;
raw Bayer ``"BA81"``/``"GRBG"``/``"RGGB"``/``"BYR2"`` or ``"Y16 "`` deliver the sensor mosaic
unconverted), ``exposure_us`` (reference exposure; ``configure(exposure=r)`` sets ``r *
exposure_us``, manual exposure), ``gain``, ``transfer`` (``"srgb"`` to undo the camera's sRGB curve,
default, or ``"linear"``), ``timeout_s`` (read timeout, default 5), ``exposure_settle_frames`` (frames
dropped after an exposure change while the sensor applies it, default 2), ``max_stale_frames`` (8).

Frames: colour formats give float32 RGB ``(H, W, 3)`` in [0, 1] (linearised); raw formats give the
``(H, W)`` uint8/uint16 mosaic (develop it with ``sssphase_core.processing.isp``). ``timestamp_ns`` is the V4L2
buffer timestamp (CLOCK_MONOTONIC) when the driver reports one, else the host's monotonic clock at
read; frames buffered before the ``grab`` call (older timestamps) are dropped, so a frame never
predates the pattern shown before it. A failed read reopens the camera once (found again by its ID); if that fails the grab raises
a :class:`DeviceError` saying the camera is gone.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_plugins.drivers import DeviceError, DeviceInfo, Frame
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import check_plugin_options, no_device, plugin_options, sysfs_identity

PLUGIN = "uvc"
#: ``[options.uvc]``: each setting and its kind (``usb_util.OPTION_KINDS``).
OPTIONS = {"width": "count", "height": "count", "fps": "positive", "fourcc": "text", "exposure_us": "positive",
           "gain": "number", "transfer": ("srgb", "linear"), "timeout_s": "positive", "exposure_settle_frames": "whole",
           "max_stale_frames": "whole"}
V4L_ROOT = Path("/sys/class/video4linux")
RAW_FOURCCS = ("BA81", "GBRG", "GRBG", "RGGB", "BYR2", "Y16 ", "GREY")
#: The Bayer layout each raw fourcc names (V4L2: BA81 = SBGGR8, BYR2 = SBGGR16); Y16 and GREY do not say
#: (the rig file's ``[processing] bayer`` decides).
FOURCC_LAYOUTS = {"BA81": "BGGR", "BYR2": "BGGR", "GBRG": "GBRG", "GRBG": "GRBG", "RGGB": "RGGB"}
OAK_VID = 0x03E7


def list_cameras(root: Path = V4L_ROOT) -> list[tuple[DeviceInfo, str]]:
    """(info, /dev/videoN) of each USB capture camera; a clear "no device found" otherwise."""
    nodes = sorted(root.glob("video*"), key=lambda p: int(p.name[5:]) if p.name[5:].isdigit() else 0) if root.is_dir() else []
    cams = []
    for node in nodes:
        if (node / "index").exists() and (node / "index").read_text().strip() not in ("", "0"):
            continue  # metadata node of a camera already listed
        ident = sysfs_identity(node / "device")
        if ident is None or ident.vid == OAK_VID:
            continue
        name = (node / "name").read_text().strip() if (node / "name").exists() else ident.product
        info = DeviceInfo(f"{PLUGIN}:{ident.vid:04x}:{ident.pid:04x}:{ident.key}", "camera", PLUGIN,
                          name or "UVC camera", ident.serial)
        if info.id not in {c.id for c, _ in cams}:
            cams.append((info, f"/dev/{node.name}"))
    if not cams:
        raise no_device("no USB video capture device (/sys/class/video4linux lists none)" if root.is_dir()
                        else "no video4linux devices on this machine (no /sys/class/video4linux)")
    return cams


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


class UvcCamera:
    """Camera driver over an OpenCV ``VideoCapture`` (``open_capture(path)`` is injectable for tests)."""

    def __init__(self, info: DeviceInfo, locate: Callable[[], str], open_capture: Callable[[str], Any],
                 options: Mapping[str, Any]) -> None:
        self.info, self.locate, self.open_capture = info, locate, open_capture
        self.opts = check_plugin_options(options, PLUGIN, OPTIONS, info.id)
        self.fourcc = self.opts.get("fourcc", "")
        if self.fourcc and len(self.fourcc) != 4:  # (OpenCV's own words: a TypeError about arguments)
            raise DeviceError(f"{info.id}: [options.uvc] fourcc must be 4 characters (\"MJPG\", \"Y16 \"), got "
                              f"{self.fourcc!r}")
        self.raw = self.fourcc in RAW_FOURCCS
        self.base_exposure_us = float(self.opts.get("exposure_us", 10_000))
        self.exposure, self.gain = 1.0, self.opts.get("gain")
        self.sequence = 0
        self.settle = 0  # frames still to drop after an exposure change
        self.cap = self._open()

    def _set(self, cap: Any, prop: str, value: float, required: bool = True) -> None:
        import cv2

        if not cap.set(getattr(cv2, prop), float(value)) and required:
            raise DeviceError(f"{self.info.id}: the camera refused {prop.removeprefix('CAP_PROP_').lower()} = {value}")

    def _open(self) -> Any:
        import cv2

        path = self.locate()
        cap = self.open_capture(path)
        if cap is None or not cap.isOpened():
            raise DeviceError(f"{self.info.id}: cannot open {path} (in use by another program, or no permission: "
                              "add the daemon's user to the video group)")
        self._set(cap, "CAP_PROP_READ_TIMEOUT_MSEC", float(self.opts.get("timeout_s", 5.0)) * 1000, required=False)
        self._set(cap, "CAP_PROP_BUFFERSIZE", 1, required=False)
        if "fps" in self.opts:
            self._set(cap, "CAP_PROP_FPS", float(self.opts["fps"]), required=False)
        settings = []
        if self.fourcc:
            settings += [("CAP_PROP_FOURCC", cv2.VideoWriter_fourcc(*self.fourcc)),
                         ("CAP_PROP_CONVERT_RGB", 0 if self.raw else 1)]
        settings += [(p, self.opts[k]) for p, k in (("CAP_PROP_FRAME_WIDTH", "width"), ("CAP_PROP_FRAME_HEIGHT", "height"))
                     if k in self.opts]
        settings += [("CAP_PROP_AUTO_EXPOSURE", 1), ("CAP_PROP_EXPOSURE", self.base_exposure_us * self.exposure / 100)]
        if self.gain is not None:
            settings.append(("CAP_PROP_GAIN", float(self.gain)))
        for prop, value in settings:
            self._set(cap, prop, value)
        return cap

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure is not None and exposure != self.exposure:
            if not exposure > 0:
                raise DeviceError(f"exposure must be positive, got {exposure}")
            self.exposure = float(exposure)
            self._set(self.cap, "CAP_PROP_EXPOSURE", self.base_exposure_us * self.exposure / 100)  # V4L2: 100 us units
            self.settle = int(self.opts.get("exposure_settle_frames", 2))
        if gain is not None:
            self.gain = float(gain)
            self._set(self.cap, "CAP_PROP_GAIN", self.gain)
        if pixel_format is not None and pixel_format != self.fourcc:
            self.fourcc, self.raw = pixel_format, pixel_format in RAW_FOURCCS
            self.cap.release()
            self.cap = self._open()

    def _convert(self, image: np.ndarray) -> np.ndarray:
        import cv2

        if self.raw:
            w, h = (int(self.cap.get(p)) for p in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT))
            flat = np.ascontiguousarray(image).reshape(-1)
            if w * h and flat.size == 2 * w * h and flat.dtype == np.uint8:
                flat = flat.view(np.uint16)
            return flat.reshape(h, w) if w * h == flat.size else np.ascontiguousarray(image)
        rgb = image[..., ::-1].astype(np.float32) / float(np.iinfo(image.dtype).max)
        return srgb_to_linear(rgb) if self.opts.get("transfer", "srgb") == "srgb" else rgb

    def _read(self) -> tuple[bool, Any]:
        try:
            return self.cap.read()
        except Exception as exc:  # cv2.error on a vanished device
            return False, exc

    def _read_fresh(self, since_ns: int) -> tuple[Any, int]:
        """The first frame whose buffer timestamp is not older than ``since_ns`` (stale buffers dropped)."""
        import cv2

        for _ in range(int(self.opts.get("max_stale_frames", 8)) + self.settle + 1):
            ok, image = self._read()
            if not ok:
                raise ConnectionError(image)
            stamp_ns = int(float(self.cap.get(cv2.CAP_PROP_POS_MSEC)) * 1e6)  # V4L2 buffer time, CLOCK_MONOTONIC
            if self.settle:
                self.settle -= 1
            elif stamp_ns <= 0 or stamp_ns >= since_ns:
                return image, stamp_ns if stamp_ns > 0 else time.monotonic_ns()
        raise DeviceError(f"{self.info.id}: the camera keeps delivering frames older than the request")

    def grab(self, timeout_s: float = 5.0) -> Frame:
        since = time.monotonic_ns()
        try:
            image, stamp = self._read_fresh(since)
        except ConnectionError:
            self.cap.release()
            try:
                self.cap = self._open()
                image, stamp = self._read_fresh(since)
            except (DeviceError, ConnectionError):
                raise DeviceError(f"{self.info.id}: no frame from the camera (disconnected or stalled; "
                                  "reopening it failed too)") from None
        frame = Frame(self._convert(image), self.sequence, stamp, self.exposure,
                      {"fourcc": self.fourcc, "gain": self.gain, "raw": self.raw,
                       **({"bayer": FOURCC_LAYOUTS[self.fourcc]} if self.raw and self.fourcc in FOURCC_LAYOUTS else {})})
        self.sequence += 1
        return frame

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def close(self) -> None:
        self.cap.release()


def _open_v4l2(path: str) -> Any:
    import cv2

    return cv2.VideoCapture(path, cv2.CAP_V4L2)


class UvcProvider:
    kind = "camera"

    def __init__(self, cameras: Callable[[], list[tuple[DeviceInfo, str]]] = list_cameras,
                 open_capture: Callable[[str], Any] = _open_v4l2) -> None:
        self.cameras, self.open_capture = cameras, open_capture

    def discover(self) -> list[DeviceInfo]:
        return [info for info, _ in self.cameras()]

    def _locate(self, device_id: str) -> str:
        try:
            paths = {info.id: path for info, path in self.cameras()}
        except DeviceError as exc:
            raise DeviceError(f"{device_id}: camera not attached ({exc})") from None
        if device_id not in paths:
            raise DeviceError(f"{device_id}: camera not attached (see `sss devices`)")
        return paths[device_id]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> UvcCamera:
        info = next((i for i in self.discover() if i.id == device_id), None)
        if info is None:
            raise DeviceError(f"no UVC camera {device_id!r} (see `sss devices`)")
        return UvcCamera(info, lambda: self._locate(device_id), self.open_capture, plugin_options(options, PLUGIN))


@hookimpl
def sssphase_cameras() -> list[UvcProvider]:
    return [UvcProvider()]
