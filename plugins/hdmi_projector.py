"""HDMI projector plugin (``hdmi``): a borderless fullscreen window on a chosen display (pygame / SDL2).

The OpenCV wheel is headless, so the window lives in its own process (``python -m
sssphase_plugins.hdmi_projector``), started when the projector is opened; the daemon never loads
SDL's video stack except for a short display query during discovery. pygame is imported only there
and in the window process (extra ``hdmi``).

Show -> capture handshake: ``show(image, confirm=True)`` sends the 8-bit frame to the window
process, which blits it, flips with vsync and flips ``settle_frames`` more times (so the new image has
been scanned out at least once), then answers ``shown <frame_id> <monotonic_ns>``. The driver then
waits the projector's own input latency (``latency_s``, measured per projector, see HARDWARE.md)
before it returns the receipt, so a camera exposure that starts after ``show`` never sees the
previous pattern. With ``confirm=False`` it returns at once; the next call collects the reply.

Window process protocol (stdin/stdout pipes, little-endian): request = ``<IHHB`` header (frame_id,
width, height, channels) + ``width*height*channels`` bytes of uint8 pixels (rows top to bottom);
reply = one ASCII line, ``ready <w> <h> <vsync>`` once at start, ``shown <id> <ns> <crc32>`` per
frame (``crc32`` of the pixels read back from the screen surface when ``verify`` is on, else 0), or
``error <message>``. Closing stdin ends the process.

Options (``[options.hdmi]`` in the rig file): ``latency_s`` (default 0.05), ``settle_frames``
(default 1), ``timeout_s`` (5), ``verify`` (read the screen back and compare, default false).
Virtual SDL drivers (``offscreen``, ``dummy``) count as displays only when ``SDL_VIDEODRIVER``
names them explicitly (tests, CI); otherwise a headless machine reports "no display".
"""

from __future__ import annotations

import os
import select
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from sssphase_plugins.drivers import DeviceError, DeviceInfo, ShowReceipt, check_pattern
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import no_device, optional_import, plugin_options

PLUGIN = "hdmi"
#: ``[options.hdmi]``: each setting and its kind (``usb_util.OPTION_KINDS``).
OPTIONS = {"latency_s": "seconds", "settle_frames": "whole", "timeout_s": "positive", "verify": "bool"}
HEADER = struct.Struct("<IHHB")
VIRTUAL_DRIVERS = ("offscreen", "dummy")


def _pygame():
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    return optional_import("pygame", "hdmi", "pygame")


#: SDL's video drivers other than Wayland, in its own order (SDL_VIDEODRIVER takes such a list)
NOT_WAYLAND = "x11,kmsdrm,offscreen,dummy"


def _init_display(pygame: Any) -> None:
    """``pygame.display.init()``; without a Wayland display to connect to (no ``WAYLAND_DISPLAY``) and no driver
    chosen by the user, SDL's Wayland probe is skipped: libwayland printed "error: XDG_RUNTIME_DIR is invalid or
    not set in the environment." to the terminal under `sss devices` on a machine without a display."""
    chosen = os.environ.get("SDL_VIDEODRIVER")
    if chosen or os.environ.get("WAYLAND_DISPLAY"):
        pygame.display.init()
        return
    os.environ["SDL_VIDEODRIVER"] = NOT_WAYLAND
    try:
        pygame.display.init()
    finally:
        del os.environ["SDL_VIDEODRIVER"]


def list_displays() -> list[tuple[int, int]]:
    """(width, height) of each display SDL can open a window on; clear errors when there is none."""
    pygame = _pygame()
    try:
        _init_display(pygame)
        driver = pygame.display.get_driver()
        sizes = [tuple(s) for s in pygame.display.get_desktop_sizes()]
    except pygame.error as exc:
        raise no_device(f"SDL has no video device ({exc}); is DISPLAY or WAYLAND_DISPLAY set for the daemon?") from None
    finally:
        pygame.display.quit()
    if driver in VIRTUAL_DRIVERS and os.environ.get("SDL_VIDEODRIVER") != driver:
        raise no_device(f"SDL fell back to its virtual {driver!r} driver (set DISPLAY or WAYLAND_DISPLAY "
                        "for the daemon's user, or SDL_VIDEODRIVER for a virtual display)")
    if not sizes:
        raise no_device("SDL reports no display")
    return sizes


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Pattern values in [0, 1], (H, W) or (H, W, 3) -> contiguous (H, W, 3) uint8."""
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3):
        raise DeviceError(f"a projector image is (H, W) or (H, W, 3), got shape {img.shape}")
    out = np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.ascontiguousarray(np.broadcast_to(out, (*out.shape[:2], 3)))


class HdmiWindow:
    """Parent side of the window process: send frames, wait for their on-screen confirmation."""

    def __init__(self, display: int, *, settle_frames: int = 1, verify: bool = False, timeout_s: float = 5.0,
                 command: list[str] | None = None) -> None:
        self.display, self.verify, self.timeout_s = display, verify, timeout_s
        cmd = command or [sys.executable, "-m", "sssphase_plugins.hdmi_projector", str(display), str(settle_frames),
                          str(int(verify))]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)
        self.pending: dict[int, int] = {}  # frame_id -> expected crc32 (0 without verify)
        reply = self._reply("ready")
        self.size = (int(reply[1]), int(reply[2]))
        self.vsync = reply[3] == "1"

    def _fail(self, what: str) -> DeviceError:
        code = self.proc.poll()
        state = f"exited with code {code}" if code is not None else "is not answering"
        return DeviceError(f"hdmi display {self.display}: {what}: the projector window process {state} "
                           "(display unplugged or window closed?)")

    def _reply(self, expect: str) -> list[str]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], self.timeout_s)
        line = self.proc.stdout.readline().decode(errors="replace").split() if ready else []
        if not line:
            raise self._fail(f"no {expect!r} reply within {self.timeout_s:g} s")
        if line[0] == "error":
            raise DeviceError(f"hdmi display {self.display}: {' '.join(line[1:])}")
        if line[0] != expect:
            raise DeviceError(f"hdmi display {self.display}: unexpected reply {' '.join(line)[:80]!r}")
        return line

    def _collect(self) -> tuple[int, int]:
        """Read one ``shown`` reply, check it against the frame sent; returns (frame_id, on-screen ns)."""
        _, shown_id, ns, crc = self._reply("shown")
        expected = self.pending.pop(int(shown_id), None)
        if self.verify and expected is not None and int(crc) != expected:
            raise DeviceError(f"hdmi display {self.display}: frame {shown_id} on screen differs from the one sent")
        return int(shown_id), int(ns)

    def send(self, frame_id: int, pixels: np.ndarray) -> None:
        h, w, c = pixels.shape
        assert self.proc.stdin is not None and self.proc.stdout is not None
        while self.pending and select.select([self.proc.stdout], [], [], 0)[0]:
            self._collect()  # replies of unconfirmed frames: never let them fill the pipe
        try:
            self.proc.stdin.write(HEADER.pack(frame_id, w, h, c) + pixels.tobytes())
        except (BrokenPipeError, OSError):
            raise self._fail(f"cannot send frame {frame_id}") from None
        self.pending[frame_id] = zlib.crc32(pixels) if self.verify else 0

    def wait(self, frame_id: int) -> int:
        """Collect replies up to ``frame_id``; returns its on-screen time (monotonic ns)."""
        while frame_id in self.pending:
            shown_id, ns = self._collect()
            if shown_id == frame_id:
                return ns
        raise DeviceError(f"hdmi display {self.display}: frame {frame_id} was never sent")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()
                self.proc.wait(timeout=2)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


class HdmiProjector:
    """Projector driver over an :class:`HdmiWindow` (``window`` is injectable for tests)."""

    def __init__(self, info: DeviceInfo, window: Any, *, latency_s: float = 0.05) -> None:
        self.info, self.window, self.latency_s = info, window, latency_s
        self.frame_id = 0

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self.window.size)  # type: ignore[return-value]

    def show(self, image: np.ndarray, *, tag: str = "", confirm: bool = True) -> ShowReceipt:
        image = check_pattern(image, self.resolution, self.info.id)
        self.frame_id += 1
        self.window.send(self.frame_id, to_uint8(image))
        if not confirm:
            return ShowReceipt(self.frame_id, tag, time.monotonic_ns() + int(self.latency_s * 1e9))
        on_screen = self.window.wait(self.frame_id) + int(self.latency_s * 1e9)
        time.sleep(max(0.0, (on_screen - time.monotonic_ns()) / 1e9))
        return ShowReceipt(self.frame_id, tag, on_screen)

    def close(self) -> None:
        self.window.close()


class HdmiProvider:
    kind = "projector"

    def __init__(self, displays: Callable[[], list[tuple[int, int]]] = list_displays,
                 window: Callable[..., Any] = HdmiWindow) -> None:
        self.displays, self.window = displays, window

    def discover(self) -> list[DeviceInfo]:
        return [DeviceInfo(f"{PLUGIN}:display{i}", "projector", PLUGIN, f"{w}x{h} display", f"display{i}")
                for i, (w, h) in enumerate(self.displays())]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> HdmiProjector:
        info = next((d for d in self.discover() if d.id == device_id), None)
        if info is None:
            raise DeviceError(f"no display {device_id!r} (see `sss devices`)")
        opts = plugin_options(options, PLUGIN, OPTIONS, device_id)
        window = self.window(int(info.serial.removeprefix("display")), settle_frames=opts.get("settle_frames", 1),
                             verify=opts.get("verify", False), timeout_s=float(opts.get("timeout_s", 5.0)))
        return HdmiProjector(info, window, latency_s=float(opts.get("latency_s", 0.05)))


@hookimpl
def sssphase_projectors() -> list[HdmiProvider]:
    return [HdmiProvider()]


# ---- the window process --------------------------------------------------------------------------
def _read_exact(stream: Any, n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def window_main(display: int, settle_frames: int, verify: bool) -> int:
    """Run the fullscreen window until stdin closes (see the module docstring for the protocol)."""
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # anything a library prints goes to stderr, never into the reply stream
    try:
        pygame = _pygame()
        _init_display(pygame)
        flags = pygame.FULLSCREEN | pygame.NOFRAME
        try:
            screen, vsync = pygame.display.set_mode((0, 0), flags, display=display, vsync=1), True
        except pygame.error:  # driver without vsync support
            screen, vsync = pygame.display.set_mode((0, 0), flags, display=display), False
        pygame.mouse.set_visible(False)
    except Exception as exc:
        out.write(f"error cannot open a window on display {display}: {exc}\n".encode())
        return 1
    w, h = screen.get_size()
    out.write(f"ready {w} {h} {int(vsync)}\n".encode())
    stdin = sys.stdin.buffer
    while (head := _read_exact(stdin, HEADER.size)) is not None:
        frame_id, fw, fh, c = HEADER.unpack(head)
        data = _read_exact(stdin, fw * fh * c)
        if data is None:
            break
        if (fw, fh, c) != (w, h, 3):
            out.write(f"error frame {frame_id} is {fw}x{fh}x{c}, the screen is {w}x{h}x3\n".encode())
            continue
        pygame.surfarray.blit_array(screen, np.frombuffer(data, np.uint8).reshape(h, w, 3).swapaxes(0, 1))
        for _ in range(1 + settle_frames):
            pygame.display.flip()
        pygame.event.pump()
        crc = zlib.crc32(np.ascontiguousarray(pygame.surfarray.array3d(screen).swapaxes(0, 1))) if verify else 0
        out.write(f"shown {frame_id} {time.monotonic_ns()} {crc}\n".encode())
    pygame.display.quit()
    return 0


if __name__ == "__main__":
    sys.exit(window_main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"))
