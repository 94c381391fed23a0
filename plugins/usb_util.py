"""Plumbing shared by the hardware plugins: optional imports, per-plugin options, USB identity and reset.

* :func:`optional_import` imports a hardware library only when a plugin is used; a missing library
  becomes a :class:`DeviceError` that says which extra to install (discovery reports it as the
  reason no device was found, never a traceback).
* :func:`plugin_options` reads a plugin's own table of the rig options (``[options.uvc]`` in a rig
  file), so the settings of several plugins in one rig never collide, and checks it against the settings the
  plugin declares (:func:`check_plugin_options`: an unknown key or a value of the wrong type is refused by name).
* :func:`sysfs_identity` reads a device's USB identity (VID/PID/serial/product) from Linux sysfs, so
  discovery needs no USB library and no access rights to the device node.
* :func:`find_usb`, :func:`reset_usb` use pyusb (extra ``usb``; needs the libusb-1.0 system library)
  for raw USB operations: the identity of an attached device and a USB port reset, which recovers a
  LightCrafter or camera whose firmware stopped answering (like unplugging and replugging it).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from sssphase_plugins.drivers import DeviceError, DeviceNotFound

SYSFS_USB_DEVICES = Path("/sys/bus/usb/devices")


def optional_import(module: str, extra: str, library: str | None = None) -> ModuleType:
    """Import a hardware library, or raise ``DeviceNotFound("no device: <lib> not installed (...)")``."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise DeviceNotFound(f"no device: {library or module} not installed (pip install sssphase[{extra}])") from None


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


#: The kinds of value a plugin's option may declare (:func:`check_plugin_options`): what it must be, said to the user.
OPTION_KINDS: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "number": ("a number", _number),
    "positive": ("a positive number", lambda v: _number(v) and v > 0),
    "seconds": ("a number of seconds >= 0", lambda v: _number(v) and v >= 0),
    "whole": ("a whole number >= 0", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0),
    "count": ("a whole number >= 1", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1),
    "bool": ("true or false (no quotes)", lambda v: isinstance(v, bool)),
    "text": ("a string", lambda v: isinstance(v, str)),
    "any": ("", lambda v: True),  # the plugin checks it itself (a basler roi)
}


def check_plugin_options(table: Mapping[str, Any], name: str, known: Mapping[str, str | tuple[str, ...]],
                         device_id: str | None = None) -> dict[str, Any]:
    """``table`` (a plugin's ``[options.<name>]``), checked against ``known``: setting -> one of
    :data:`OPTION_KINDS`, or a tuple of the strings it may be. A setting not in ``known`` (a misspelt ``latency``) or
    of the wrong type (``gain = "high"``; ``verify = "false"``, which ``bool()`` read as true; ``buffers = 0.5``, which
    ``int()`` made 0) raises a :class:`DeviceError` naming it: either was used as the default, or as something else,
    without a word. -> the table as a dict."""
    who = device_id or name
    unknown = sorted(str(k) for k in table if k not in known)
    if unknown:
        raise DeviceError(f"{who}: unknown [options.{name}] setting(s) {', '.join(unknown)[:200]} "
                          f"(known: {', '.join(sorted(known))})")
    for key, value in table.items():
        kind = known[key]
        if isinstance(kind, tuple):
            if value not in kind or not isinstance(value, str):
                raise DeviceError(f"{who}: [options.{name}] {key} must be one of {', '.join(kind)}, got {value!r:.60}")
            continue
        what, ok = OPTION_KINDS[kind]
        if not ok(value):
            raise DeviceError(f"{who}: [options.{name}] {key} must be {what}, got {value!r:.60}")
    return dict(table)


def plugin_options(options: Mapping[str, Any], name: str, known: Mapping[str, str | tuple[str, ...]] | None = None,
                   device_id: str | None = None) -> dict[str, Any]:
    """The ``[options.<plugin>]`` table of a rig's options (empty when absent); with ``known``, checked by
    :func:`check_plugin_options` (errors named after ``device_id``)."""
    table = options.get(name, {})
    if not isinstance(table, Mapping):
        raise DeviceError(f"rig option {name!r} must be a table of {name} settings, got {type(table).__name__}")
    return dict(table) if known is None else check_plugin_options(table, name, known, device_id)


def no_device(reason: str) -> DeviceError:
    """The error discovery raises when the library works but sees no device: says why and what to check."""
    return DeviceNotFound(f"no device found: {reason}")


@dataclass(frozen=True)
class UsbIdentity:
    """Who a USB device is; ``port`` is the sysfs bus path (``1-2.3``), stable while it stays plugged in."""

    vid: int
    pid: int
    serial: str = ""
    manufacturer: str = ""
    product: str = ""
    port: str = ""

    @property
    def key(self) -> str:
        """A stable name: the serial number, else the bus port."""
        return self.serial or f"port-{self.port}"


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def sysfs_identity(node: Path) -> UsbIdentity | None:
    """The USB device that a sysfs node (e.g. ``/sys/class/video4linux/video0/device``) belongs to."""
    try:
        path = node.resolve()
    except OSError:
        return None
    for candidate in (path, *path.parents):
        vid = _read(candidate / "idVendor")
        if vid:
            return UsbIdentity(int(vid, 16), int(_read(candidate / "idProduct") or "0", 16), _read(candidate / "serial"),
                               _read(candidate / "manufacturer"), _read(candidate / "product"), candidate.name)
    return None


def sysfs_usb_devices(vid: int, pid: int | None = None, root: Path = SYSFS_USB_DEVICES) -> list[UsbIdentity]:
    """Attached USB devices with this VID (and PID), read from sysfs; empty when there is no sysfs."""
    found = []
    for dev in sorted(root.glob("*")) if root.is_dir() else []:
        ident = sysfs_identity(dev) if (dev / "idVendor").exists() else None
        if ident is not None and ident.vid == vid and (pid is None or ident.pid == pid):
            found.append(ident)
    return found


def _pyusb():
    return optional_import("usb.core", "usb", "pyusb")


def find_usb(vid: int, pid: int, serial: str | None = None) -> list[UsbIdentity]:
    """Devices with this VID/PID (and serial) as pyusb sees them; clear errors when it cannot look."""
    core = _pyusb()
    try:
        devices = list(core.find(find_all=True, idVendor=vid, idProduct=pid))
    except core.NoBackendError:
        raise DeviceNotFound("no device: pyusb has no backend (install the libusb-1.0 system library, "
                          "e.g. apt install libusb-1.0-0)") from None
    out = []
    for dev in devices:
        try:
            serial_str = (dev.serial_number or "") if dev.iSerialNumber else ""
        except (ValueError, core.USBError):  # no permission to read string descriptors
            serial_str = ""
        port = f"{dev.bus}-{'.'.join(map(str, dev.port_numbers or ()))}"
        ident = UsbIdentity(dev.idVendor, dev.idProduct, serial_str, port=port)
        if serial is None or ident.serial == serial:
            out.append(ident)
    return out


def reset_usb(vid: int, pid: int, serial: str | None = None) -> UsbIdentity:
    """USB port reset of one device (the host re-enumerates it, like a replug). Returns who was reset."""
    core = _pyusb()
    matches = find_usb(vid, pid, serial)
    if not matches:
        raise no_device(f"no USB device {vid:04x}:{pid:04x}{f' with serial {serial}' if serial else ''} to reset")
    target = matches[0]
    for dev in core.find(find_all=True, idVendor=vid, idProduct=pid):
        if f"{dev.bus}-{'.'.join(map(str, dev.port_numbers or ()))}" == target.port:
            try:
                dev.reset()
            except core.USBError as exc:
                raise DeviceError(f"USB reset of {vid:04x}:{pid:04x} failed: {exc} "
                                  "(permission? install the udev rules: sss udev install)") from None
            return target
    raise no_device(f"USB device {vid:04x}:{pid:04x} went away before the reset")
