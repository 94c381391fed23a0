"""Model backends: ``torch`` (the paper's method) and ``analytic`` (a physics baseline), plus plugins.

Backends register through the pluggy hook ``sssphase_model_backends`` (entry-point group
``sssphase_backends``, spec in :mod:`sssphase_core.learning.backends.hookspecs`). This package registers the
built-ins itself (entry point ``builtin = "sssphase_core.learning.backends"``) with lazy factories, so
loading the plugin manager (e.g. in the daemon) never imports torch.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable

import pluggy

from sssphase_core.errors import InputError
from sssphase_core.learning.backends.base import FootprintBackend, Query, as_patches

#: Same project name as the plugin manager (``sssphase_plugins.hookspecs.PROJECT``).
hookimpl = pluggy.HookimplMarker("sssphase")

BUILTIN = {
    "torch": "sssphase_core.learning.backends.torch_backend:TorchBackend",
    "analytic": "sssphase_core.learning.backends.analytic_backend:AnalyticBackend",
}


def _lazy(target: str) -> Callable[..., FootprintBackend]:
    """A factory that imports ``module:Class`` only when a backend is built."""

    def build(**options: object) -> FootprintBackend:
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)(**options)

    build.__name__ = build.__qualname__ = target.split(":")[1]
    return build


@hookimpl
def sssphase_model_backends() -> dict[str, Callable[..., FootprintBackend]]:
    return {name: _lazy(target) for name, target in BUILTIN.items()}


PluginBackends = Callable[[], Iterable[dict[str, Callable[..., FootprintBackend]]]]
_plugin_backends: PluginBackends | None = None


def use_plugin_backends(source: PluginBackends | None) -> None:
    """Where plugin backends come from: ``source()`` returns the ``sssphase_model_backends`` results,
    earliest plugin first. The plugin manager registers itself here when it is imported (core does not
    import the plugin layer); None: the built-ins only."""
    global _plugin_backends
    _plugin_backends = source


def available_backends() -> dict[str, Callable[..., FootprintBackend]]:
    """{name: factory} of the built-ins and of every plugin implementing ``sssphase_model_backends``
    (a later plugin's name replaces an earlier one's)."""
    found = sssphase_model_backends()
    for result in _plugin_backends() if _plugin_backends is not None else []:
        found.update(result)
    return found


def get_backend(name: str, **options: object) -> FootprintBackend:
    """Build backend ``name`` with its options (e.g. ``checkpoint=...`` for torch)."""
    backends = available_backends()
    if name not in backends:
        raise InputError(f"unknown model backend {name!r}; available: {', '.join(sorted(backends))}")
    return backends[name](**options)


__all__ = ["BUILTIN", "FootprintBackend", "Query", "as_patches", "available_backends", "get_backend", "hookimpl",
           "use_plugin_backends"]
