"""TI DLP LightCrafter 4500 plugin (``lcr4500``): DLPC350 control over USB HID (hidapi), pixels over HDMI.

The EVM (USB VID 0x0451, PID 0x6401, native DMD resolution 912x1140) is controlled through the
DLPC350's USB HID command interface (TI DLPU010, "DLPC350 Programmer's Guide", section 2.1 and the
command tables of chapter 2.4); the images themselves reach it as HDMI video, shown by the ``hdmi``
plugin's fullscreen window on the display the EVM appears as. hidapi is imported only when the plugin
is used (extra ``hid``).

HID packet layout (every report is 64 bytes, sent with a leading report ID 0x00 -> 65 bytes)::

    byte 0     flags: bit 7 R/W (1 = read), bit 6 reply wanted, bit 5 error (NACK, in replies),
               bits 2:0 destination (0 = projector control)
    byte 1     sequence number (incremented per message)
    bytes 2-3  length, little-endian: bytes that follow (2 command bytes + payload)
    bytes 4-5  command, little-endian 16-bit: CMD3 then CMD2 (0x1A1B -> 1B 1A)
    bytes 6-   payload; zero padding to 64 bytes

A message longer than one report continues in further reports of 64 raw bytes each (no header).
Replies use the same header (bit 7 set for read replies, bit 5 on error) followed by the data;
writes are sent with "reply wanted" and the ACK/NACK reply is checked.

Commands used (CMD2 CMD3, payload):

=========  ================  ==========================================================================
0x1A00     input source      1 byte: bits 2:0 source (0 parallel/HDMI), bits 4:3 port width (1 = 24 bit)
0x1A0A     hardware status   read 1 byte: bit0 init done, bit2 DRC error, bit3 forced swap error,
                             bit6 sequence abort, bit7 sequencer error
0x1A0B     system status     read 1 byte: bit0 internal memory test passed
0x1A0C     main status       read 1 byte: bit0 DMD parked, bit1 sequencer running, bit2 video frozen,
                             bit3 external source locked
0x0205     version           read 16 bytes: application, API, software config, sequence config (u32 each)
0x1A1A     LUT validate      write 0x00 starts validation; read 1 byte: bit0 bad exposure/period,
                             bit1 bad pattern number, bit2 trigger-out-1 overlap (warning), bit3 no
                             post-vector (warning), bit4 exposure/period difference < 230 us
                             (warning), bit7 busy
0x1A1B     display mode      1 byte: 0 video, 1 pattern sequence
0x1A1D     trigger out 1     3 bytes: invert, rising-edge delay, falling-edge delay; delay code
                             ``187 + round(delay_us / 0.107136)`` (0xBB = no delay)
0x1A22     pattern source    1 byte: 0 video port, 3 internal flash
0x1A23     trigger mode      1 byte: 0 VSYNC, 1 internal/external trigger
0x1A24     start/stop        1 byte: 0 stop, 1 pause, 2 start (read back: current state)
0x1A29     exposure/period   8 bytes: exposure then frame period, microseconds, u32 little-endian
0x1A31     pattern config    4 bytes: LUT entries - 1, repeat (bit0), patterns for trigger out 2 - 1,
                             image indices - 1
0x1A32     mailbox address   1 byte: LUT offset (0..127)
0x1A33     mailbox control   1 byte: 0 close, 1 image-index LUT, 2 pattern LUT
0x1A34     mailbox data      3 bytes per pattern LUT entry (24-bit word, little-endian):
                             bits 1:0 trigger (0 internal, 1 external positive/VSYNC, 2 external
                             negative, 3 continue), bits 7:2 pattern number, bits 11:8 bit depth,
                             bits 14:12 LEDs (bit0 red, bit1 green, bit2 blue), bit16 invert, bit17
                             insert black, bit18 buffer swap, bit19 trigger-out-1 from previous
=========  ================  ==========================================================================

Modes (``[options.lcr4500]`` ``mode``): ``video`` (default) projects the HDMI input as is;
``pattern`` runs the VSYNC-triggered pattern sequence: each HDMI frame carries one 8-bit pattern in
its green channel (pattern 0 = G7..G0) shown with all LEDs for ``exposure_us`` of every
``period_us``, and trigger out 1 is high during each pattern exposure (wire it to the camera's
trigger input for hardware sync). Other options: ``display`` (index of the HDMI display; default:
the first 912x1140 one), ``latency_s``, ``settle_frames``, ``timeout_s`` (as for ``hdmi``).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sssphase_plugins.drivers import DeviceError, DeviceInfo, DeviceNotFound, ShowReceipt, check_pattern
from sssphase_plugins.hdmi_projector import HdmiProjector, HdmiWindow, list_displays
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import no_device, optional_import, plugin_options, sysfs_usb_devices

PLUGIN = "lcr4500"
#: ``[options.lcr4500]``: each setting and its kind (``usb_util.OPTION_KINDS``).
OPTIONS = {"mode": ("video", "pattern"), "display": "whole", "exposure_us": "count", "period_us": "count",
           "latency_s": "seconds", "settle_frames": "whole", "timeout_s": "positive"}
VID, PID = 0x0451, 0x6401
NATIVE_RESOLUTION = (912, 1140)
REPORT_LEN = 64
FLAG_READ, FLAG_REPLY, FLAG_ERROR = 0x80, 0x40, 0x20
TRIG_DELAY_UNIT_US, TRIG_DELAY_ZERO, TRIG_DELAY_MAX = 0.107136, 187, 0xD5

COMMANDS = {
    "input_source": 0x1A00, "status_hw": 0x1A0A, "status_sys": 0x1A0B, "status_main": 0x1A0C,
    "version": 0x0205, "lut_validate": 0x1A1A, "display_mode": 0x1A1B, "trigger_out1": 0x1A1D,
    "pattern_source": 0x1A22, "trigger_mode": 0x1A23, "start_stop": 0x1A24, "exposure_period": 0x1A29,
    "pattern_config": 0x1A31, "mailbox_address": 0x1A32, "mailbox_control": 0x1A33, "mailbox_data": 0x1A34,
}
COMMAND_NAMES = {code: name for name, code in COMMANDS.items()}
HW_ERRORS = {2: "DRC error", 3: "forced swap error", 6: "sequence abort", 7: "sequencer error"}
VALIDATE_ERRORS = {0: "exposure or frame period invalid", 1: "pattern number invalid"}
VALIDATE_WARNINGS = {2: "trigger out 1 overlaps", 3: "no post-vector", 4: "exposure/period difference below 230 us"}


def pack_message(cmd: int, payload: bytes = b"", *, read: bool = False, reply: bool = True, seq: int = 0) -> list[bytes]:
    """The HID output reports (report ID 0 + 64 bytes each) of one DLPC350 command."""
    body = struct.pack("<H", cmd) + bytes(payload)
    if len(body) > 0xFFFF:
        raise DeviceError(f"DLPC350 message too long ({len(body)} bytes)")
    flags = (FLAG_READ if read else 0) | (FLAG_REPLY if reply else 0)
    message = struct.pack("<BBH", flags, seq & 0xFF, len(body)) + body
    return [b"\x00" + message[i:i + REPORT_LEN].ljust(REPORT_LEN, b"\x00") for i in range(0, len(message), REPORT_LEN)]


@dataclass(frozen=True)
class LutEntry:
    """One pattern LUT entry (see the module docstring for the bit layout)."""

    pattern: int = 0
    bit_depth: int = 8
    leds: int = 0b111
    trigger: int = 1
    invert: bool = False
    insert_black: bool = False
    buffer_swap: bool = True
    trigger_out_prev: bool = False

    def word(self) -> int:
        if not (0 <= self.pattern <= 24 and 1 <= self.bit_depth <= 8 and 0 <= self.leds <= 7 and 0 <= self.trigger <= 3):
            raise DeviceError(f"invalid pattern LUT entry {self}")
        return (self.trigger | self.pattern << 2 | self.bit_depth << 8 | self.leds << 12 | self.invert << 16
                | self.insert_black << 17 | self.buffer_swap << 18 | self.trigger_out_prev << 19)


def _bits(value: int, names: dict[int, str]) -> list[str]:
    return [name for bit, name in names.items() if value >> bit & 1]


class Dlpc350:
    """Command channel to one DLPC350 over an open hidapi device (``write``/``read``/``close``)."""

    def __init__(self, device: Any, *, name: str = PLUGIN, timeout_s: float = 1.0, poll_s: float = 0.02) -> None:
        self.device, self.name, self.timeout_s, self.poll_s = device, name, timeout_s, poll_s
        self.seq = 0

    # ---- transport -----------------------------------------------------------------------------
    def _lost(self, exc: BaseException | str) -> DeviceError:
        return DeviceError(f"{self.name}: USB HID link lost ({exc}); is the LightCrafter still connected and powered?")

    def _read_report(self) -> bytes:
        try:
            data = bytes(self.device.read(REPORT_LEN, int(self.timeout_s * 1000)))
        except (OSError, ValueError) as exc:
            raise self._lost(exc) from None
        if not data:
            raise self._lost(f"no reply within {self.timeout_s:g} s")
        return data.ljust(REPORT_LEN, b"\x00")

    def transact(self, cmd: int, payload: bytes = b"", *, read: bool = False) -> bytes:
        """Send one command and return the reply data (the ACK's for a write); NACK -> DeviceError."""
        name = COMMAND_NAMES.get(cmd, "command")
        for report in pack_message(cmd, payload, read=read, reply=True, seq=self.seq):
            try:
                written = self.device.write(report)
            except (OSError, ValueError) as exc:
                raise self._lost(exc) from None
            if written is not None and written < 0:
                raise self._lost("write failed")
        self.seq = (self.seq + 1) & 0xFF
        first = self._read_report()
        flags, _seq, length = struct.unpack_from("<BBH", first)
        if flags & FLAG_ERROR:
            raise DeviceError(f"{self.name}: the DLPC350 refused {name} 0x{cmd:04X} (payload {bytes(payload).hex() or '-'})")
        data = first[4:4 + length]
        while len(data) < length:
            data += self._read_report()[:length - len(data)]
        if read and not data:
            raise DeviceError(f"{self.name}: empty reply to {name} 0x{cmd:04X}")
        return data

    def write(self, name: str, *payload: int) -> None:
        self.transact(COMMANDS[name], bytes(payload))

    def read(self, name: str) -> bytes:
        return self.transact(COMMANDS[name], read=True)

    def close(self) -> None:
        self.device.close()

    # ---- commands ------------------------------------------------------------------------------
    def _poll(self, name: str, done: Callable[[int], bool], what: str) -> int:
        deadline = time.monotonic() + self.timeout_s * 5
        while not done(value := self.read(name)[0]):
            if time.monotonic() > deadline:
                raise DeviceError(f"{self.name}: timed out waiting for {what} (last value 0x{value:02X})")
            time.sleep(self.poll_s)
        return value

    def stop(self) -> None:
        self.write("start_stop", 0)
        self._poll("start_stop", lambda v: v == 0, "the pattern sequence to stop")

    def start(self) -> None:
        self.write("start_stop", 2)

    def set_display_mode(self, pattern: bool) -> None:
        self.write("display_mode", int(pattern))

    def set_input_source(self, source: int = 0, port_width_code: int = 1) -> None:
        self.write("input_source", (source & 0x7) | (port_width_code & 0x3) << 3)

    def set_pattern_source(self, flash: bool = False) -> None:
        self.write("pattern_source", 3 if flash else 0)

    def set_trigger_mode(self, mode: int) -> None:
        self.write("trigger_mode", mode)

    def set_exposure_period(self, exposure_us: int, period_us: int) -> None:
        if not 0 < exposure_us <= period_us:
            raise DeviceError(f"{self.name}: exposure {exposure_us} us must be in (0, period {period_us} us]")
        self.write("exposure_period", *struct.pack("<II", exposure_us, period_us))

    def set_pattern_config(self, n_entries: int, *, repeat: bool = True, n_trigger_out2: int | None = None,
                           n_images: int = 1) -> None:
        self.write("pattern_config", (n_entries - 1) & 0x7F, int(repeat),
                   ((n_trigger_out2 or n_entries) - 1) & 0xFF, (n_images - 1) & 0x3F)

    def upload_pattern_lut(self, entries: list[LutEntry]) -> None:
        """Open the pattern-LUT mailbox, write the entries from offset 0, close the mailbox."""
        if not 0 < len(entries) <= 128:
            raise DeviceError(f"{self.name}: the pattern LUT holds 1..128 entries, got {len(entries)}")
        self.write("mailbox_control", 2)
        self.write("mailbox_address", 0)
        self.write("mailbox_data", *b"".join(e.word().to_bytes(3, "little") for e in entries))
        self.write("mailbox_control", 0)

    def set_trigger_out1(self, *, invert: bool = False, rising_delay_us: float = 0.0, falling_delay_us: float = 0.0) -> None:
        codes = [TRIG_DELAY_ZERO + round(d / TRIG_DELAY_UNIT_US) for d in (rising_delay_us, falling_delay_us)]
        if not all(0 <= c <= TRIG_DELAY_MAX for c in codes):
            raise DeviceError(f"{self.name}: trigger-out delays must lie in [-20.05, 2.79] us")
        self.write("trigger_out1", int(invert), *codes)

    def validate(self) -> list[str]:
        """Validate the pattern sequence; raise on errors, return the warnings."""
        self.write("lut_validate", 0)
        status = self._poll("lut_validate", lambda v: not v & 0x80, "pattern sequence validation")
        errors = _bits(status, VALIDATE_ERRORS)
        if errors:
            raise DeviceError(f"{self.name}: pattern sequence rejected: {', '.join(errors)}")
        return _bits(status, VALIDATE_WARNINGS)

    def status(self) -> dict[str, Any]:
        hw, sys_, main = (self.read(n)[0] for n in ("status_hw", "status_sys", "status_main"))
        return {"init_done": bool(hw & 1), "errors": _bits(hw, HW_ERRORS), "memory_test_ok": bool(sys_ & 1),
                "parked": bool(main & 1), "sequencer_running": bool(main & 2), "video_frozen": bool(main & 4),
                "source_locked": bool(main & 8)}

    def check_hardware(self) -> None:
        hw = self.read("status_hw")[0]
        if _bits(hw, HW_ERRORS):
            raise DeviceError(f"{self.name}: DLPC350 hardware status reports {', '.join(_bits(hw, HW_ERRORS))}")

    def version(self) -> dict[str, str]:
        words = struct.unpack("<4I", self.read("version")[:16].ljust(16, b"\x00"))
        names = ("application", "api", "software_config", "sequence_config")
        return {n: f"{w >> 24}.{w >> 16 & 0xFF}.{w & 0xFFFF}" for n, w in zip(names, words, strict=True)}

    def configure_video(self) -> None:
        self.stop()
        self.set_display_mode(False)
        self.set_input_source(0, 1)

    def configure_pattern(self, exposure_us: int, period_us: int) -> list[str]:
        """VSYNC-triggered 8-bit patterns from the green channel of each HDMI frame, trigger out 1 per pattern."""
        self.stop()
        self.set_display_mode(True)
        self.set_pattern_source(flash=False)
        self.set_pattern_config(1, repeat=True, n_trigger_out2=1, n_images=1)
        self.set_trigger_mode(0)
        self.set_exposure_period(exposure_us, period_us)
        self.upload_pattern_lut([LutEntry(pattern=0, bit_depth=8, leds=0b111, trigger=1, buffer_swap=True)])
        self.set_trigger_out1()
        warnings = self.validate()
        self.start()
        return warnings


class LightCrafterProjector(HdmiProjector):
    """Projector driver: HDMI window for the pixels, DLPC350 for the mode and a status check per frame."""

    def __init__(self, info: DeviceInfo, dlpc: Dlpc350, window: Any, *, mode: str = "video",
                 exposure_us: int = 16_000, period_us: int = 16_666, latency_s: float = 0.05) -> None:
        super().__init__(info, window, latency_s=latency_s)
        if mode not in ("video", "pattern"):
            raise DeviceError(f"{info.id}: mode is 'video' or 'pattern', not {mode!r}")
        self.dlpc, self.mode = dlpc, mode
        self.warnings: list[str] = []  # validation warnings of the pattern sequence
        if mode == "pattern":
            self.warnings = dlpc.configure_pattern(exposure_us, period_us)
        else:
            dlpc.configure_video()
        dlpc.check_hardware()

    def show(self, image: np.ndarray, *, tag: str = "", confirm: bool = True) -> ShowReceipt:
        if self.mode == "pattern":  # one 8-bit pattern per frame, in the green channel
            gray = check_pattern(image, self.resolution, self.info.id)
            gray = gray.mean(axis=2) if gray.ndim == 3 else gray
            image = np.zeros((*gray.shape, 3), np.float32)
            image[..., 1] = gray
        receipt = super().show(image, tag=tag, confirm=confirm)
        self.dlpc.check_hardware()
        return receipt

    def status(self) -> dict[str, Any]:
        return self.dlpc.status()

    def close(self) -> None:
        try:
            if self.mode == "pattern":
                self.dlpc.stop()
        except DeviceError:
            pass  # already gone: nothing left to stop
        finally:
            self.dlpc.close()
            super().close()


def _hid():
    return optional_import("hid", "hid", "hidapi")


class LightCrafterProvider:
    kind = "projector"

    def __init__(self, hid_api: Callable[[], Any] = _hid, displays: Callable[[], list[tuple[int, int]]] = list_displays,
                 window: Callable[..., Any] = HdmiWindow) -> None:
        self.hid_api, self.displays, self.window = hid_api, displays, window

    def _found(self) -> list[tuple[DeviceInfo, Any]]:
        hid = self.hid_api()
        found = [d for d in hid.enumerate(VID, PID) if d.get("interface_number", 0) in (0, -1)]
        if not found:
            if sysfs_usb_devices(VID, PID):
                raise no_device("a LightCrafter 4500 is attached but hidapi cannot open it: install the udev rules "
                                "(sss udev install) and replug it")
            raise no_device("hidapi sees no LightCrafter 4500 (USB 0451:6401): check USB cable and power")
        out = []
        for i, d in enumerate(found):
            serial = d.get("serial_number") or str(i)
            out.append((DeviceInfo(f"{PLUGIN}:{serial}", "projector", PLUGIN, "TI DLP LightCrafter 4500", serial), d["path"]))
        return out

    def discover(self) -> list[DeviceInfo]:
        return [info for info, _ in self._found()]

    def _display(self, opts: Mapping[str, Any]) -> int:
        if "display" in opts:
            return opts["display"]
        sizes = self.displays()
        if tuple(NATIVE_RESOLUTION) in sizes:
            return sizes.index(tuple(NATIVE_RESOLUTION))
        raise DeviceNotFound(f"no {NATIVE_RESOLUTION[0]}x{NATIVE_RESOLUTION[1]} HDMI display found (displays: {sizes}); "
                          "set [options.lcr4500] display = <index>")

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> LightCrafterProjector:
        found = {info.id: (info, path) for info, path in self._found()}
        if device_id not in found:
            raise DeviceError(f"no LightCrafter {device_id!r} (see `sss devices`)")
        info, path = found[device_id]
        opts = plugin_options(options, PLUGIN, OPTIONS, device_id)
        dev = self.hid_api().device()
        try:
            dev.open_path(path)
        except (OSError, ValueError) as exc:
            raise DeviceError(f"{device_id}: cannot open the HID device ({exc}); install the udev rules "
                              "(sss udev install)") from None
        dlpc = Dlpc350(dev, name=device_id, timeout_s=float(opts.get("timeout_s", 1.0)))
        window = None
        try:
            window = self.window(self._display(opts), settle_frames=opts.get("settle_frames", 1),
                                 timeout_s=float(opts.get("timeout_s", 5.0)))
            if tuple(window.size) != NATIVE_RESOLUTION:
                raise DeviceError(f"{device_id}: the HDMI display is {window.size[0]}x{window.size[1]}, the LightCrafter "
                                  f"needs {NATIVE_RESOLUTION[0]}x{NATIVE_RESOLUTION[1]} (set it in the display settings)")
            return LightCrafterProjector(info, dlpc, window, mode=opts.get("mode", "video"),
                                         exposure_us=opts.get("exposure_us", 16_000),
                                         period_us=opts.get("period_us", 16_666),
                                         latency_s=float(opts.get("latency_s", 0.05)))
        except Exception:
            dlpc.close()
            if window is not None:
                window.close()
            raise


@hookimpl
def sssphase_projectors() -> list[LightCrafterProvider]:
    return [LightCrafterProvider()]
