"""`sss udev install`: install the udev rules of the hardware plugins (see ``udev/README.md``)."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import typer
from rich.console import Console

from sssphase_core.errors import InputError

RULES_SOURCE = Path(__file__).resolve().parents[1] / "udev"
RULES_DIR = Path("/etc/udev/rules.d")
console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)


def rules_files(source: Path = RULES_SOURCE) -> list[Path]:
    files = sorted(source.glob("*.rules"))
    if not files:
        raise InputError(f"no udev rules found in {source} (install sssphase from a source checkout)")
    return files


def install_commands(files: list[Path], dest: Path) -> list[list[str]]:
    """The commands that install ``files`` into ``dest`` and make udev apply them."""
    copies = [["install", "-m", "0644", str(f), str(dest / f.name)] for f in files]
    return [*copies, ["udevadm", "control", "--reload-rules"], ["udevadm", "trigger"]]


def install_rules(dest: Path, *, dry_run: bool, is_root: bool, run: Callable[[list[str]], int],
                  have_udevadm: bool, echo: Callable[[str], None]) -> int:
    """Install the rules (or say what would be done); returns the exit code."""
    if dest.exists() and not dest.is_dir():
        raise InputError(f"--rules-dir {dest} is a file: give the folder udev reads rules from (default {RULES_DIR})")
    commands = install_commands(rules_files(), dest)
    if dry_run or not is_root:
        echo("dry run, nothing changed; these commands install the rules:" if dry_run
             else "installing udev rules needs root; run:")
        for cmd in commands:
            echo(f"  {'' if dry_run else 'sudo '}{shlex.join(cmd)}")
        return 0 if dry_run else 1
    dest.mkdir(parents=True, exist_ok=True)
    for cmd in commands:
        if cmd[0] == "udevadm" and not have_udevadm:
            echo(f"skipped (udevadm not found): {shlex.join(cmd)}")
            continue
        if cmd[0] == "install":
            src, dst = cmd[-2:]
            shutil.copyfile(src, dst)
            os.chmod(dst, 0o644)
            echo(f"copied {src} -> {dst}")
        elif run(cmd) != 0:
            echo(f"failed: {shlex.join(cmd)}")
            return 1
        else:
            echo(f"ran: {shlex.join(cmd)}")
    echo("done: replug the devices, and add the daemon's user to the plugdev and video groups")
    return 0


def udev_install(
    dry_run: bool = typer.Option(False, "--dry-run", help="Only print what would be done."),
    rules_dir: Path = typer.Option(RULES_DIR, help="Where udev reads rules from."),
) -> None:
    """Copy the device rules into the udev rules directory, reload udev and re-trigger the devices."""
    code = install_rules(rules_dir, dry_run=dry_run, is_root=os.geteuid() == 0,
                         run=lambda cmd: subprocess.run(cmd, check=False).returncode,
                         have_udevadm=shutil.which("udevadm") is not None, echo=console.print)
    raise typer.Exit(code)


def register(groups: dict[str, typer.Typer]) -> None:
    udev = typer.Typer(no_args_is_help=True, help="udev rules for the supported USB devices.")
    udev.command("install")(udev_install)
    groups["root"].add_typer(udev, name="udev")
