"""Fakes at the hardware-library boundary: a DLPC350 behind hidapi, a serial board, OpenCV and depthai sources."""

from __future__ import annotations

import datetime
import struct
import time
from types import SimpleNamespace

import numpy as np
import serial


class FakeDlpc350Hid:
    """An open ``hid.device`` of a LightCrafter: records every output report and answers like a DLPC350.

    It parses the reports with its own reading of the programmer's guide layout (flags, sequence,
    length, CMD3 CMD2, payload; continuation reports carry raw data) and keeps the written values as
    registers, so reads return what was written (start/stop, validation, status).
    """

    def __init__(self, *, nack: set[int] = frozenset(), validate_status: int = 0, hw_status: int = 0x01) -> None:
        self.reports: list[bytes] = []
        self.commands: list[tuple[int, int, int, bytes]] = []  # (flags, seq, cmd, payload)
        self.replies: list[bytes] = []
        self.registers: dict[int, bytes] = {0x1A0A: bytes([hw_status]), 0x1A0B: b"\x01", 0x1A0C: b"\x0a",
                                             0x0205: struct.pack("<4I", 0x03000001, 0x01020003, 0, 0)}
        self.nack, self.validate_status = set(nack), validate_status
        self.validate_polls = 0
        self.pending: bytearray | None = None
        self.connected = True

    def write(self, report) -> int:
        if not self.connected:
            raise OSError("write error")
        report = bytes(report)
        assert len(report) == 65 and report[0] == 0, "a DLPC350 report is report ID 0 + 64 bytes"
        self.reports.append(report)
        body = report[1:]
        if self.pending is not None:  # continuation of a long message
            self.pending += body
        else:
            self.pending = bytearray(body)
        flags, seq, length = struct.unpack_from("<BBH", self.pending)
        if len(self.pending) - 4 < length:
            return 65
        message, self.pending = bytes(self.pending[4:4 + length]), None
        cmd = message[0] | message[1] << 8
        payload = message[2:]
        self.commands.append((flags, seq, cmd, payload))
        self._answer(flags, seq, cmd, payload)
        return 65

    def _answer(self, flags: int, seq: int, cmd: int, payload: bytes) -> None:
        if cmd in self.nack:
            self.replies.append(bytes([flags | 0x20, seq, 0, 0]).ljust(64, b"\x00"))
            return
        if flags & 0x80:  # read
            if cmd == 0x1A1A:
                self.validate_polls += 1
                data = bytes([0x80 if self.validate_polls < 2 else self.validate_status])
            else:
                data = self.registers.get(cmd, b"\x00")
            self.replies.append((bytes([flags, seq]) + struct.pack("<H", len(data)) + data).ljust(64, b"\x00"))
            return
        self.registers[cmd] = payload
        if cmd == 0x1A1A:
            self.validate_polls = 0
        self.replies.append((bytes([flags, seq, 2, 0]) + struct.pack("<H", cmd)).ljust(64, b"\x00"))

    def read(self, size: int, timeout_ms: int = 0) -> list[int]:
        if not self.connected:
            raise OSError("read error")
        return list(self.replies.pop(0)) if self.replies else []

    def close(self) -> None:
        self.connected = False

    def written(self, cmd: int) -> list[bytes]:
        return [p for f, _s, c, p in self.commands if c == cmd and not f & 0x80]


class FakeHidApi:
    """Stand-in for the ``hid`` module: one enumerable LightCrafter whose device is ``dev``."""

    def __init__(self, dev: FakeDlpc350Hid, serial_number: str = "LCR1") -> None:
        self.dev, self.serial_number = dev, serial_number

    def enumerate(self, vid: int = 0, pid: int = 0) -> list[dict]:
        return [{"path": b"/dev/hidraw7", "serial_number": self.serial_number, "interface_number": 0,
                 "vendor_id": 0x0451, "product_id": 0x6401}]

    def device(self):
        dev = self.dev
        dev.open_path = lambda path: None
        return dev


class FakeWindow:
    """Stand-in for the HDMI window process: records the frames it was sent."""

    def __init__(self, display: int = 0, *, size=(912, 1140), **kwargs) -> None:
        self.display, self.size, self.frames, self.closed = display, size, [], False
        self.alive = True

    def send(self, frame_id: int, pixels: np.ndarray) -> None:
        if not self.alive:
            from sssphase_plugins.drivers import DeviceError

            raise DeviceError("hdmi display 0: the projector window process exited")
        self.frames.append((frame_id, pixels))

    def wait(self, frame_id: int) -> int:
        return time.monotonic_ns()

    def close(self) -> None:
        self.closed = True


class FakeBoard:
    """A scripted sssphase serial board; its replies travel through a pyserial ``loop://`` port.

    The host writes a command; the board parses it and writes its reply line into the loop, where
    the host's ``readline`` (with pyserial's real timeout handling) picks it up.
    """

    def __init__(self, *, caps: str = "TRIG,TURN", serial_number: str = "B1", silent: set[str] = frozenset()) -> None:
        self.loop = serial.serial_for_url("loop://", timeout=1.0)
        self.caps, self.serial_number, self.silent = caps, serial_number, set(silent)
        self.angle, self.clock_us, self.fired = 0.0, 1_000_000, 0
        self.dead = False
        self.log: list[str] = []

    @property
    def timeout(self) -> float:
        return self.loop.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self.loop.timeout = value

    def reset_input_buffer(self) -> None:
        self._check()
        self.loop.reset_input_buffer()

    def _check(self) -> None:
        if self.dead:
            raise serial.SerialException("device reports readiness to read but returned no data (device disconnected?)")

    def write(self, data: bytes) -> int:
        self._check()
        line = data.decode().strip()
        self.log.append(line)
        verb, *args = line.split()
        if verb in self.silent:
            return len(data)
        if verb == "ID?":
            reply = f"OK SSS-BOARD 1.0 {self.serial_number} {self.caps}"
        elif verb == "FIRE":
            self.fired += 1
            self.clock_us += 16_667
            reply = f"OK FIRE {self.clock_us}"
        elif verb == "POS?":
            reply = f"OK POS {self.angle:.3f}"
        elif verb == "MOVE" and args:
            self.angle = float(args[0]) % 360
            reply = f"OK MOVE {self.angle:.3f}"
        else:
            reply = f"ERR 2 unknown command {verb}"
        self.loop.write(f"{reply}\n".encode())
        return len(data)

    def readline(self) -> bytes:
        self._check()
        return self.loop.readline()

    def close(self) -> None:
        self.loop.close()


class FakeCapture:
    """An OpenCV ``VideoCapture`` stand-in serving BGR (or raw) frames with V4L2-like timestamps."""

    def __init__(self, frames: int = 1000, *, shape=(24, 32, 3), dtype=np.uint8, fail_after: int | None = None,
                 stale: int = 0, refuse: set[int] = frozenset()) -> None:
        self.props: dict[int, float] = {3: shape[1], 4: shape[0]}
        self.shape, self.dtype, self.left, self.fail_after = shape, dtype, frames, fail_after
        self.stale, self.refuse = stale, set(refuse)
        self.reads, self.opened, self.last_stamp_ms = 0, True, 0.0

    def isOpened(self) -> bool:
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        if prop in self.refuse:
            return False
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.last_stamp_ms if prop == 0 else self.props.get(prop, 0.0)

    def read(self):
        if self.fail_after is not None and self.reads >= self.fail_after:
            return False, None
        now_ms = time.monotonic_ns() / 1e6
        self.last_stamp_ms = now_ms - 1000.0 if self.stale > 0 else now_ms
        self.stale -= 1
        self.reads += 1
        value = self.reads % 200
        if len(self.shape) == 3:  # BGR with distinct channels: blue = frame number, green 50, red 250
            return True, np.stack([np.full(self.shape[:2], v, self.dtype) for v in (value, 50, 250)], axis=-1)
        return True, np.full(self.shape, value, self.dtype)

    def release(self) -> None:
        self.opened = False


class FakeQueue:
    def __init__(self, owner: FakeDepthai) -> None:
        self.owner = owner

    def get(self, timeout: datetime.timedelta):
        o = self.owner
        if not o.connected:
            raise RuntimeError("Communication exception - possible device error/misconfiguration. Original message "
                               "'Couldn't read data from stream: 'cam' (X_LINK_ERROR)'")
        o.served += 1
        exposure_us = o.exposure_us if o.served > o.lag else o.old_exposure_us
        start = datetime.timedelta(seconds=time.monotonic() - (1.0 if o.served <= o.stale else 0.0))
        end = start + datetime.timedelta(microseconds=exposure_us)
        h, w = o.shape
        return SimpleNamespace(
            getExposureTime=lambda: datetime.timedelta(microseconds=exposure_us),
            getTimestamp=lambda offset="END": start if offset == "START" else end,
            getFrame=lambda: np.full((h, w, 3), 128, np.uint8), getSequenceNum=lambda: o.served,
            getSensitivity=lambda: o.iso, getData=lambda: o.raw10, getWidth=lambda: w, getHeight=lambda: h,
            getStride=lambda: w * 5 // 4)


class FakeDepthai:
    """A depthai v3 stand-in: one OAK whose camera serves frames; records controls and IR settings."""

    def __init__(self, device_ids: tuple[str, ...] = ("1844301011B546F500",), *, shape=(8, 16)) -> None:
        self.ids, self.shape = list(device_ids), shape
        self.connected = True
        self.exposure_us, self.old_exposure_us, self.iso = 0, 0, 0
        self.served, self.lag, self.stale = 0, 0, 0
        self.ir: dict[str, float] = {}
        self.raw10 = np.zeros(shape[0] * shape[1] * 5 // 4, np.uint8)
        self.opened = 0
        fake = self

        class Device:
            @staticmethod
            def getAllAvailableDevices():
                return [SimpleNamespace(getDeviceId=lambda i=i: i, name="1.2") for i in fake.ids]

            def __init__(self, info) -> None:
                fake.opened += 1
                fake.connected = True

            def setIrLaserDotProjectorIntensity(self, v: float) -> bool:
                fake.ir["dots"] = v
                return True

            def setIrFloodLightIntensity(self, v: float) -> bool:
                fake.ir["flood"] = v
                return True

            def close(self) -> None:
                pass

        class CameraControl:
            FrameSyncMode = SimpleNamespace(INPUT="INPUT")

            def setManualExposure(self, us: int, iso: int):
                self.us, self.iso = us, iso
                return self

        class Camera:
            def build(self, socket):
                self.socket = socket
                self.raw = SimpleNamespace(createOutputQueue=lambda **kw: FakeQueue(fake))
                self.initialControl = SimpleNamespace(setFrameSyncMode=lambda m: None, setExternalTrigger=lambda a, b: None)
                self.inputControl = SimpleNamespace(createInputQueue=lambda: SimpleNamespace(send=fake._control))
                return self

            def requestFullResolutionOutput(self, type=None):
                return SimpleNamespace(createOutputQueue=lambda **kw: FakeQueue(fake))

        class Pipeline:
            def __init__(self, device) -> None:
                pass

            def create(self, node):
                return node()

            def start(self) -> None:
                pass

            def stop(self) -> None:
                pass

        self.Device, self.CameraControl, self.Pipeline = Device, CameraControl, Pipeline
        self.node = SimpleNamespace(Camera=Camera)
        self.CameraBoardSocket = SimpleNamespace(CAM_A="CAM_A", CAM_B="CAM_B")
        self.ImgFrame = SimpleNamespace(Type=SimpleNamespace(RGB888i="RGB888i"))
        self.CameraExposureOffset = SimpleNamespace(START="START", MIDDLE="MIDDLE", END="END")

    def _control(self, ctrl) -> None:
        self.old_exposure_us, self.exposure_us, self.iso = self.exposure_us, ctrl.us, ctrl.iso
        self.served = 0
