"""udev rules content and `sss udev install`."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from sssphase_cli import cmd_udev
from sssphase_core.errors import InputError
from sssphase_plugins import basler_camera


def rules_text() -> str:
    return "".join(f.read_text() for f in cmd_udev.rules_files())


def test_rules_cover_every_supported_device_group_based():
    rules = [line for line in rules_text().splitlines() if line and not line.startswith("#")]
    assert rules and all('GROUP="plugdev", MODE="0660"' in line for line in rules)
    text = "\n".join(rules)
    for pattern in (r'SUBSYSTEM=="usb", ATTR\{idVendor\}=="0451", ATTR\{idProduct\}=="6401"',
                    r'SUBSYSTEM=="hidraw", ATTRS\{idVendor\}=="0451", ATTRS\{idProduct\}=="6401"',
                    r'SUBSYSTEM=="usb", ATTRS\{idVendor\}=="03e7", GROUP',
                    rf'SUBSYSTEM=="usb", ATTRS\{{idVendor\}}=="{basler_camera.USB_VENDOR:04x}", GROUP',
                    r'SUBSYSTEM=="tty", ATTRS\{idVendor\}=="0403", ATTRS\{idProduct\}=="6001"',
                    r'SUBSYSTEM=="tty", ATTRS\{idVendor\}=="2e8a", ATTRS\{idProduct\}=="000a"'):
        assert re.search(pattern, text), pattern


def test_serial_rules_match_the_plugin_ids():
    from sssphase_plugins.serial_devices import BOARD_IDS

    for vid, pid in BOARD_IDS:
        assert f'ATTRS{{idVendor}}=="{vid:04x}", ATTRS{{idProduct}}=="{pid:04x}"' in rules_text()


def test_install_copies_reloads_and_reports(tmp_path):
    ran, said = [], []
    code = cmd_udev.install_rules(tmp_path / "rules.d", dry_run=False, is_root=True,
                                     run=lambda cmd: ran.append(cmd) or 0, have_udevadm=True, echo=said.append)
    assert code == 0
    assert (tmp_path / "rules.d" / "60-sssphase.rules").read_text() == rules_text()
    assert ran == [["udevadm", "control", "--reload-rules"], ["udevadm", "trigger"]]
    assert said[0].startswith("copied") and said[-1].startswith("done")


def test_not_root_prints_the_commands(tmp_path):
    said: list[str] = []
    code = cmd_udev.install_rules(tmp_path, dry_run=False, is_root=False, run=lambda cmd: 1 / 0,
                                     have_udevadm=True, echo=said.append)
    assert code == 1 and "needs root" in said[0]
    assert any(s.strip().startswith("sudo install -m 0644") for s in said)
    assert said[-1].strip() == "sudo udevadm trigger" and not list(tmp_path.iterdir())


def test_cli_dry_run(tmp_path):
    app = typer.Typer()
    cmd_udev.register({"root": app})
    app.command("noop")(lambda: None)  # keep `udev` a sub-command group
    result = CliRunner().invoke(app, ["udev", "install", "--dry-run", "--rules-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "dry run" in result.output and "udevadm control --reload-rules" in result.output
    assert not list(tmp_path.iterdir())


def test_a_rules_dir_that_is_a_file_is_one_line_and_left_alone(tmp_path):
    """`--rules-dir FILE` failed as "FILE: File exists" (from the folder's creation), naming no option."""
    afile = tmp_path / "afile"
    afile.write_text("mine")
    for dry_run in (True, False):
        with pytest.raises(InputError, match=rf"--rules-dir {afile} is a file: give the folder udev reads rules from"):
            cmd_udev.install_rules(afile, dry_run=dry_run, is_root=True, run=lambda cmd: 0, have_udevadm=True,
                                   echo=lambda line: None)
    assert afile.read_text() == "mine"
