"""LightCrafter 4500: DLPC350 HID packets checked byte for byte against the programmer's guide layout."""

from __future__ import annotations

import numpy as np
import pytest
from dev_fakes import FakeDlpc350Hid, FakeHidApi, FakeWindow

from sssphase_plugins import lightcrafter as lcr
from sssphase_plugins.drivers import DeviceError, DeviceNotFound


def report(*head_and_body: int) -> bytes:
    """Report ID 0 + the given bytes, zero-padded to the 64-byte report."""
    return bytes([0, *head_and_body]).ljust(65, b"\x00")


def test_write_packet_layout():
    # flags 0x40 (write, reply wanted), seq 5, length 3 (2 command bytes + 1), CMD3 0x1B, CMD2 0x1A, payload 1
    assert lcr.pack_message(0x1A1B, b"\x01", seq=5) == [report(0x40, 0x05, 0x03, 0x00, 0x1B, 0x1A, 0x01)]


def test_read_packet_layout():
    # flags 0xC0 (read, reply wanted), length 2: the command only
    assert lcr.pack_message(0x1A0A, read=True, seq=0) == [report(0xC0, 0x00, 0x02, 0x00, 0x0A, 0x1A)]
    assert lcr.pack_message(0x0205, read=True, seq=255) == [report(0xC0, 0xFF, 0x02, 0x00, 0x05, 0x02)]


def test_long_message_continues_in_raw_reports():
    payload = bytes(range(90))  # 30 LUT entries: 92-byte body, 96-byte message
    reports = lcr.pack_message(0x1A34, payload, seq=1)
    assert len(reports) == 2 and all(len(r) == 65 and r[0] == 0 for r in reports)
    assert reports[0][1:7] == bytes([0x40, 0x01, 92, 0x00, 0x34, 0x1A])
    assert reports[0][7:] == payload[:58]  # 64 - 4 header - 2 command bytes
    assert reports[1][1:33] == payload[58:] and reports[1][33:] == bytes(32)


def test_lut_entry_words():
    # 8-bit pattern 0 (G7..G0), all LEDs, external positive (VSYNC) trigger, buffer swap
    assert lcr.LutEntry(pattern=0, bit_depth=8, leds=7, trigger=1, buffer_swap=True).word().to_bytes(3, "little") == b"\x01\x78\x04"
    # 8-bit pattern 2 (B7..B0), blue LED only
    assert lcr.LutEntry(pattern=2, bit_depth=8, leds=4, trigger=1, buffer_swap=True).word().to_bytes(3, "little") == b"\x09\x48\x04"
    entry = lcr.LutEntry(pattern=23, bit_depth=1, leds=1, trigger=3, invert=True, insert_black=True, buffer_swap=False,
                         trigger_out_prev=True)
    assert entry.word() == 3 | 23 << 2 | 1 << 8 | 1 << 12 | 1 << 16 | 1 << 17 | 1 << 19
    with pytest.raises(DeviceError, match="invalid pattern LUT entry"):
        lcr.LutEntry(pattern=25).word()


def test_pattern_mode_command_sequence():
    dev = FakeDlpc350Hid(validate_status=0x08)
    warnings = lcr.Dlpc350(dev, poll_s=0).configure_pattern(16_000, 16_666)
    assert warnings == ["no post-vector"]
    writes = [(c, p) for f, _s, c, p in dev.commands if not f & 0x80]
    assert writes == [
        (0x1A24, b"\x00"),  # stop
        (0x1A1B, b"\x01"),  # pattern display mode
        (0x1A22, b"\x00"),  # patterns from the video port
        (0x1A31, b"\x00\x01\x00\x00"),  # 1 LUT entry, repeat, 1 pattern for trigger out 2, 1 image
        (0x1A23, b"\x00"),  # VSYNC trigger
        (0x1A29, bytes.fromhex("803e0000" "1a410000")),  # 16000 us, 16666 us
        (0x1A33, b"\x02"), (0x1A32, b"\x00"), (0x1A34, b"\x01\x78\x04"), (0x1A33, b"\x00"),  # pattern LUT
        (0x1A1D, b"\x00\xbb\xbb"),  # trigger out 1: normal polarity, no delays
        (0x1A1A, b"\x00"),  # validate
        (0x1A24, b"\x02"),  # start
    ]
    seqs = [s for _f, s, _c, _p in dev.commands]
    assert seqs == list(range(len(seqs)))  # one sequence number per message
    reads = [c for f, _s, c, _p in dev.commands if f & 0x80]
    assert reads.count(0x1A1A) == 2  # polled until the busy bit cleared


def test_video_mode_and_status_readback():
    dev = FakeDlpc350Hid()
    dlpc = lcr.Dlpc350(dev, poll_s=0)
    dlpc.configure_video()
    assert dev.written(0x1A1B) == [b"\x00"] and dev.written(0x1A00) == [b"\x08"]  # parallel port, 24 bit
    status = dlpc.status()
    assert status["init_done"] and status["errors"] == [] and status["memory_test_ok"]
    assert status["sequencer_running"] and status["source_locked"] and not status["parked"]
    assert dlpc.version()["application"] == "3.0.1"


def test_refusals_and_validation_errors_are_clear():
    with pytest.raises(DeviceError, match=r"refused display_mode 0x1A1B \(payload 01\)"):
        lcr.Dlpc350(FakeDlpc350Hid(nack={0x1A1B})).set_display_mode(True)
    with pytest.raises(DeviceError, match="pattern number invalid"):
        lcr.Dlpc350(FakeDlpc350Hid(validate_status=0x02), poll_s=0).validate()
    with pytest.raises(DeviceError, match="sequence abort"):
        lcr.Dlpc350(FakeDlpc350Hid(hw_status=0x41)).check_hardware()
    with pytest.raises(DeviceError, match="exposure"):
        lcr.Dlpc350(FakeDlpc350Hid()).set_exposure_period(20_000, 16_666)
    with pytest.raises(DeviceError, match="trigger-out delays"):
        lcr.Dlpc350(FakeDlpc350Hid()).set_trigger_out1(rising_delay_us=3.0)


def test_trigger_out_delay_codes():
    dev = FakeDlpc350Hid()
    lcr.Dlpc350(dev).set_trigger_out1(invert=True, rising_delay_us=-20.0, falling_delay_us=1.0)
    assert dev.written(0x1A1D) == [bytes([1, 0, 187 + 9])]  # 0 = -20.05 us; each step 0.107 us


def open_projector(dev: FakeDlpc350Hid, window: FakeWindow, mode: str):
    def make_window(display: int, **kwargs):
        window.display = display
        return window

    provider = lcr.LightCrafterProvider(hid_api=lambda: FakeHidApi(dev), displays=lambda: [(1920, 1080), (912, 1140)],
                                        window=make_window)
    (info,) = provider.discover()
    assert info.id == "lcr4500:LCR1"
    proj = provider.open(info.id, {"lcr4500": {"mode": mode, "latency_s": 0}}, {})
    assert window.display == 1  # the 912x1140 display
    return proj


def test_pattern_mode_projector_packs_green_channel_and_checks_status():
    dev, window = FakeDlpc350Hid(), FakeWindow()
    proj = open_projector(dev, window, "pattern")
    assert proj.resolution == (912, 1140)
    gray = np.linspace(0, 1, 912 * 1140, dtype=np.float32).reshape(1140, 912)
    receipt = proj.show(gray, tag="psp/x/0")
    assert receipt.tag == "psp/x/0" and receipt.frame_id == 1
    pixels = window.frames[-1][1]
    assert pixels.shape == (1140, 912, 3)
    np.testing.assert_array_equal(pixels[..., 1], np.rint(gray * 255).astype(np.uint8))
    assert not pixels[..., 0].any() and not pixels[..., 2].any()
    hw_reads = sum(1 for f, _s, c, _p in dev.commands if c == 0x1A0A and f & 0x80)
    assert hw_reads == 2  # after configuring, and after the frame
    proj.close()
    assert dev.written(0x1A24)[-1] == b"\x00" and window.closed  # sequence stopped on close


def test_disconnect_mid_capture_raises_clear_error():
    dev, window = FakeDlpc350Hid(), FakeWindow()
    proj = open_projector(dev, window, "video")
    image = np.zeros((1140, 912), np.float32)
    proj.show(image)
    dev.connected = False  # USB cable pulled
    with pytest.raises(DeviceError, match="USB HID link lost.*still connected"):
        proj.show(image)
    dev.connected, window.alive = True, False  # HDMI side gone instead
    with pytest.raises(DeviceError, match="window process exited"):
        proj.show(image)
    proj.close()


def test_wrong_hdmi_resolution_is_refused():
    with pytest.raises(DeviceError, match="needs 912x1140"):
        open_projector(FakeDlpc350Hid(), FakeWindow(size=(1920, 1080)), "video")


def test_discovery_without_device():
    class NoLightCrafter:
        def enumerate(self, vid, pid):
            return []

    with pytest.raises(DeviceNotFound, match="no device found: hidapi sees no LightCrafter 4500"):
        lcr.LightCrafterProvider(hid_api=NoLightCrafter).discover()


def test_real_hidapi_finds_no_device():
    pytest.importorskip("hid")
    with pytest.raises(DeviceNotFound, match="no device found"):
        lcr.LightCrafterProvider().discover()


def test_attached_but_not_accessible_points_to_udev(tmp_path, monkeypatch):
    from sssphase_plugins import usb_util

    dev = tmp_path / "1-4"
    dev.mkdir()
    for name, value in {"idVendor": "0451", "idProduct": "6401", "product": "DLPC350"}.items():
        (dev / name).write_text(value)
    (found,) = usb_util.sysfs_usb_devices(0x0451, 0x6401, root=tmp_path)
    assert (found.vid, found.pid, found.product, found.key) == (0x0451, 0x6401, "DLPC350", "port-1-4")
    assert usb_util.sysfs_usb_devices(0x03E7, root=tmp_path) == []

    class HiddenLightCrafter:
        def enumerate(self, vid, pid):
            return []

    monkeypatch.setattr(lcr, "sysfs_usb_devices", lambda vid, pid: [found])
    with pytest.raises(DeviceError, match="attached but hidapi cannot open it: install the udev rules"):
        lcr.LightCrafterProvider(hid_api=HiddenLightCrafter).discover()
