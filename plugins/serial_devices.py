"""Serial trigger board and turntable plugin (``serial``), over pyserial (extra ``serial``).

One microcontroller board (or two) on a USB serial port drives the camera trigger line and/or the
turntable's stepper. Ports are found by USB VID/PID (and the board's USB serial number, which keeps
the device ID stable when the port name changes after a replug). Supported USB bridges, also
covered by ``udev/60-sssphase.rules``:

* FTDI FT232R, ``0403:6001`` (Arduino Nano clones with FTDI, FTDI cables)
* Raspberry Pi Pico / RP2040 CDC-ACM, ``2e8a:000a`` (MicroPython/TinyUSB serial)

Add others with ``SSS_SERIAL_IDS="vid:pid,vid:pid"`` (hex).

Line protocol (ASCII, 115200 baud 8N1, every line ends with ``\\n``; the board answers each command
with exactly one line)::

    ID?          -> OK SSS-BOARD <firmware> <serial> <capabilities>   capabilities: TRIG,TURN
    FIRE         -> OK FIRE <t_us>      one trigger pulse; t_us = board clock (microseconds) at the edge
    POS?         -> OK POS <deg>        turntable angle in degrees
    MOVE <deg>   -> OK MOVE <deg>       absolute move; the reply comes once the table has settled
    (failure)    -> ERR <code> <message>

Timeouts: ``timeout_s`` per command (default 1 s), ``move_timeout_s`` for MOVE (default 60 s).
Reconnection: when the port fails (unplugged, USB reset) or a reply times out, the board is
re-found by its serial number, reopened and re-identified, and an idempotent command (``ID?``,
``POS?``, ``MOVE``) is retried once; a ``FIRE`` is never repeated (a lost reply may still have fired),
it raises and the next call uses the new connection. Options: ``[options.serial]`` ``baudrate``,
``timeout_s``, ``move_timeout_s``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from typing import Any

from sssphase_plugins.drivers import DeviceError, DeviceInfo
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import no_device, optional_import, plugin_options

PLUGIN = "serial"
#: ``[options.serial]``: each setting and its kind (``usb_util.OPTION_KINDS``).
OPTIONS = {"baudrate": "count", "timeout_s": "positive", "move_timeout_s": "positive"}
BOARD_IDS = {(0x0403, 0x6001): "FTDI FT232R serial board", (0x2E8A, 0x000A): "RP2040 CDC-ACM serial board"}
CAPABILITY = {"trigger": "TRIG", "turntable": "TURN"}
BAUDRATE = 115200


def _serial():
    return optional_import("serial", "serial", "pyserial")


def board_ids() -> dict[tuple[int, int], str]:
    """The USB VID/PIDs that count as boards: the built-in ones plus ``$SSS_SERIAL_IDS``."""
    ids = dict(BOARD_IDS)
    for item in filter(None, (s.strip() for s in os.environ.get("SSS_SERIAL_IDS", "").split(","))):
        try:
            vid, pid = (int(x, 16) for x in item.split(":"))
        except ValueError:
            raise DeviceError(f"SSS_SERIAL_IDS entry {item!r} is not vid:pid in hex") from None
        ids[(vid, pid)] = f"serial board {vid:04x}:{pid:04x}"
    return ids


def list_boards(comports: Callable[[], list[Any]] | None = None) -> list[tuple[str, str, str]]:
    """(stable key, port device, model) of each attached port with a board VID/PID."""
    if comports is None:
        comports = optional_import("serial.tools.list_ports", "serial", "pyserial").comports
    ids = board_ids()
    boards = [(p.serial_number or p.device.rsplit("/", 1)[-1], p.device, ids[(p.vid, p.pid)])
              for p in comports() if (p.vid, p.pid) in ids]
    if not boards:
        known = ", ".join(f"{v:04x}:{p:04x}" for v, p in ids)
        raise no_device(f"no serial port with a board USB id ({known}); check the cable, or add yours to SSS_SERIAL_IDS")
    return sorted(boards)


class SerialBoard:
    """A connection to one board: commands with timeouts, reconnection on failure (see module docstring)."""

    def __init__(self, name: str, locate: Callable[[], str], connect: Callable[[str], Any], *,
                 timeout_s: float = 1.0, move_timeout_s: float = 60.0) -> None:
        self.name, self.locate, self.connect = name, locate, connect
        self.timeout_s, self.move_timeout_s = timeout_s, move_timeout_s
        self.port: Any = None
        self.capabilities: set[str] = set()
        self.users = 0
        self._open()

    def _open(self) -> None:
        try:
            self.port = self.connect(self.locate())
        except DeviceError:
            raise
        except Exception as exc:  # pyserial raises SerialException/OSError/ValueError
            raise DeviceError(f"{self.name}: cannot open the serial port: {exc}") from None
        try:
            reply = self._exchange("ID?", self.timeout_s)
        except (ConnectionError, DeviceError) as exc:
            self._drop()
            raise DeviceError(f"{self.name}: the port does not answer as an sssphase board ({exc})") from None
        self.capabilities = set(reply[4].split(","))

    def _drop(self) -> None:
        if self.port is not None:
            try:
                self.port.close()
            except Exception:
                pass  # already gone
            self.port = None

    def _exchange(self, line: str, timeout_s: float) -> list[str]:
        """Write one command, read one reply line; ``ConnectionError`` when the link failed."""
        serial = _serial()
        try:
            self.port.reset_input_buffer()
            self.port.timeout = timeout_s
            self.port.write(f"{line}\n".encode())
            raw = self.port.readline()
        except (serial.SerialException, OSError) as exc:
            raise ConnectionError(f"port failed: {exc}") from None
        if not raw.endswith(b"\n"):
            raise ConnectionError(f"no reply to {line.split()[0]} within {timeout_s:g} s")
        words = raw.decode("ascii", errors="replace").split()
        if words and words[0] == "ERR":
            raise DeviceError(f"{self.name}: board error for {line!r}: {' '.join(words[1:])}")
        verb = line.split()[0]
        expected = ("SSS-BOARD", 5) if verb == "ID?" else (verb.rstrip("?"), 3)
        if words[:2] != ["OK", expected[0]] or len(words) < expected[1]:
            raise DeviceError(f"{self.name}: unexpected reply to {line!r}: {' '.join(words)[:80]!r}")
        return words

    def _attempt(self, line: str, timeout_s: float) -> list[str]:
        if self.port is None:
            try:
                self._open()
            except DeviceError as exc:
                raise DeviceError(f"{self.name}: disconnected and not back ({exc})") from None
        try:
            return self._exchange(line, timeout_s)
        except ConnectionError:
            self._drop()
            raise

    def command(self, line: str, *, timeout_s: float | None = None, idempotent: bool = True) -> list[str]:
        """Run one command; on a link failure reconnect, and retry it once when it is idempotent."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            return self._attempt(line, timeout)
        except ConnectionError as exc:
            if not idempotent:
                raise DeviceError(f"{self.name}: {exc} (board disconnected? it reconnects on the next command)") from None
        try:
            return self._attempt(line, timeout)
        except ConnectionError as exc:
            raise DeviceError(f"{self.name}: {exc} after reconnecting (board disconnected?)") from None

    def require(self, capability: str) -> None:
        if capability not in self.capabilities:
            raise DeviceError(f"{self.name}: this board has no {capability} function (it offers {sorted(self.capabilities)})")

    def release(self) -> None:
        self.users -= 1
        if self.users <= 0:
            self._drop()


class SerialTrigger:
    def __init__(self, info: DeviceInfo, board: SerialBoard) -> None:
        self.info, self.board = info, board

    def fire(self) -> int:
        return int(float(self.board.command("FIRE", idempotent=False)[2]) * 1000)

    def close(self) -> None:
        self.board.release()


class SerialTurntable:
    def __init__(self, info: DeviceInfo, board: SerialBoard) -> None:
        self.info, self.board = info, board

    @property
    def angle(self) -> float:
        return float(self.board.command("POS?")[2])

    def move_to(self, angle_deg: float) -> float:
        return float(self.board.command(f"MOVE {float(angle_deg):.3f}", timeout_s=self.board.move_timeout_s)[2])

    def close(self) -> None:
        self.board.release()


class SerialProvider:
    """Boards for one kind (trigger or turntable); a board with both functions is shared within a rig."""

    def __init__(self, kind: str, boards: Callable[[], list[tuple[str, str, str]]] = list_boards,
                 connect: Callable[..., Any] | None = None) -> None:
        self.kind, self.boards, self._connect = kind, boards, connect

    def discover(self) -> list[DeviceInfo]:
        return [DeviceInfo(f"{PLUGIN}:{key}", self.kind, PLUGIN, model, key) for key, _dev, model in self.boards()]

    def _locate(self, key: str) -> str:
        port = {k: dev for k, dev, _ in self.boards()}.get(key)
        if port is None:
            raise DeviceError(f"{PLUGIN}:{key}: cannot open the serial port: board not attached")
        return port

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> SerialTrigger | SerialTurntable:
        key = device_id.removeprefix(f"{PLUGIN}:")
        info = next((d for d in self.discover() if d.id == device_id), None)
        if info is None:
            raise DeviceError(f"no serial board {device_id!r} (see `sss devices`)")
        opts = plugin_options(options, PLUGIN, OPTIONS, device_id)
        baud = opts.get("baudrate", BAUDRATE)
        connect = self._connect or (lambda port: _serial().serial_for_url(port, baudrate=baud, timeout=1.0, write_timeout=1.0))
        board = shared.get(f"serial-board:{key}")
        if board is None:
            board = SerialBoard(device_id, lambda: self._locate(key), connect, timeout_s=float(opts.get("timeout_s", 1.0)),
                                move_timeout_s=float(opts.get("move_timeout_s", 60.0)))
            shared[f"serial-board:{key}"] = board
        board.require(CAPABILITY[self.kind])
        board.users += 1
        return SerialTrigger(info, board) if self.kind == "trigger" else SerialTurntable(info, board)


@hookimpl
def sssphase_triggers() -> list[SerialProvider]:
    return [SerialProvider("trigger")]


@hookimpl
def sssphase_turntables() -> list[SerialProvider]:
    return [SerialProvider("turntable")]
