"""The one pluggy plugin manager for device plugins and model backends.

Loads, like pytest/tox do, the hook specifications (devices, and model backends from
``sssphase_core.learning.backends.hookspecs``), then the plugins of the entry-point groups
``sssphase_devices`` and ``sssphase_backends``, then any modules named in ``$SSS_PLUGINS``
(comma-separated, like ``PYTEST_PLUGINS``). A plugin that fails to import, implements an unknown
hook, or raises inside a hook is recorded with its name in ``load_errors`` and left out; the others
keep working.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import pluggy

from sssphase_core.errors import InputError
from sssphase_core.learning import backends
from sssphase_core.learning.backends import hookspecs as backend_hookspecs
from sssphase_plugins import hookspecs
from sssphase_plugins.drivers import DeviceInfo, DeviceNotFound, DeviceProvider

ENTRY_POINT_GROUPS = ("sssphase_devices", "sssphase_backends")
BUILTIN_PLUGINS = {"sim": "sssphase_plugins.sim_plugin"}
ENV_PLUGINS = "SSS_PLUGINS"


class PluginManager(pluggy.PluginManager):
    """pluggy's manager plus a record of plugins that could not be loaded or failed in a hook."""

    def __init__(self) -> None:
        super().__init__(hookspecs.PROJECT)
        self.load_errors: dict[str, str] = {}
        self.distributions: dict[int, tuple[str, str]] = {}  # id(plugin) -> (version, project) of an entry point's
        self.left_out: list[str] = []  # plugins named '-name' in $SSS_PLUGINS: neither imported nor called


@dataclass(frozen=True)
class PluginRecord:
    name: str
    kind: str  # "device", "backend", "device+backend", "broken", or "off" (left out by $SSS_PLUGINS)
    version: str
    source: str  # distribution, module path, or the error message
    ok: bool


_manager: PluginManager | None = None


def _error_text(exc: BaseException) -> str:
    """``Type: message`` in one line: pluggy's PluginValidationError says its cause (an argument the hook spec does
    not have) on its later lines, which a one-line listing cut off."""
    text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    return f"{type(exc).__name__}: {text}".strip()


def _registration_error(pm: PluginManager, exc: BaseException) -> str:
    """One line for a plugin that could not be registered. pluggy's own words for a module registered twice end
    with the repr of every plugin, one module path after another over many lines."""
    first = str(exc).split("\n", 1)[0]
    if isinstance(exc, ValueError) and first.startswith("Plugin already registered under a different name: "):
        module = first.split("=", 1)[-1]
        other = next((n for n, p in pm.list_name_plugin() if p is not None and repr(p) == module), None)
        return (f"its module is already loaded as plugin {other!r}: two entry points (or {ENV_PLUGINS} entries) "
                "name one module; remove one")
    if isinstance(exc, ValueError) and first.startswith("Plugin name already registered: "):
        return "another plugin is registered under this name: rename one of the two entry points"
    if isinstance(exc, pluggy.PluginValidationError) and first.startswith("unknown hook "):
        import difflib

        hook = first.split("'")[1] if first.count("'") >= 2 else "?"
        hooks = sorted(h for h in dir(pm.hook) if h.startswith("sssphase_") and getattr(pm.hook, h).spec is not None)
        near = difflib.get_close_matches(hook, hooks, n=1)
        return (f"unknown hook {hook!r}{f' (did you mean {near[0]}?)' if near else ''}: the hooks are "
                f"{', '.join(hooks)}; one from a newer sssphase is marked hookimpl(optionalhook=True)")
    return _error_text(exc)


def _register_checked(pm: PluginManager, name: str, load: Any) -> None:
    """Register one plugin, isolating its failure (import error, unknown hook) under its name."""
    try:
        load()
        pm.check_pending()
    except (Exception, SystemExit) as exc:  # a broken third-party plugin must not take the others down
        plugin = pm.get_plugin(name)
        if plugin is not None:
            pm.unregister(plugin)
        pm.load_errors[name] = _registration_error(pm, exc)


def _ours(module: str) -> bool:
    """Whether ``module`` (an entry point's or a plugin's) is one of this package's built-in plugins."""
    return module.split(".", 1)[0] in ("sssphase_plugins", "sssphase_core")


def _name_taken(pm: PluginManager, name: str, module: str, where: str) -> bool:
    """Whether ``name`` is registered already; when by another module than ``module`` (a third-party entry point
    named ``basler``), record the newcomer as broken under ``name (where)``: it was dropped, or replaced the built-in
    one, without a word. The same module named twice (an entry point also in $SSS_PLUGINS) is no error."""
    registered = pm.get_plugin(name)
    if registered is None:
        return pm.is_blocked(name)  # (left out: not imported)
    other = getattr(registered, "__name__", type(registered).__name__)
    if other != module:
        fix = ("name another module in SSS_PLUGINS (a module there is registered under its own name)"
               if where == ENV_PLUGINS else "rename one of the two entry points")
        pm.load_errors[f"{name} ({where})"] = f"another plugin is registered under this name ({other}): {fix}"
    return True


def _register_entry_point(pm: PluginManager, ep: importlib.metadata.EntryPoint) -> None:
    """Register this one entry point (pluggy's ``load_setuptools_entrypoints(group, name)`` loads the first of every
    distribution's entry points of that name: a third-party ``basler`` earlier on the path took the built-in's place)
    and remember its distribution's version and name (read once: a distribution's metadata is parsed on each read,
    our README included)."""
    plugin = _imported(ep.name, ep.load) if not _ours(ep.module) else ep.load()
    pm.register(plugin, name=ep.name)
    if getattr(ep, "dist", None) is not None:
        pm.distributions[id(plugin)] = (str(ep.dist.version), str(ep.dist.name))


def build_plugin_manager() -> PluginManager:
    """A fresh manager with every hookspec and plugin loaded (see module docstring). The built-in plugins are
    registered first: a third-party plugin under one of their names is listed as broken, never in their place."""
    pm = PluginManager()
    pm.add_hookspecs(hookspecs)
    pm.add_hookspecs(backend_hookspecs)
    points = [ep for group in ENTRY_POINT_GROUPS for ep in importlib.metadata.entry_points(group=group)]
    points.sort(key=lambda ep: not _ours(ep.module))  # (stable: each group's order kept)
    entries = [m.strip() for m in os.environ.get(ENV_PLUGINS, "").split(",") if m.strip()]
    _leave_out(pm, [m[1:].strip() for m in entries if m.startswith("-")], [*BUILTIN_PLUGINS, *(ep.name for ep in points)])
    builtins = [(n, m) for n, m in BUILTIN_PLUGINS.items() if not any(ep.name == n and _ours(ep.module) for ep in points)]
    for name, module in builtins:  # ours when not installed with their entry points (a source tree)
        if not pm.is_blocked(name):
            _register_checked(pm, name, lambda n=name, m=module: pm.register(importlib.import_module(m), name=n))
    for ep in points:
        where = ep.dist.name if getattr(ep, "dist", None) is not None else ep.value
        if _name_taken(pm, ep.name, ep.module, where):
            continue
        _register_checked(pm, ep.name, lambda e=ep: _register_entry_point(pm, e))
    for module in (m for m in entries if not m.startswith("-")):
        if _name_taken(pm, module, module, ENV_PLUGINS):
            continue
        _register_checked(pm, module, lambda m=module: pm.register(_imported(m, lambda: importlib.import_module(m)),
                                                                   name=m))
    for name, plugin in pm.list_name_plugin():  # (listed as kind "none": nothing said why its devices never appeared)
        unmarked = _unmarked_hooks(pm, plugin) if plugin is not None and not pm.get_hookcallers(plugin) else []
        if unmarked and name not in pm.load_errors:
            pm.load_errors[name] = (f"provides nothing: its {', '.join(unmarked)} {'is' if len(unmarked) == 1 else 'are'} "
                                    "not marked @hookimpl (from sssphase_plugins.api import hookimpl)")
    return pm


def _leave_out(pm: PluginManager, names: list[str], installed: list[str]) -> None:
    """Block the plugins named ``-name`` in $SSS_PLUGINS (a broken or hanging plugin, or a library not wanted at
    all): they are neither imported nor called. A name no plugin has is said (a misspelling left it in)."""
    for name in names:
        if name not in installed:
            pm.load_errors[f"-{name} ({ENV_PLUGINS})"] = (f"no plugin is named {name!r} to leave out; the installed "
                                                          f"plugins: {', '.join(sorted(set(installed)))}")
            continue
        pm.set_blocked(name)
        pm.left_out.append(name)


def _imported(name: str, load: Any) -> Any:
    """A third-party plugin's module, imported within :func:`discovery_timeout_s`: one whose import blocks (a
    network mount, a device probed at import) hung `sss plugins` and `sss devices` for ever; it is named as broken
    and the others load (its import may finish later, unused)."""
    try:
        return _within(discovery_timeout_s(), load)
    except _Hung:
        raise TimeoutError(f"importing it did not finish within {discovery_timeout_s():g} s (it hangs at import): "
                           f"leave it out ({ENV_PLUGINS}=-{name}) or uninstall it") from None


def get_plugin_manager(*, refresh: bool = False) -> PluginManager:
    """The process-wide plugin manager (built on first use)."""
    global _manager
    if _manager is None or refresh:
        _manager = build_plugin_manager()
    return _manager


def _plugin_version(pm: PluginManager, plugin: object) -> tuple[str, str]:
    if id(plugin) in pm.distributions:
        return pm.distributions[id(plugin)]
    version = getattr(plugin, "__version__", None)
    module = getattr(plugin, "__name__", type(plugin).__name__)
    if version is None and module.startswith(("sssphase_plugins.", "sssphase_core.")):  # ours: the package's
        from sssphase_core import __version__ as version
    return str(version) if version is not None else "?", module


def plugin_records(pm: PluginManager | None = None) -> list[PluginRecord]:
    """Every plugin with its kind and version, broken ones included (``ok=False``)."""
    pm = pm or get_plugin_manager()
    device_hooks = set(hookspecs.DEVICE_HOOKS.values())
    records = []
    for name, plugin in pm.list_name_plugin():
        if plugin is None or name in pm.load_errors:  # a plugin whose hook failed is listed once, as broken
            continue
        hooks = {impl_hook.name for impl_hook in pm.get_hookcallers(plugin) or []}
        kinds = [k for k, present in (("device", hooks & device_hooks), ("backend", "sssphase_model_backends" in hooks))
                 if present]  # (an optionalhook this version has no spec for is neither: it is never called)
        version, source = _plugin_version(pm, plugin)
        records.append(PluginRecord(name, "+".join(kinds) or "none", version, source, True))
    records += [PluginRecord(n, "broken", "?", err, False) for n, err in pm.load_errors.items()]
    records += [PluginRecord(n, "off", "", f"left out by {ENV_PLUGINS}=-{n}", False) for n in pm.left_out]
    return sorted(records, key=lambda r: r.name)


def _unmarked_hooks(pm: PluginManager, plugin: Any) -> list[str]:
    """The functions of ``plugin`` named like a hook (``sssphase_cameras``) but not marked ``@hookimpl``: pluggy
    passes over them without a word."""
    hooks = {h for h in dir(pm.hook) if h.startswith("sssphase_") and getattr(pm.hook, h).spec is not None}
    return sorted(h for h in hooks if callable(getattr(plugin, h, None))
                  and pm.parse_hookimpl_opts(plugin, h) is None)


def device_providers(pm: PluginManager | None = None, kind: str | None = None,
                     timeout: float | None = None) -> list[tuple[str, DeviceProvider]]:
    """(plugin name, provider) for every device hook implementation; a raising plugin is recorded, and with a
    ``timeout`` (seconds per hook) so is one whose hook hangs, by name, its devices left out."""
    pm = pm or get_plugin_manager()
    out: list[tuple[str, DeviceProvider]] = []
    for k, hook_name in hookspecs.DEVICE_HOOKS.items():
        if kind is not None and k != kind:
            continue
        for impl in getattr(pm.hook, hook_name).get_hookimpls():
            try:
                call = lambda impl=impl: list(impl.function() or [])  # noqa: E731
                providers = call() if timeout is None else _within(timeout, call)
                bad = [p for p in providers if not all(hasattr(p, a) for a in ("kind", "discover", "open"))]
                if bad:
                    raise TypeError(f"returned {type(bad[0]).__name__!s:.40} instead of device providers "
                                    "(objects with kind, discover and open)")
            except _Hung:
                pm.load_errors[impl.plugin_name] = (f"its hook {hook_name} did not return within {timeout:g} s (it "
                                                    "hangs): its devices are left out; leave it out "
                                                    f"({ENV_PLUGINS}=-{impl.plugin_name}) or uninstall it")
                continue
            except (Exception, SystemExit) as exc:
                pm.load_errors[impl.plugin_name] = f"{hook_name} failed: {_error_text(exc)}"
                continue
            out += [(impl.plugin_name, p) for p in providers]
    return out


def _discover(provider: DeviceProvider) -> list[DeviceInfo]:
    """``provider.discover()``, checked: a list of DeviceInfo (else TypeError)."""
    found = list(provider.discover())
    if not all(isinstance(d, DeviceInfo) for d in found):
        raise TypeError("discover() returned something other than DeviceInfo records")
    for d in found:  # (a numpy serial failed the daemon's reply: `sss devices` waited 40 s, no plugin named)
        wrong = next((f for f in ("id", "kind", "plugin", "model", "serial") if not isinstance(getattr(d, f), str)), None)
        if wrong is not None:
            raise TypeError(f"discover() returned a DeviceInfo whose {wrong} is {type(getattr(d, wrong)).__name__} "
                            f"{str(getattr(d, wrong))[:40]!r}: its fields are text (str)")
    kind = getattr(provider, "kind", None)
    other = next((d for d in found if d.kind != kind), None)
    if other is not None:  # (listed as one kind, it then failed to open "is a projector, not a turntable")
        raise TypeError(f"a {kind} provider's discover() reported {other.id} as a {other.kind}: a provider reports "
                        "devices of its own kind")
    return found


def _say(errors: dict[str, str], plugin: str, text: str) -> None:
    """Add ``text`` to what is said of ``plugin`` (one line per plugin, its problems joined by '; ')."""
    errors[plugin] = f"{errors[plugin]}; {text}" if plugin in errors else text


#: Seconds a plugin's hooks, or one provider's discover(), may take before it is reported as hung and left out
#: (``sss devices`` waited for ever on a plugin stuck in a USB call).
#: None: ``$SSS_DISCOVERY_TIMEOUT_S``, else 30 (read when discovery runs: a bad value is one line naming it).
DISCOVERY_TIMEOUT_S: float | None = None


def discovery_timeout_s() -> float:
    from sssphase_core.settings import env_seconds

    return DISCOVERY_TIMEOUT_S if DISCOVERY_TIMEOUT_S is not None else env_seconds("SSS_DISCOVERY_TIMEOUT_S", 30.0)


class _Hung(Exception):
    pass


def _started(fn: Any) -> tuple[Any, dict[str, Any]]:
    """``fn()`` started in a daemon thread; the box gets its ``value`` or the ``error`` it raised."""
    import threading

    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001  (handed to the caller, sys.exit() too)
            box["error"] = exc

    thread = threading.Thread(target=run, name="sss-discover", daemon=True)
    thread.start()
    return thread, box


def _outcome(thread: Any, box: dict[str, Any]) -> Any:
    if thread.is_alive():
        raise _Hung()
    if "error" in box:
        raise box["error"]
    return box["value"]


def _within(seconds: float, fn: Any) -> Any:
    """``fn()`` run in a daemon thread: its value, or what it raised; :class:`_Hung` when it has not returned
    within ``seconds`` (the thread is left behind: a plugin's call cannot be interrupted)."""
    thread, box = _started(fn)
    thread.join(seconds)
    return _outcome(thread, box)


#: Discoveries that did not return in time, by (plugin, kind): (their thread, when it started). A hung plugin is
#: not called again until its call returns (each `sss devices` through the daemon left one more thread stuck in it).
_PENDING: dict[tuple[str, str], tuple[Any, float]] = {}


def _start_discovery(plugin: str, provider: DeviceProvider, now: float) -> Any:
    """``provider.discover()`` started in a thread: ``(thread, box)``, or, for a provider whose earlier call is still
    hung, the seconds since that call began (it is not called again until it returns)."""
    key = (plugin, str(getattr(provider, "kind", "device")))
    pending = _PENDING.get(key)
    if pending is not None and pending[0].is_alive():
        return now - pending[1]
    _PENDING.pop(key, None)
    return _started(lambda: _discover(provider))


def _finish_discovery(plugin: str, provider: DeviceProvider, run: Any, deadline: float, now: float) -> Any:
    """The outcome of :func:`_start_discovery`'s ``run`` by ``deadline`` (monotonic): the devices, the exception
    raised (:class:`_Hung` past the deadline, remembered in ``_PENDING``), or the seconds a pending call has hung."""
    if isinstance(run, float):
        return run
    thread, box = run
    thread.join(max(0.0, deadline - time.monotonic()))
    try:
        return _outcome(thread, box)
    except BaseException as exc:  # noqa: BLE001  (sorted out by the caller)
        if isinstance(exc, _Hung):
            _PENDING[(plugin, str(getattr(provider, "kind", "device")))] = (thread, now)
        return exc


# Discovery is one call at a time: run all at once, the built-in plugins' hardware libraries started together
# (depthai's import, SDL's display start, pylon's start-up: C libraries with no promise of safety beside one
# another), and a CI test process died with a segmentation fault inside discovery.
def discovery_wait_s(timeout: float) -> float:
    """The longest :func:`discover_devices` takes with a per-provider ``timeout``: each provider has ``timeout``
    from its own start, and the last starts at most ``timeout / 2`` after the first (:func:`_discover_all`)."""
    return 1.5 * timeout


def _discover_all(providers: list[tuple[str, DeviceProvider]], timeout: float) -> list[tuple[str, str, Any]]:
    """Each provider's discover(), one after the other: the next starts when the one before returns, or once that
    one has run ``timeout / (2 n)`` (a slow or hung plugin; waiting out its whole timeout before the next one made
    two hung plugins outlast `sss devices`). Each provider has ``timeout`` from its own start. Per provider
    (plugin, kind, outcome of :func:`_finish_discovery`)."""
    stagger = timeout / (2 * max(1, len(providers)))
    runs = []
    for plugin, provider in providers:
        started = time.monotonic()
        run = _start_discovery(plugin, provider, started)
        if not isinstance(run, float):
            run[0].join(stagger)
        runs.append((plugin, provider, run, started))
    return [(plugin, str(getattr(provider, "kind", "device")),
             _finish_discovery(plugin, provider, run, started + timeout, started))
            for plugin, provider, run, started in runs]


def _outcome_problem(kind: str, outcome: Any, timeout: float) -> str | None:
    """What a discovery outcome says of its plugin (None: it found devices)."""
    if isinstance(outcome, float):
        return (f"discovery of {kind}s has not returned for {outcome:.0f} s (the plugin hangs): its devices are left "
                "out, and it is not asked again until that call returns")
    if isinstance(outcome, _Hung):
        return f"discovery of {kind}s did not return within {timeout:g} s (the plugin hangs): its devices are left out"
    if isinstance(outcome, DeviceNotFound):  # an absent device is an answer, not a failure
        return str(outcome).strip()
    if isinstance(outcome, Exception | SystemExit):
        return f"discovery of {kind}s failed: {_error_text(outcome)}"
    if isinstance(outcome, BaseException):
        raise outcome
    return None


def discover_devices(pm: PluginManager | None = None) -> tuple[list[DeviceInfo], dict[str, str]]:
    """Run discovery on every provider (this may do device I/O), one after the other (:func:`_discover_all`).
    Returns devices and errors by plugin; a plugin whose hooks or discover() do not return within
    :func:`discovery_timeout_s` is reported as hung and left out, and is not called again until that call returns."""
    timeout = discovery_timeout_s()
    pm = pm or get_plugin_manager()
    found: dict[str, tuple[str, DeviceInfo]] = {}  # id -> (plugin, device): one entry per id
    errors: dict[str, str] = {}
    providers = device_providers(pm, timeout=timeout)  # (a hook that hangs is named in pm.load_errors, added below)
    for plugin, kind, devices in _discover_all(providers, timeout):
        problem = _outcome_problem(kind, devices, timeout)
        if problem is not None:
            errors[plugin] = problem
            continue
        for d in devices:
            if d.id not in found:
                found[d.id] = (plugin, d)
                continue
            first = found[d.id][0]
            if first == plugin and found[d.id][1].kind != d.kind:
                _say(errors, plugin, f"reports {d.id} as a {found[d.id][1].kind} and as a {d.kind}: ids must be unique")
                continue
            prefix = d.id.split(":", 1)[0]  # ids are 'plugin:...': the plugin an id names owns it
            if prefix not in (first, plugin):
                _say(errors, plugin, f"reports device {d.id}, which plugin {first} reports too, and neither is "
                                     f"{prefix!r}, the plugin its id names: it opens from neither until one is disabled")
                continue
            owner, loser = (plugin, first) if prefix == plugin else (first, plugin)
            found[d.id] = (owner, d if owner == plugin else found[d.id][1])
            if loser != owner:
                _say(errors, loser, f"reports device {d.id}, which plugin {owner} reports too: it opens from {owner}")
    errors.update(pm.load_errors)
    return sorted((d for _, d in found.values()), key=lambda d: d.id), errors


def check_rig_options(options: Mapping[str, Any], device_ids: Iterable[str], pm: PluginManager | None = None) -> None:
    """Refuse, by name, rig options that no plugin reads (an :class:`InputError`): a table named after no installed
    device plugin (``[options.basle]``), and, in a rig without a simulated device (the sim plugin reads the bare keys,
    and checks them), a bare key outside every plugin's table (``[options] exposure_us = 1000``). Either was ignored
    without a word: the devices ran with their defaults. Each plugin checks the settings of its own table."""
    pm = pm or get_plugin_manager()
    device_ids = [str(d) for d in device_ids]
    registered = {r.name for r in plugin_records(pm) if r.ok and "device" in r.kind.split("+")}
    # a plugin reads the table of its own name, which its devices' ids begin with (one named in $SSS_PLUGINS is
    # registered under its module's name)
    plugins = sorted((registered | {d.partition(":")[0] for d in device_ids}) - {"sim"})
    known = ", ".join(f"[options.{n}]" for n in plugins)
    unknown = sorted(str(k) for k, v in options.items() if isinstance(v, Mapping) and k not in plugins and k != "sim")
    if unknown:
        raise InputError(f"rig options {', '.join(f'[options.{k}]' for k in unknown)[:200]}: no installed device plugin "
                         f"has that name (a misspelt table is ignored); the tables of the installed plugins: {known}")
    if not any(d.partition(":")[0] == "sim" for d in device_ids):
        bare = sorted(str(k) for k, v in options.items() if not isinstance(v, Mapping))
        if bare:
            raise InputError(f"rig options {', '.join(bare)[:200]} are outside every plugin's table: a device's settings "
                             f"go in its plugin's table, e.g. [options.basler] exposure_us = 10000 (tables: {known})")


def find_provider(device_id: str, pm: PluginManager | None = None, kind: str | None = None) -> DeviceProvider:
    """The provider that owns ``device_id`` (of ``kind``: camera, projector, ...; KeyError naming the
    device's real kind otherwise). IDs are ``plugin:...``, so only that plugin's providers are asked
    first (opening a sim rig never runs discovery, or imports, of hardware plugins)."""
    pm = pm or get_plugin_manager()
    providers = device_providers(pm)
    prefix = device_id.split(":", 1)[0]
    # the id's own plugin first, then providers of the kind asked for: a hung provider of another kind is not waited on
    ranked = sorted(providers, key=lambda np_: (np_[0] != prefix, kind is not None and getattr(np_[1], "kind", None) != kind))
    matches: list[tuple[str, DeviceProvider]] = []
    timeout = discovery_timeout_s()
    hung: dict[str, str] = {}  # plugins whose discover() hangs, said if the device is not found elsewhere
    for name, provider in ranked:  # one at a time, each within the timeout (a hung one held the daemon's lock)
        now = time.monotonic()
        found = _finish_discovery(name, provider, _start_discovery(name, provider, now), now + timeout, now)
        if isinstance(found, float | _Hung):
            hung[name] = _outcome_problem(str(getattr(provider, "kind", "device")), found, timeout) or ""
            continue
        if isinstance(found, BaseException):  # a plugin with no device (or a broken one) must not block the others
            if not isinstance(found, Exception | SystemExit):
                raise found
            continue
        ids = [d.id for d in found]
        if device_id in ids:
            if name == prefix:  # the plugin the id names owns it
                matches = [(name, provider)]
                break
            matches.append((name, provider))
    if len({n for n, _ in matches}) > 1:
        raise KeyError(f"device {device_id!r} is reported by plugins {', '.join(sorted({n for n, _ in matches}))} and "
                       f"none of them is {prefix!r}, the plugin its id names: uninstall or disable one (sss plugins)")
    if matches:
        provider = matches[0][1]
        if kind is not None and provider.kind != kind:
            raise KeyError(f"{device_id} is a {provider.kind}, not a {kind}")
        return provider
    if hung:  # (the daemon said "the plugins' hooks did not return": it was a plugin's discover(), which may hold it)
        raise KeyError(f"{device_id} was not found, and plugin{'s' if len(hung) > 1 else ''} "
                       + "; ".join(f"{name}'s {problem}" for name, problem in sorted(hung.items(), key=lambda i: i[0] != prefix)))
    devices, errors = discover_devices(pm)
    known = ", ".join(d.id for d in devices if kind is None or d.kind == kind) or "none"
    # (it said only "no camera"); a plugin left out for its name's clash is keyed "name (where)"
    why = "; ".join(f"{name}: {e}" for name, e in errors.items() if name.split(" (", 1)[0].split(".")[0] == prefix)
    raise KeyError(f"no {kind or 'device'} {device_id!r} (known {kind or 'device'}s: {known})"
                   + (f"; plugin {why}" if why else ""))


def _plugin_model_backends() -> list[tuple[str, Any]]:
    """Every third-party plugin's ``sssphase_model_backends`` result, or the exception it raised, by plugin name,
    earliest plugin first (pluggy calls the latest first). Each is called alone: one plugin's hook that raised made
    every relight an "internal error", built-in backends too."""
    found = []
    for impl in reversed(get_plugin_manager().hook.sssphase_model_backends.get_hookimpls()):
        if impl.function is backends.sssphase_model_backends:  # (the built-ins: core has them already)
            continue
        try:
            found.append((impl.plugin_name, impl.function()))
        except (Exception, SystemExit) as exc:  # noqa: BLE001  (a third party's code: named, never fatal)
            found.append((impl.plugin_name, exc))
    return found


def plugin_provides(pm: PluginManager | None = None) -> dict[str, list[str]]:
    """What each plugin provides, by name: the device kinds of its hooks (``cameras``, ...) and the model backends
    relighting takes from it (a backend whose name another owner has is not its own: :func:`available_backends`
    warns of it, and of a hook that raised)."""
    pm = pm or get_plugin_manager()
    out: dict[str, list[str]] = {}
    for kind, hook_name in hookspecs.DEVICE_HOOKS.items():
        for impl in getattr(pm.hook, hook_name).get_hookimpls():
            out.setdefault(impl.plugin_name, []).append(f"{kind}s")
    builtin = next((i.plugin_name for i in pm.hook.sssphase_model_backends.get_hookimpls()
                    if i.function is backends.sssphase_model_backends), None)
    for plugin, names in backends.backend_plugins().items():  # (warns of the problems)
        if plugin is None and builtin is None:
            continue
        said = ("no backend (see the warning)" if names is None else
                f"backends {', '.join(names)}" if names else "no backend of its own")
        out.setdefault(builtin if plugin is None else plugin, []).append(said)
    return out


backends.use_plugin_backends(_plugin_model_backends)  # core asks for plugin backends through this
