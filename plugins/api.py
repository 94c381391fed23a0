"""The public API for device-plugin authors: everything a third-party plugin needs, from one module.

A plugin imports only from here (``from sssphase_plugins.api import hookimpl, DeviceInfo, ...``); the
modules behind it (``hookspecs``, ``drivers``, ``usb_util``) may be rearranged without breaking it.

- :data:`hookimpl` marks the hook implementations (``sssphase_cameras``, ``sssphase_projectors``,
  ``sssphase_triggers``, ``sssphase_turntables``: see :mod:`sssphase_plugins.hookspecs`);
- the hooks return :class:`DeviceProvider` objects whose ``open()`` gives a driver that follows
  :class:`Camera` (or :class:`TriggeredCamera`), :class:`Projector` (or :class:`PreloadingProjector`),
  :class:`Trigger` or :class:`Turntable`;
- drivers exchange :class:`Frame` and :class:`ShowReceipt` records and raise :class:`DeviceError`
  (discovery that finds nothing raises :class:`DeviceNotFound`); :func:`check_pattern` checks a
  pattern handed to ``show`` against the projector's resolution;
- :func:`optional_import` imports a hardware library inside ``discover``/``open`` with the standard
  message when it is missing, :func:`plugin_options` reads the plugin's own table of rig options and checks it
  against the settings the plugin declares (:func:`check_plugin_options` for a table already read).

:mod:`sssphase_plugins.conformance` holds a driver to the protocols from a plugin's own tests
(``check_driver(kind, make)``); ``tests/devices/test_dev_conformance.py`` holds every built-in driver to them.
"""

from __future__ import annotations

from sssphase_plugins.drivers import (
    DEVICE_KINDS,
    Camera,
    DeviceError,
    DeviceInfo,
    DeviceKind,
    DeviceNotFound,
    DeviceProvider,
    Frame,
    PreloadingProjector,
    Projector,
    ShowReceipt,
    Trigger,
    TriggeredCamera,
    Turntable,
    check_pattern,
)
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.usb_util import check_plugin_options, optional_import, plugin_options

__all__ = [
    "DEVICE_KINDS",
    "Camera",
    "DeviceError",
    "DeviceInfo",
    "DeviceKind",
    "DeviceNotFound",
    "DeviceProvider",
    "Frame",
    "PreloadingProjector",
    "Projector",
    "ShowReceipt",
    "Trigger",
    "TriggeredCamera",
    "Turntable",
    "check_pattern",
    "check_plugin_options",
    "hookimpl",
    "optional_import",
    "plugin_options",
]
