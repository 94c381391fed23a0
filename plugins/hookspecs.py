"""Hook specifications for device plugins (pluggy project name ``sssphase``).

A plugin is a module (or object) with functions decorated by :data:`hookimpl`. Third-party plugins
register through the ``sssphase_devices`` entry-point group, like pytest plugins do. Each hook
returns :class:`~sssphase_plugins.drivers.DeviceProvider` objects only: device I/O never runs
inside a hook call (discovery and opening happen later, in the daemon).
"""

from __future__ import annotations

import pluggy

PROJECT = "sssphase"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def sssphase_cameras() -> list:
    """Return camera providers."""


@hookspec
def sssphase_projectors() -> list:
    """Return projector providers."""


@hookspec
def sssphase_triggers() -> list:
    """Return hardware-trigger providers."""


@hookspec
def sssphase_turntables() -> list:
    """Return turntable / stage providers."""


DEVICE_HOOKS = {
    "camera": "sssphase_cameras",
    "projector": "sssphase_projectors",
    "trigger": "sssphase_triggers",
    "turntable": "sssphase_turntables",
}
