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


PluginBackends = Callable[[], Iterable[tuple[str, object]]]
_plugin_backends: PluginBackends | None = None
_told: set[str] = set()  # the plugin problems warned of (once per process)


def use_plugin_backends(source: PluginBackends | None) -> None:
    """Where plugin backends come from: ``source()`` returns ``(plugin name, its sssphase_model_backends result or
    the exception it raised)``, earliest plugin first. The plugin manager registers itself here when it is imported
    (core does not import the plugin layer); None: the built-ins only."""
    global _plugin_backends
    _plugin_backends = source


def _warn_once(text: str) -> None:
    import warnings

    if text not in _told:
        _told.add(text)
        warnings.warn(text, UserWarning, stacklevel=3)


def backends_result_problem(result: object) -> str | None:
    """Why a plugin's ``sssphase_model_backends()`` result is no ``{name: factory}`` (names non-empty text,
    factories callable), or None."""
    if not isinstance(result, dict):
        return f"returned {type(result).__name__}, not {{name: factory}}"
    for name, factory in result.items():
        if not isinstance(name, str) or not name.strip():
            return f"returned a backend named {name!r}: names are non-empty text"
        if not callable(factory):
            return f"returned backend {name!r} as {type(factory).__name__} {str(factory)[:30]!r}, not a factory (callable)"
    return None


def backend_plugins() -> dict[str | None, list[str] | None]:
    """Whose each backend is, as :func:`available_backends` decides: {plugin: the names it owns} (``None`` for the
    built-ins), and ``None`` for a plugin whose hook raised or returned no ``{name: factory}`` (warned of)."""
    owners: dict[str | None, list[str] | None] = {None: list(BUILTIN)}
    available_backends(owners)
    return owners


def available_backends(owners: dict[str | None, list[str] | None] | None = None) -> dict[str, Callable[..., FootprintBackend]]:
    """{name: factory} of the built-ins and of every plugin implementing ``sssphase_model_backends``. A name is the
    first owner's: the built-ins', then the earliest plugin's (a plugin's ``analytic`` replaced the built-in without
    a word); a plugin whose hook raised, or returned no ``{name: factory}``, is left out. Each is warned of once.
    ``owners``, when given, gets each plugin's own names (:func:`backend_plugins`)."""
    found = sssphase_model_backends()
    owner = dict.fromkeys(found, "a built-in backend")
    owners = {} if owners is None else owners
    for plugin, result in _plugin_backends() if _plugin_backends is not None else []:
        if isinstance(result, BaseException):
            _warn_once(f"model backend plugin {plugin} failed ({type(result).__name__}: {str(result)[:160]}): its "
                       "backends are left out (sss plugins lists it)")
            owners[plugin] = None
            continue
        problem = backends_result_problem(result)
        if problem is not None:
            _warn_once(f"model backend plugin {plugin} {problem}: its backends are left out")
            owners[plugin] = None
            continue
        owners[plugin] = []
        for name, factory in result.items():
            if name in found:
                _warn_once(f"backend {name!r} of plugin {plugin} is left out: {name!r} is {owner[name]} (rename it)")
                continue
            found[name], owner[name] = factory, f"plugin {plugin}'s"
            owners[plugin].append(name)  # type: ignore[union-attr]
    return found


def accepted_options(name: str, offered: dict[str, object]) -> dict[str, object]:
    """Of ``offered`` (what relighting knows of a view: ``patch``, ``black``, ``device``, ``checkpoint``), those
    backend ``name``'s factory takes: every one where it takes ``**options``, else those it names (a plugin's
    factory was called with none, so a trained plugin backend never got its weights nor the session's patch size)."""
    import inspect

    factory = available_backends().get(name)
    try:
        parameters = inspect.signature(factory).parameters.values() if factory is not None else ()
    except (TypeError, ValueError):  # (a builtin or C callable without a signature: nothing offered)
        return {}
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return dict(offered)
    names = {p.name for p in parameters if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)}
    return {k: v for k, v in offered.items() if k in names}


def get_backend(name: str, **options: object) -> FootprintBackend:
    """Build backend ``name`` with its options (e.g. ``checkpoint=...`` for torch)."""
    backends = available_backends()
    if name not in backends:
        raise InputError(f"unknown model backend {name!r}; available: {', '.join(sorted(backends))}")
    return backends[name](**options)


__all__ = ["BUILTIN", "FootprintBackend", "Query", "accepted_options", "as_patches", "available_backends", "get_backend",
           "hookimpl",
           "use_plugin_backends"]
