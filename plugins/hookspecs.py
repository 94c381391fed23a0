"""Hook specifications for device plugins (pluggy project name ``sssphase``).

A plugin is a module (or object) with functions decorated by :data:`hookimpl`. Third-party plugins
register through the ``sssphase_devices`` entry-point group, like pytest plugins do. Each hook
returns :class:`~sssphase_plugins.drivers.DeviceProvider` objects only: device I/O never runs
inside a hook call (discovery and opening happen later, in the daemon).
"""

from __future__ import annotations

import pluggy

from sssphase_plugins.drivers import DeviceProvider

PROJECT = "sssphase"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def sssphase_cameras() -> list[DeviceProvider]:
    """Return the camera providers this plugin offers.

    :return: providers whose ``kind`` is ``"camera"``; each ``open()`` returns a
        :class:`~sssphase_plugins.drivers.Camera` (a :class:`~sssphase_plugins.drivers.TriggeredCamera`
        if it can expose on a trigger pulse). Build them cheaply: no device I/O or heavy import here.

    Called once per plugin manager; an exception is reported for this plugin only (``sss plugins``).
    """


@hookspec
def sssphase_projectors() -> list[DeviceProvider]:
    """Return the projector providers this plugin offers.

    :return: providers whose ``open()`` returns a :class:`~sssphase_plugins.drivers.Projector` (a
        :class:`~sssphase_plugins.drivers.PreloadingProjector` if it takes a capture's patterns in advance).
    """


@hookspec
def sssphase_triggers() -> list[DeviceProvider]:
    """Return the hardware-trigger providers this plugin offers.

    :return: providers whose ``open()`` returns a :class:`~sssphase_plugins.drivers.Trigger`; a rig
        opened with one fires it once per captured frame and takes the frame with the camera's
        ``wait_frame``.
    """


@hookspec
def sssphase_turntables() -> list[DeviceProvider]:
    """Return the turntable / stage providers this plugin offers.

    :return: providers whose ``open()`` returns a :class:`~sssphase_plugins.drivers.Turntable`; the
        capture moves it to ``360 * view / views`` degrees before each view.
    """


DEVICE_HOOKS = {
    "camera": "sssphase_cameras",
    "projector": "sssphase_projectors",
    "trigger": "sssphase_triggers",
    "turntable": "sssphase_turntables",
}
