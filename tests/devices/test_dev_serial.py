"""Serial trigger board / turntable: the line protocol over pyserial's loop:// with a scripted board."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

pytest.importorskip("serial")
from dev_fakes import FakeBoard  # noqa: E402

from sssphase_plugins import serial_devices as sd  # noqa: E402
from sssphase_plugins.drivers import DeviceError, DeviceNotFound  # noqa: E402


class Bench:
    """Ports as the OS lists them, and the boards behind them (a replug swaps in a new board)."""

    def __init__(self, board: FakeBoard | None) -> None:
        self.board = board
        self.port = "/dev/ttyACM0"

    def boards(self):
        if self.board is None:
            raise DeviceNotFound("no device found: no serial port with a board USB id")
        return [(self.board.serial_number, self.port, "RP2040 CDC-ACM serial board")]

    def connect(self, port: str):
        assert port == self.port
        if self.board is None:
            raise OSError(f"could not open port {port}")
        return self.board


def open_device(bench: Bench, kind: str, shared: dict | None = None, **opts):
    provider = sd.SerialProvider(kind, boards=bench.boards, connect=bench.connect)
    (info,) = provider.discover()
    assert info.id == "serial:B1" and info.kind == kind
    return provider.open(info.id, {"serial": {"timeout_s": 0.2, **opts}}, {} if shared is None else shared)


def test_trigger_and_turntable_protocol():
    bench = Bench(FakeBoard())
    shared: dict = {}
    trigger, table = open_device(bench, "trigger", shared), open_device(bench, "turntable", shared)
    assert trigger.board is table.board  # one connection for a combined board
    t0, t1 = trigger.fire(), trigger.fire()
    assert t1 - t0 == 16_667_000 and bench.board.fired == 2
    assert table.move_to(90) == 90.0 and table.angle == 90.0
    assert table.move_to(-45) == 315.0
    assert bench.board.log == ["ID?", "FIRE", "FIRE", "MOVE 90.000", "POS?", "MOVE -45.000"]
    trigger.close()
    assert table.board.port is not None  # still used by the turntable
    table.close()
    assert table.board.port is None


def test_board_errors_and_missing_capability():
    bench = Bench(FakeBoard(caps="TRIG"))
    with pytest.raises(DeviceError, match=r"no TURN function \(it offers \['TRIG'\]\)"):
        open_device(bench, "turntable")
    trigger = open_device(bench, "trigger")
    with pytest.raises(DeviceError, match="board error for 'HOME': 2 unknown command HOME"):
        trigger.board.command("HOME")


def test_timeout_gives_clear_error():
    bench = Bench(FakeBoard(silent={"FIRE"}))
    trigger = open_device(bench, "trigger")
    with pytest.raises(DeviceError, match=r"no reply to FIRE within 0.2 s \(board disconnected\?"):
        trigger.fire()
    assert bench.board.log.count("FIRE") == 1  # a trigger pulse is never repeated


def test_reconnects_after_replug_and_retries_idempotent_commands():
    bench = Bench(FakeBoard())
    table = open_device(bench, "turntable")
    table.move_to(30)
    bench.board.dead = True  # unplugged mid-capture ...
    bench.board, bench.port = FakeBoard(), "/dev/ttyACM1"  # ... and back under a new port name
    bench.board.angle = 30.0
    assert table.angle == 30.0
    assert bench.board.log == ["ID?", "POS?"]


def test_disconnect_without_replug_raises_clear_error():
    bench = Bench(FakeBoard())
    trigger = open_device(bench, "trigger")
    bench.board.dead = True
    with pytest.raises(DeviceError, match="port failed.*device disconnected"):
        trigger.fire()
    bench.board = None
    with pytest.raises(DeviceError, match="disconnected and not back"):
        trigger.fire()


def test_wrong_device_on_port_is_refused():
    class Modem(FakeBoard):
        def write(self, data: bytes) -> int:
            self.loop.write(b"OK\n")
            return len(data)

    with pytest.raises(DeviceError, match="does not answer as an sssphase board"):
        open_device(Bench(Modem()), "trigger")


def test_ports_found_by_vid_pid_and_serial(monkeypatch):
    ports = [SimpleNamespace(device="/dev/ttyS0", vid=None, pid=None, serial_number=None),
             SimpleNamespace(device="/dev/ttyUSB0", vid=0x0403, pid=0x6001, serial_number="A10K"),
             SimpleNamespace(device="/dev/ttyACM3", vid=0x1234, pid=0x5678, serial_number=None)]
    assert sd.list_boards(lambda: ports) == [("A10K", "/dev/ttyUSB0", "FTDI FT232R serial board")]
    monkeypatch.setenv("SSS_SERIAL_IDS", "1234:5678")
    assert [b[0] for b in sd.list_boards(lambda: ports)] == ["A10K", "ttyACM3"]
    monkeypatch.setenv("SSS_SERIAL_IDS", "nonsense")
    with pytest.raises(DeviceError, match="not vid:pid"):
        sd.list_boards(lambda: ports)


def test_real_pyserial_enumeration_without_board():
    with pytest.raises(DeviceNotFound, match="no device found: no serial port with a board USB id"):
        sd.SerialProvider("trigger").discover()
