"""Basler camera plugin (``basler``): machine-vision cameras through Basler's own pylon SDK (``pypylon``,
extra ``basler``).

Discovery asks pylon's transport layers (USB3 Vision, GigE, and the camera emulation that
``PYLON_CAMEMU=N`` switches on); each camera is ``basler:<serial number>``, an ID that survives a replug
or another USB port. pypylon is imported only when discovery or a camera needs it.

Options (``[options.basler]``, all optional):

- ``pixel_format``: a pylon name (``BayerRG12``, ``BayerGB8``, ``Mono12``, ``RGB8``, ...) or ``auto``
  (default): the camera's deepest raw Bayer format (12, 10, 16, then 8 bit), else RGB8/BGR8, else Mono.
  Bayer frames are delivered raw (``(H, W)`` uint16/uint8, the sensor mosaic) with their layout, bit
  depth and black level in the frame's metadata, for the session's raw pipeline; RGB and Mono formats
  are delivered as linear float32 RGB ``(H, W, 3)`` in [0, 1] (the camera's gamma is set to 1 where it
  has one).
- ``exposure_us`` (reference exposure, default 10000: ``configure(exposure=r)`` sets ``r * exposure_us``),
  ``gain`` (dB), ``black_level`` (the camera's BlackLevel setting, in its own units).
- ``roi``: ``[offset_x, offset_y, width, height]`` in sensor pixels (Bayer: even offsets keep the layout).
- ``trigger``: ``software`` (default: each grab fires pylon's software trigger) or ``Line1``..``Line3``
  (hardware: the frame exposes on the edge the projector's or trigger board's output puts on that
  line, ``trigger_activation`` ``RisingEdge`` by default; see HARDWARE.md for the wiring).
- ``timeout_s`` (how long a frame may take beyond its exposure, default 5), ``buffers`` (pylon's MaxNumBuffer, default 10).
- ``image_file``: emulated cameras only (``PYLON_CAMEMU``): a file or folder the emulator streams
  instead of its test image (16-bit PNG/TIFF: the value ``v << (16 - bits)`` gives ``v``). The emulator
  reads it when acquisition starts, so each grab then starts and stops acquisition (a file rewritten
  between grabs is read afresh).

Frames carry ``sequence`` (ours, rising), ``timestamp_ns`` (the camera's clock when it stamps frames,
else the host's monotonic clock at delivery) and in ``meta`` the camera's ``block_id``, ``pixel_format``,
``gain`` and ``exposure_us``; a gap in the camera's frame counter counts as dropped frames
(``dropped_frames``, also logged). Every grab result is released to pylon before the frame is returned
(the pixel data is copied out), so buffers never run out over long captures.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sssphase_plugins.drivers import DeviceError, DeviceInfo, Frame
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import check_plugin_options, no_device, optional_import, plugin_options

log = logging.getLogger(__name__)

PLUGIN = "basler"
USB_VENDOR = 0x2676  # Basler AG (USB3 Vision): its udev rule is in udev/60-sssphase.rules
TRIGGERS = ("software", "Line1", "Line2", "Line3")
#: The ``auto`` choice among raw Bayer formats, best first (12-bit sensors are the common case).
BAYER_DEPTHS = (12, 10, 16, 8)
#: ``[options.basler]``: each setting and its kind (``usb_util.OPTION_KINDS``); the camera checks the ranges.
OPTIONS = {"pixel_format": "text", "exposure_us": "positive", "gain": "number", "black_level": "number", "roi": "any",
           "trigger": "text", "trigger_activation": "text", "timeout_s": "positive", "buffers": "count",
           "image_file": "text"}


@dataclass(frozen=True)
class PixelFormat:
    """What a pylon pixel format delivers: ``kind`` bayer / mono / rgb / bgr, the Bayer ``layout``, ``bits``."""

    name: str
    kind: str
    bits: int
    layout: str | None = None

    @property
    def raw(self) -> bool:
        return self.kind == "bayer"


def parse_format(name: str) -> PixelFormat | None:
    """A pylon pixel-format name -> :class:`PixelFormat`, or None for formats sssphase does not take
    (packed 10/12p, YUV, planar, ...)."""
    if m := re.fullmatch(r"Bayer(RG|GR|GB|BG)(8|10|12|16)", name):
        layout = {"RG": "RGGB", "GR": "GRBG", "GB": "GBRG", "BG": "BGGR"}[m.group(1)]
        return PixelFormat(name, "bayer", int(m.group(2)), layout)
    if m := re.fullmatch(r"Mono(8|10|12|16)", name):
        return PixelFormat(name, "mono", int(m.group(1)))
    if m := re.fullmatch(r"(RGB|BGR)8(Packed)?", name):
        return PixelFormat(name, m.group(1).lower(), 8)
    return None


def choose_format(offered: tuple[str, ...], asked: str, device_id: str = PLUGIN) -> PixelFormat:
    """The format to use among the camera's ``offered`` names (``asked``: a name or ``auto``)."""
    usable = [f for f in map(parse_format, offered) if f is not None]
    if asked != "auto":
        chosen = parse_format(asked)
        if asked not in offered or chosen is None:
            names = ", ".join(f.name for f in usable) or "none"
            why = "this camera does not offer it" if asked not in offered else "sssphase does not read it"
            raise DeviceError(f"{device_id}: pixel format {asked!r}: {why}; use one of {names}")
        return chosen
    for bits in BAYER_DEPTHS:
        for f in usable:
            if f.raw and f.bits == bits:
                return f
    for kind in ("rgb", "bgr", "mono"):
        best = [f for f in usable if f.kind == kind]
        if best:
            return max(best, key=lambda f: f.bits)
    raise DeviceError(f"{device_id}: the camera offers no pixel format sssphase reads (offers {', '.join(offered)})")


def _pylon() -> Any:
    return optional_import("pypylon.pylon", "basler", "pypylon")


def list_cameras(pylon: Any = None) -> list[tuple[DeviceInfo, Any]]:
    """(info, pylon device info) of every camera pylon sees; a clear "no device found" otherwise."""
    pylon = pylon or _pylon()
    try:
        found = list(pylon.TlFactory.GetInstance().EnumerateDevices())
    except Exception as exc:  # a transport layer that fails to load: say so, do not crash discovery
        raise no_device(f"pylon could not enumerate cameras ({exc})") from None
    cams = []
    for dev in found:
        serial = str(dev.GetSerialNumber())
        cams.append((DeviceInfo(f"{PLUGIN}:{serial}", "camera", PLUGIN, str(dev.GetModelName()), serial), dev))
    if not cams:
        raise no_device("pylon sees no Basler camera (USB3: is it on a USB 3 port, and are the udev rules installed "
                        "(`sss udev install`)? GigE: is it on this machine's subnet?)")
    return cams


class BaslerCamera:
    """Camera driver over a pylon ``InstantCamera`` (opened by :class:`BaslerProvider`)."""

    def __init__(self, info: DeviceInfo, camera: Any, pylon: Any, options: Mapping[str, Any]) -> None:
        self.info, self.cam, self.pylon = info, camera, pylon
        self.opts = check_plugin_options(options, PLUGIN, OPTIONS, info.id)
        self.exposure, self.sequence, self.dropped = 1.0, 0, 0
        self.base_exposure_us = self._positive("exposure_us", 10_000.0)
        self.timeout_s = self._positive("timeout_s", 5.0)
        self.trigger = str(self.opts.get("trigger", "software"))
        if self.trigger not in TRIGGERS:
            raise DeviceError(f"{info.id}: trigger must be one of {', '.join(TRIGGERS)}, got {self.trigger!r}")
        self.snap = "image_file" in self.opts  # the emulator reads its image file when acquisition starts
        self.last_block: int | None = None
        self.device_clock: bool | None = None  # decided on the first frame: does the camera stamp frames?
        self.closed = False
        try:
            self._setup()
        except DeviceError:
            self.close()
            raise
        except self.pylon.GenericException as exc:
            self.close()
            raise DeviceError(f"{info.id}: the camera refused its settings: {_first_line(exc)}") from None

    # --- settings --------------------------------------------------------------------------------------

    def _positive(self, key: str, default: float) -> float:
        value = self.opts.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 1e9:
            raise DeviceError(f"{self.info.id}: [options.basler] {key} must be a positive number, got {value!r}")
        return float(value)

    def _node(self, *names: str) -> Any:
        """The first of ``names`` the camera has and can write (ExposureTime / ExposureTimeAbs ...)."""
        from pypylon import genicam

        for name in names:
            try:
                node = getattr(self.cam, name)
                if genicam.IsWritable(node):
                    return node
            except Exception:  # a placeholder for a feature this model lacks
                continue
        return None

    def _set(self, value: Any, *names: str, required: bool = True) -> None:
        node = self._node(*names)
        if node is None:
            if required:
                raise DeviceError(f"{self.info.id}: the camera has no writable {names[0]}")
            return
        if isinstance(value, int | float) and not isinstance(value, bool) and hasattr(node, "Min"):
            lo, hi = node.Min, node.Max
            if not lo <= value <= hi:
                raise DeviceError(f"{self.info.id}: {names[0]} = {value:g} is out of the camera's range [{lo:g}, {hi:g}]"
                                  + (" (us: the rig's exposure_us times the relative exposure)" if "Exposure" in names[0] else ""))
        try:
            node.Value = value
        except self.pylon.GenericException as exc:
            raise DeviceError(f"{self.info.id}: the camera refused {names[0]} = {value!r}: {_first_line(exc)}") from None

    def _setup(self) -> None:
        cam = self.cam
        cam.MaxNumBuffer.Value = int(self._positive("buffers", 10))
        self.format = choose_format(tuple(cam.PixelFormat.Symbolics), str(self.opts.get("pixel_format", "auto")), self.info.id)
        self._set(self.format.name, "PixelFormat")
        if not self.format.raw:
            self._set(1.0, "Gamma", required=False)
        if "roi" in self.opts:
            self._set_roi(self.opts["roi"])
        if "black_level" in self.opts:
            self._set(float(self.opts["black_level"]), "BlackLevel", "BlackLevelRaw")
        if "gain" in self.opts:
            self._set(float(self.opts["gain"]), "Gain", "GainRaw")
        self._set_exposure()
        self._set("FrameStart", "TriggerSelector", required=False)
        self._set("On", "TriggerMode")
        self._set("Software" if self.trigger == "software" else self.trigger, "TriggerSource")
        if self.trigger != "software":
            self._set(str(self.opts.get("trigger_activation", "RisingEdge")), "TriggerActivation")
        if self.snap:
            self._set("Off", "TestImageSelector", "TestPattern", required=False)
            self._set("On", "ImageFileMode")
            self._set(str(self.opts["image_file"]), "ImageFilename")

    def _set_roi(self, roi: Any) -> None:
        if not (isinstance(roi, list | tuple) and len(roi) == 4 and all(isinstance(v, int) and v >= 0 for v in roi)):
            raise DeviceError(f"{self.info.id}: [options.basler] roi must be [offset_x, offset_y, width, height] "
                              f"in whole pixels, got {roi!r}")
        x, y, w, h = roi
        self._set(0, "OffsetX")
        self._set(0, "OffsetY")
        self._set(w, "Width")
        self._set(h, "Height")
        self._set(x, "OffsetX")
        self._set(y, "OffsetY")

    def _set_exposure(self) -> None:
        self._set(self.base_exposure_us * self.exposure, "ExposureTime", "ExposureTimeAbs")

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure is not None and exposure != self.exposure:
            if not exposure > 0:
                raise DeviceError(f"exposure must be positive, got {exposure}")
            old, self.exposure = self.exposure, float(exposure)
            try:
                self._set_exposure()
            except DeviceError:
                self.exposure = old
                raise
        if gain is not None:
            self._set(float(gain), "Gain", "GainRaw")
        if pixel_format is not None and pixel_format != self.format.name:
            chosen = choose_format(tuple(self.cam.PixelFormat.Symbolics), pixel_format, self.info.id)
            self._stop()  # the format cannot change while acquiring
            self._set(chosen.name, "PixelFormat")
            self.format = chosen

    # --- acquisition ------------------------------------------------------------------------------------

    def _start(self) -> None:
        if not self.cam.IsGrabbing():
            self.cam.StartGrabbing(self.pylon.GrabStrategy_OneByOne)
            self.last_block = None  # the camera's counter restarts with acquisition

    def _stop(self) -> None:
        if self.cam.IsGrabbing():
            self.cam.StopGrabbing()

    def _gone(self) -> bool:
        try:
            return bool(self.cam.IsCameraDeviceRemoved()) or not self.cam.IsOpen()
        except Exception:
            return True

    def _fail(self, exc: BaseException | None, doing: str) -> DeviceError:
        if self._gone():
            return DeviceError(f"{self.info.id}: the camera is gone while {doing} (unplugged, powered off or closed): "
                               "reconnect it and continue the capture with --resume")
        return DeviceError(f"{self.info.id}: {doing} failed: {_first_line(exc) if exc else 'no reason given'}")

    def wait_s(self, timeout_s: float | None = None) -> float:
        """How long a grab waits for its frame: the exposure under way plus ``timeout_s`` (``[options.basler]
        timeout_s`` by default), so that an 8 s exposure is not "no frame within 5 s"."""
        return self.base_exposure_us * self.exposure / 1e6 + (self.timeout_s if timeout_s is None else float(timeout_s))

    def _waited(self, wait_s: float) -> str:
        """What a wait of ``wait_s`` (:meth:`wait_s`) was made of."""
        exposure_s = self.base_exposure_us * self.exposure / 1e6
        return f"the {exposure_s:g} s exposure and {wait_s - exposure_s:g} s more"

    def grab(self, timeout_s: float | None = None) -> Frame:
        """One frame: software trigger (``trigger = software``), else the next hardware-triggered frame."""
        if self.closed:
            raise DeviceError(f"{self.info.id}: the camera is closed")
        timeout = self.wait_s(timeout_s)
        try:
            self._start()
            if self.trigger == "software":
                self._drain()
                if not self.cam.WaitForFrameTriggerReady(int(timeout * 1000), self.pylon.TimeoutHandling_Return):
                    raise DeviceError(f"{self.info.id}: the camera was not ready for a trigger within {timeout:g} s "
                                      f"({self._waited(timeout)})")
                self.cam.ExecuteSoftwareTrigger()
            return self._retrieve(timeout)
        except self.pylon.GenericException as exc:
            raise self._fail(exc, "grabbing a frame") from None
        finally:
            if self.snap and not self.closed:
                self._safely(self._stop)

    def wait_frame(self, timeout_s: float | None = None) -> Frame:
        """The frame a hardware trigger pulse just exposed (a rig's ``trigger`` device fired it)."""
        if self.trigger == "software":
            raise DeviceError(f"{self.info.id}: a rig with a trigger device needs [options.basler] trigger = \"Line1\" "
                              "(the line the trigger output is wired to)")
        return self.grab(timeout_s)

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def _drain(self) -> None:
        """Drop frames already waiting (exposed before this grab): a frame never predates its request."""
        while self.cam.NumReadyBuffers.Value > 0:
            result = self.cam.RetrieveResult(0, self.pylon.TimeoutHandling_Return)
            if result is None or not result.IsValid():
                return
            result.Release()

    def _retrieve(self, timeout: float) -> Frame:
        """The next frame, waiting ``timeout`` seconds (:meth:`wait_s`) at most."""
        result = self.cam.RetrieveResult(int(timeout * 1000), self.pylon.TimeoutHandling_Return)
        if result is None or not result.IsValid():
            if self._gone():
                raise self._fail(None, "waiting for a frame")
            cause = ("the trigger never came: is the projector's trigger output wired to "
                     f"{self.trigger} (HARDWARE.md)?" if self.trigger != "software" else "the camera sent nothing")
            raise DeviceError(f"{self.info.id}: no frame within {timeout:g} s ({self._waited(timeout)}): {cause}")
        try:
            if not result.GrabSucceeded():
                raise DeviceError(f"{self.info.id}: the frame was lost: {result.GetErrorDescription()} "
                                  f"(code {result.GetErrorCode():#x})")
            data = np.array(result.GetArray(), copy=True)  # ours: the buffer goes back to pylon below
            block, stamp = int(result.BlockID), int(result.TimeStamp)
        finally:
            result.Release()
        return self._frame(data, block, stamp)

    def _frame(self, data: np.ndarray, block: int, stamp: int) -> Frame:
        if self.last_block is not None and block > self.last_block + 1:
            self.dropped += block - self.last_block - 1
            log.warning("%s: %d frame(s) dropped before block %d", self.info.id, block - self.last_block - 1, block)
        self.last_block = block
        if self.device_clock is None:
            self.device_clock = stamp > 0  # the emulator stamps 0: the host's clock then
        now = time.monotonic_ns()
        fmt = self.format
        meta: dict[str, Any] = {"block_id": block, "pixel_format": fmt.name, "exposure_us": self.base_exposure_us * self.exposure,
                                "dropped_frames": self.dropped, "clock": "device" if self.device_clock else "host"}
        if fmt.raw:
            meta.update(raw=True, bayer=fmt.layout, bit_depth=fmt.bits)
            black = self._value("BlackLevel", "BlackLevelRaw")
            if black is not None:
                meta["black_level"] = float(black)
        else:
            scale = np.float32(2**fmt.bits - 1)
            data = data.astype(np.float32) / scale
            if fmt.kind == "mono":
                data = np.repeat(data[..., None], 3, axis=-1)
            elif fmt.kind == "bgr":
                data = data[..., ::-1]
            data = np.ascontiguousarray(data)
        gain = self._value("Gain", "GainRaw")
        if gain is not None:
            meta["gain"] = float(gain)
        frame = Frame(data, self.sequence, stamp if self.device_clock else now, self.exposure, meta)
        self.sequence += 1
        return frame

    def _value(self, *names: str) -> Any:
        for name in names:
            try:
                return getattr(self.cam, name).Value
            except Exception:
                continue
        return None

    @staticmethod
    def _safely(step: Any) -> None:
        try:
            step()
        except Exception:  # closing what is already gone
            pass

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._safely(self._stop)
        self._safely(self.cam.Close)
        self._safely(self.cam.DestroyDevice)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__).split(" : ")[0].strip()


class BaslerProvider:
    kind = "camera"

    def __init__(self, pylon: Any = None) -> None:
        self._pylon = pylon

    @property
    def pylon(self) -> Any:
        return self._pylon or _pylon()

    def discover(self) -> list[DeviceInfo]:
        return [info for info, _ in list_cameras(self.pylon)]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> BaslerCamera:
        pylon = self.pylon
        try:
            found = dict(list_cameras(pylon))
        except DeviceError as exc:
            raise DeviceError(f"{device_id}: camera not attached ({exc})") from None
        match = next(((info, dev) for info, dev in found.items() if info.id == device_id), None)
        if match is None:
            known = ", ".join(i.id for i in found) or "none"
            raise DeviceError(f"no Basler camera {device_id!r} (attached: {known}; see `sss devices`)")
        info, dev = match
        try:
            camera = pylon.InstantCamera(pylon.TlFactory.GetInstance().CreateDevice(dev))
            camera.Open()
        except pylon.GenericException as exc:
            raise DeviceError(f"{device_id}: cannot open the camera: it is open in another program (pylon Viewer, "
                              f"another daemon?) or this user may not access it (`sss udev install`); pylon says: "
                              f"{_first_line(exc)}") from None
        return BaslerCamera(info, camera, pylon, plugin_options(options, PLUGIN))


@hookimpl
def sssphase_cameras() -> list[BaslerProvider]:
    return [BaslerProvider()]
