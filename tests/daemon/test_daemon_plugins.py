"""Plugin manager (broken plugins isolated, both hook families) and the sim devices' hardware-like behaviour."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from sssphase_plugins import manager, sim_plugin
from sssphase_plugins.drivers import Camera, DeviceError, DeviceInfo, Projector, Turntable

GOOD = """
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.drivers import DeviceInfo
__version__ = "2.5"
class P:
    kind = "trigger"
    def discover(self):
        return [DeviceInfo("acme:trig-7", "trigger", "acme_good", "Acme trigger", "7")]
    def open(self, device_id, options, shared):
        raise NotImplementedError
@hookimpl
def sssphase_triggers():
    return [P()]
"""
BROKEN_IMPORT = "import a_module_that_does_not_exist\n"
UNKNOWN_HOOK = """
from sssphase_plugins.hookspecs import hookimpl
@hookimpl
def sssphase_cameraz():
    return []
"""
RAISING_HOOK = """
from sssphase_plugins.hookspecs import hookimpl
@hookimpl
def sssphase_cameras():
    raise RuntimeError("usb stack exploded")
"""

NOT_A_LIST = """
from sssphase_plugins.hookspecs import hookimpl
@hookimpl
def sssphase_cameras():
    return 5
"""
NO_KIND = """
from sssphase_plugins.hookspecs import hookimpl
class P:
    def discover(self):
        raise RuntimeError("no")
@hookimpl
def sssphase_projectors():
    return [P()]
"""
BAD_DISCOVERY = """
from sssphase_plugins.hookspecs import hookimpl
class P:
    kind = "turntable"
    def discover(self):
        return ["not a DeviceInfo", 5]
    def open(self, device_id, options, shared):
        raise NotImplementedError
@hookimpl
def sssphase_turntables():
    return [P()]
"""
EXITS = "import sys\nsys.exit(3)\n"
UNVERSIONED = """
from sssphase_plugins.hookspecs import hookimpl
@hookimpl
def sssphase_triggers():
    return []
"""
PLUGINS = {"acme_good": GOOD, "acme_broken": BROKEN_IMPORT, "acme_typo": UNKNOWN_HOOK, "acme_raises": RAISING_HOOK,
           "acme_int": NOT_A_LIST, "acme_nokind": NO_KIND, "acme_baddisc": BAD_DISCOVERY, "acme_exits": EXITS,
           "acme_plain": UNVERSIONED}


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    for name, src in PLUGINS.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(src))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, ",".join(PLUGINS))
    return tmp_path


def test_broken_plugins_are_named_and_do_not_take_others_down(plugin_dir):
    pm = manager.build_plugin_manager()
    devices, errors = manager.discover_devices(pm)
    ids = {d.id for d in devices}
    assert {"acme:trig-7", sim_plugin.CAMERA_ID, sim_plugin.PROJECTOR_ID, sim_plugin.TURNTABLE_ID} <= ids
    assert "ModuleNotFoundError" in errors["acme_broken"]
    assert "sssphase_cameraz" in errors["acme_typo"]
    assert "usb stack exploded" in errors["acme_raises"]
    # hooks that return the wrong things, or exit the interpreter, are named too (they took `sss devices`,
    # `sss plugins` and every capture down with a TypeError/AttributeError, or ended the process)
    assert "sssphase_cameras failed" in errors["acme_int"] and "instead of device providers" in errors["acme_nokind"]
    assert "DeviceInfo" in errors["acme_baddisc"] and "SystemExit" in errors["acme_exits"]
    records = {r.name: r for r in manager.plugin_records(pm)}
    assert records["acme_good"].ok and records["acme_good"].version == "2.5" and records["acme_good"].kind == "device"
    assert not records["acme_broken"].ok and records["sim"].ok
    assert records["acme_plain"].ok and records["acme_plain"].version == "?"  # not sssphase's own version
    assert records["sim"].version != "?"  # the built-in plugin carries the package's
    assert not records["acme_raises"].ok and [r.name for r in manager.plugin_records(pm)].count("acme_raises") == 1
    assert manager.find_provider(sim_plugin.CAMERA_ID, pm).kind == "camera"  # the others keep working
    with pytest.raises(KeyError, match="is a projector, not a camera"):
        manager.find_provider(sim_plugin.PROJECTOR_ID, pm, kind="camera")


def test_one_module_registered_under_two_names_is_one_line_naming_the_first(monkeypatch):
    """pluggy's words ended with the repr of every registered plugin, over many lines of module paths."""
    monkeypatch.setenv(manager.ENV_PLUGINS, "sssphase_plugins.sim_plugin")  # the built-in `sim`, named again
    records = {r.name: r for r in manager.plugin_records(manager.build_plugin_manager())}
    twice = records["sssphase_plugins.sim_plugin"]
    assert not twice.ok and records["sim"].ok
    assert twice.source == ("its module is already loaded as plugin 'sim': two entry points (or SSS_PLUGINS entries) "
                            "name one module; remove one")




def test_a_misspelt_hook_names_the_hooks_and_the_nearest_one(tmp_path, monkeypatch):
    """pluggy said "unknown hook 'sssphase_camera' in plugin <module ...>": not which hooks there are, nor how a
    plugin written for a newer sssphase keeps a hook this one lacks from failing it."""
    (tmp_path / "acme_misspelt.py").write_text("from sssphase_plugins.api import hookimpl\n@hookimpl\n"
                                           "def sssphase_camera():\n    return []\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_misspelt")
    records = {r.name: r for r in manager.plugin_records(manager.build_plugin_manager())}
    assert not records["acme_misspelt"].ok and records["sim"].ok
    assert records["acme_misspelt"].source == (
        "unknown hook 'sssphase_camera' (did you mean sssphase_cameras?): the hooks are sssphase_cameras, "
        "sssphase_model_backends, sssphase_projectors, sssphase_triggers, sssphase_turntables; one from a newer "
        "sssphase is marked hookimpl(optionalhook=True)")
    (tmp_path / "acme_later.py").write_text("from sssphase_plugins.api import hookimpl\n@hookimpl(optionalhook=True)\n"
                                            "def sssphase_lenses():\n    return []\n")
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_later")
    records = {r.name: r for r in manager.plugin_records(manager.build_plugin_manager())}
    assert records["acme_later"].ok and records["acme_later"].kind == "none"  # it was listed as a "backend"

SHADOW = """
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.drivers import DeviceInfo
class P:
    kind = "camera"
    def discover(self):
        return [DeviceInfo("basler:extra0", "camera", "basler", "third-party thing", "extra0")]
    def open(self, device_id, options, shared):
        raise RuntimeError("not a camera")
@hookimpl
def sssphase_cameras():
    return [P()]
"""


def test_a_third_party_plugin_named_like_a_built_in_one_is_listed_broken_and_the_built_in_stays(tmp_path, monkeypatch):
    """An installed distribution's entry point named ``basler`` earlier on the path replaced the built-in Basler
    plugin without a word (pluggy loads the first entry point of a name), and one later on it was dropped without
    one. A module of $SSS_PLUGINS named like a built-in (``sim``) was dropped silently too."""
    (tmp_path / "acme_shadow.py").write_text(SHADOW)
    (tmp_path / "sim.py").write_text(SHADOW)
    info = tmp_path / "acme_shadow-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-shadow\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[sssphase_devices]\nbasler = acme_shadow\n")
    monkeypatch.syspath_prepend(str(tmp_path))  # before the built-in's distribution on the path
    monkeypatch.setenv(manager.ENV_PLUGINS, "sim")
    pm = manager.build_plugin_manager()
    records = {r.name: r for r in manager.plugin_records(pm)}
    assert records["basler"].ok and records["basler"].source == "sssphase"
    assert pm.get_plugin("basler").__name__ == "sssphase_plugins.basler_camera"
    said = "another plugin is registered under this name ({}): rename one of the two entry points"
    assert not records["basler (acme-shadow)"].ok
    assert records["basler (acme-shadow)"].source == said.format("sssphase_plugins.basler_camera")
    assert records["sim"].ok and pm.get_plugin("sim").__name__ == "sssphase_plugins.sim_plugin"
    assert records["sim (SSS_PLUGINS)"].source == ("another plugin is registered under this name "
                                                   "(sssphase_plugins.sim_plugin): name another module in SSS_PLUGINS "
                                                   "(a module there is registered under its own name)")
    _, errors = manager.discover_devices(pm)
    assert "basler (acme-shadow)" in errors  # `sss devices` names it too
    assert "basler:extra0" not in {d.id for d in manager.discover_devices(pm)[0]}
    with pytest.raises(KeyError, match=r"no camera 'basler:extra0' .*; basler \(acme-shadow\): another plugin is "
                                       "registered under this name"):  # (it said "no camera" alone)
        manager.find_provider("basler:extra0", pm, kind="camera")



def test_rig_options_no_plugin_reads_are_refused_naming_the_known_tables():
    """[options.basle] (misspelt) and, in a rig of real devices, [options] exposure_us = 1000 (outside every table)
    were ignored: the capture ran with the devices' defaults and exited 0."""
    from sssphase_core.errors import InputError

    pm = manager.build_plugin_manager()
    with pytest.raises(InputError, match=r"rig options \[options.basle\]: no installed device plugin has that name .*"
                                         r"the tables of the installed plugins: \[options.basler\], .*\[options.hdmi\]"):
        manager.check_rig_options({"basle": {"exposure_us": 1000}}, ["basler:1", "hdmi:display0"], pm)
    with pytest.raises(InputError, match=r"rig options exposure_us are outside every plugin's table"):
        manager.check_rig_options({"exposure_us": 1000}, ["basler:1", "hdmi:display0"], pm)
    manager.check_rig_options({"basler": {"gain": 0}, "hdmi": {}}, ["basler:1", "hdmi:display0"], pm)
    manager.check_rig_options({"object": "star", "basler": {"gain": 0}}, ["sim:camera0", "hdmi:display0"], pm)  # sim's


CLONES = {  # two plugins that report the sim's camera, and one id that two plugins other than its own report
    "acme_clone": """
from sssphase_plugins.hookspecs import hookimpl
from sssphase_plugins.drivers import DeviceInfo
class P:
    kind = "camera"
    def discover(self):
        return [DeviceInfo("sim:camera0", "camera", "acme_clone", "Not the sim", "1"),
                DeviceInfo("other:cam", "camera", "acme_clone", "Shared", "1")]
    def open(self, device_id, options, shared):
        raise NotImplementedError
@hookimpl
def sssphase_cameras():
    return [P()]
""",
}
CLONES["acme_clone2"] = CLONES["acme_clone"].replace("acme_clone", "acme_clone2")


def test_a_device_id_reported_twice_is_said_and_opens_from_the_plugin_it_names(tmp_path, monkeypatch):
    for name, src in CLONES.items():
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(src))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, ",".join(CLONES))
    pm = manager.build_plugin_manager()
    devices, errors = manager.discover_devices(pm)
    ids = [d.id for d in devices]
    assert len(ids) == len(set(ids)) and sim_plugin.CAMERA_ID in ids and "other:cam" in ids  # each id listed once
    assert [d.plugin for d in devices if d.id == sim_plugin.CAMERA_ID] == ["sim"]
    assert all(f"reports device {sim_plugin.CAMERA_ID}, which plugin sim reports too" in errors[n] for n in CLONES)
    assert "other:cam" in errors["acme_clone2"] and "neither is 'other'" in errors["acme_clone2"]
    assert type(manager.find_provider(sim_plugin.CAMERA_ID, pm)).__module__.startswith("sssphase_plugins.sim")
    with pytest.raises(KeyError, match="reported by plugins acme_clone, acme_clone2 and none of them is 'other'"):
        manager.find_provider("other:cam", pm)


def test_backend_hookspecs_and_entry_point_groups_share_the_manager():
    assert manager.ENTRY_POINT_GROUPS == ("sssphase_devices", "sssphase_backends")
    pm = manager.get_plugin_manager(refresh=True)
    assert pm.project_name == "sssphase" and pm.has_plugin("sim")
    assert all(hasattr(pm.hook, h) for h in ("sssphase_cameras", "sssphase_projectors", "sssphase_turntables"))


def test_discovery_ids_are_stable():
    first, _ = manager.discover_devices(manager.build_plugin_manager())
    second, _ = manager.discover_devices(manager.build_plugin_manager())
    assert [d.id for d in first] == [d.id for d in second]
    assert len({d.id for d in first}) == len(first)


@pytest.fixture(scope="module")
def sim_rig():
    shared: dict = {}
    opts = {"object": "pear", "n_views": 4, "seed": 3}
    pm = manager.build_plugin_manager()
    cam, proj, table = (manager.find_provider(dev_id, pm).open(dev_id, opts, shared)
                        for dev_id in (sim_plugin.CAMERA_ID, sim_plugin.PROJECTOR_ID, sim_plugin.TURNTABLE_ID))
    return cam, proj, table


def test_sim_devices_follow_the_driver_protocols(sim_rig):
    cam, proj, table = sim_rig
    assert isinstance(cam, Camera) and isinstance(proj, Projector) and isinstance(table, Turntable)
    assert proj.resolution == (256, 192)
    with pytest.raises(DeviceError, match="of the projector.s 256x192"):
        proj.show(np.zeros((10, 10), np.float32))
    with pytest.raises(DeviceError):
        cam.configure(exposure=0)


def test_camera_sees_only_a_pattern_that_is_already_on_screen(sim_rig):
    cam, proj, table = sim_rig
    w, h = proj.resolution
    black, white = np.zeros((h, w), np.float32), np.ones((h, w), np.float32)
    proj.preload([("black", lambda: black), ("white", lambda: white)])  # one render pass for both
    cam.configure(exposure=1.0)
    proj.show(black, tag="black")
    dark = cam.grab()
    proj.show(white, tag="white", confirm=False)  # not yet on screen: the exposure still sees black
    early = cam.grab()
    assert early.meta["pattern_tag"] == "black"
    proj.show(white, tag="white")
    lit = cam.grab()
    assert lit.meta["pattern_tag"] == "white" and lit.sequence == early.sequence + 1
    assert lit.timestamp_ns > early.timestamp_ns > dark.timestamp_ns
    assert lit.data.mean() > 5 * max(early.data.mean(), 1e-3)


def test_sim_frames_are_reproducible_per_pattern_and_exposure(sim_rig):
    cam, proj, table = sim_rig
    w, h = proj.resolution
    img = np.full((h, w), 0.5, np.float32)
    proj.preload([("half", lambda: img)])
    proj.show(img, tag="half")
    a = cam.grab().data
    proj.show(img, tag="half")
    b = cam.grab().data
    cam.configure(exposure=2.0)
    proj.show(img, tag="half")
    c = cam.grab().data
    cam.configure(exposure=1.0)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert table.move_to(90.0) == 90.0
    proj.show(img, tag="half")
    assert not np.array_equal(cam.grab().data, a)  # another view
    table.move_to(0.0)


def test_fault_injection_option_fails_the_camera():
    shared: dict = {}
    provider = manager.find_provider(sim_plugin.CAMERA_ID, manager.build_plugin_manager())
    cam = provider.open(sim_plugin.CAMERA_ID, {"fail_at_frame": 0}, shared)
    with pytest.raises(DeviceError, match="simulated sensor failure"):
        cam.grab()


def test_the_transport_model_is_a_sim_option():
    state = sim_plugin.SimRigState({"object": "soap", "transport": "directional_dipole"})
    assert state.rig.transport == "directional_dipole" and state.scene.transport.name == "directional_dipole"
    assert sim_plugin.SimRigState({"object": "soap"}).scene.transport.name == "burley"
    radiative = sim_plugin.SimRigState({"object": "soap", "transport": "radiative", "anisotropy": 0.6}).scene.transport
    assert radiative.name == "radiative" and radiative.profiles.g == 0.6
    from sssphase_core.errors import InputError

    with pytest.raises(InputError, match="unknown transport model"):
        sim_plugin.SimRigState({"object": "soap", "transport": "dipole!"})


HANGS = """
import threading
from sssphase_plugins.hookspecs import hookimpl
RELEASE = threading.Event()
class P:
    kind = "camera"
    def discover(self):
        RELEASE.wait()  # a USB call that never returns
        return []
    def open(self, device_id, options, shared):
        raise NotImplementedError
@hookimpl
def sssphase_cameras():
    if HOOK_HANGS:
        RELEASE.wait()
    return [P()]
HOOK_HANGS = False
"""


def test_sss_devices_exits_cleanly_past_a_plugin_still_hanging_in_discovery(tmp_path):
    """The table was printed, then the interpreter's teardown crashed under the hung thread (SIGSEGV/abort)."""
    import os
    import subprocess
    import sys

    (tmp_path / "acme_hangs.py").write_text(textwrap.dedent(HANGS))
    env = {**os.environ, manager.ENV_PLUGINS: "acme_hangs", "PYTHONPATH": str(tmp_path),
           "SSS_DISCOVERY_TIMEOUT_S": "0.05", "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    res = subprocess.run([sys.executable, "-m", "sssphase_cli.main", "devices"], capture_output=True, text=True,
                         timeout=120, env=env)
    assert res.returncode == 0, res.stderr[-500:]
    assert "did not return within 0.05 s" in res.stdout + res.stderr


@pytest.mark.parametrize("value", ["abc", "nan", "0", "-1", "inf", "1e999"])
def test_a_bad_timeout_in_the_environment_is_one_line_naming_it(tmp_path, value):
    """SSS_DISCOVERY_TIMEOUT_S=abc was an internal ValueError raised while importing the plugin manager (every
    command); 0 or nan timed every plugin out; SSS_OPEN_TIMEOUT_S=abc ended the daemon with a traceback."""
    import os
    import subprocess
    import sys

    from sss_process import run_sss

    env = {**os.environ, "SSS_DISCOVERY_TIMEOUT_S": value, "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    res = run_sss(["devices"], env=env, timeout=120)
    assert res.returncode == 2 and (res.stdout + res.stderr).strip().splitlines() == [
        f"error: SSS_DISCOVERY_TIMEOUT_S={value!r}: give a number of seconds above 0 and at most 86400 (or unset it "
        "for the default, 30)"], res.stdout + res.stderr
    env = {**os.environ, "SSS_OPEN_TIMEOUT_S": value, "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    res = subprocess.run([sys.executable, "-m", "sssphase_daemon", "--endpoint", f"ipc://{tmp_path}/c.sock",
                          "--state-file", str(tmp_path / "d.json")], capture_output=True, text=True, timeout=60, env=env)
    assert res.returncode == 2 and f"SSS_OPEN_TIMEOUT_S={value!r}" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_a_plugin_that_hangs_in_discovery_is_named_and_left_out(tmp_path, monkeypatch):
    """`sss devices` without a daemon waited for ever on a plugin stuck in discover() or in its hook."""
    import sys

    (tmp_path / "acme_hangs.py").write_text(textwrap.dedent(HANGS))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_hangs")
    monkeypatch.setattr(manager, "DISCOVERY_TIMEOUT_S", 0.5)
    pm = manager.build_plugin_manager()
    try:
        devices, errors = manager.discover_devices(pm)
        assert sim_plugin.CAMERA_ID in {d.id for d in devices}  # the others are listed
        assert "discovery of cameras did not return within 0.5 s (the plugin hangs)" in errors["acme_hangs"]
        sys.modules["acme_hangs"].HOOK_HANGS = True
        devices, errors = manager.discover_devices(pm)  # the hook itself hangs: that plugin named, the others listed
        assert sim_plugin.CAMERA_ID in {d.id for d in devices}
        assert "its hook sssphase_cameras did not return within 0.5 s (it hangs)" in errors["acme_hangs"], errors
    finally:
        sys.modules["acme_hangs"].RELEASE.set()


def test_plugins_hung_in_discovery_share_one_timeout_and_are_not_asked_again_while_hung(tmp_path, monkeypatch):
    """One after the other, two hung plugins took twice the timeout (the daemon's 60 s outlasted `sss devices`'
    wait, and the daemon looked dead), and every later discovery left one more thread stuck in each."""
    import sys
    import time

    for name in ("acme_stuck", "acme_stuck_too"):
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(HANGS) + "CALLS = []\nP.discover = (lambda f: lambda self: "
                                             "(CALLS.append(1), f(self))[1])(P.discover)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_stuck,acme_stuck_too")
    monkeypatch.setattr(manager, "DISCOVERY_TIMEOUT_S", 0.6)
    pm = manager.build_plugin_manager()
    try:
        t0 = time.monotonic()
        devices, errors = manager.discover_devices(pm)
        assert time.monotonic() - t0 < 1.1  # one timeout for both, not 1.2 s
        assert all("did not return within 0.6 s" in errors[n] for n in ("acme_stuck", "acme_stuck_too")), errors
        assert sim_plugin.CAMERA_ID in {d.id for d in devices}
        devices, errors = manager.discover_devices(pm)  # still hung: said at once, not called again
        assert "discovery of cameras has not returned for" in errors["acme_stuck"], errors
        assert [len(sys.modules[n].CALLS) for n in ("acme_stuck", "acme_stuck_too")] == [1, 1]
        for n in ("acme_stuck", "acme_stuck_too"):
            sys.modules[n].RELEASE.set()
        time.sleep(0.2)
        devices, errors = manager.discover_devices(pm)  # returned since: asked again, and answers
        assert "acme_stuck" not in errors and [len(sys.modules[n].CALLS) for n in ("acme_stuck", "acme_stuck_too")] == [2, 2]
    finally:
        for n in ("acme_stuck", "acme_stuck_too"):
            if n in sys.modules:
                sys.modules[n].RELEASE.set()


TIMED = """
import threading, time
from sssphase_plugins.hookspecs import hookimpl
CALLS = []
class P:
    def __init__(self, kind):
        self.kind = kind
    def discover(self):
        CALLS.append((time.monotonic(), "in", self.kind, threading.get_ident()))
        time.sleep(0.1)  # a bus that takes a moment to enumerate
        CALLS.append((time.monotonic(), "out", self.kind, threading.get_ident()))
        return []
    def open(self, device_id, options, shared):
        raise NotImplementedError
@hookimpl
def sssphase_cameras():
    return [P("camera")]
@hookimpl
def sssphase_projectors():
    return [P("projector")]
"""


def test_discovery_calls_one_plugin_at_a_time(tmp_path, monkeypatch):
    """All discoveries started at once: the built-in plugins' hardware libraries started together in one process,
    and a CI test worker died with a segmentation fault inside discovery. Each call now begins after the one
    before it has returned (a plugin that hangs holds the next back only for its share of the timeout)."""
    import sys

    for name in ("acme_timed", "acme_timed_too"):
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(TIMED))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_timed,acme_timed_too")
    monkeypatch.setattr(manager, "DISCOVERY_TIMEOUT_S", 60.0)
    pm = manager.build_plugin_manager()
    devices, errors = manager.discover_devices(pm)
    assert "acme_timed" not in errors and sim_plugin.CAMERA_ID in {d.id for d in devices}, errors
    calls = sorted(c for n in ("acme_timed", "acme_timed_too") for c in sys.modules[n].CALLS)
    assert len(calls) == 8 and [c[1] for c in calls] == ["in", "out"] * 4, calls  # never two inside at once


def test_a_plugin_named_with_a_minus_in_sss_plugins_is_left_out_unimported(tmp_path):
    """A hung plugin's message said "disable it (SSS_PLUGINS, ...)", but SSS_PLUGINS could only add plugins: an
    installed one could not be turned off short of uninstalling it. ``-name`` leaves it out, not even imported;
    a name no plugin has is said, with the installed ones."""
    import json
    import os
    import subprocess
    import sys

    code = ("import json, sys\nfrom sssphase_plugins import manager\npm = manager.build_plugin_manager()\n"
            "devices, errors = manager.discover_devices(pm)\n"
            "print(json.dumps({'records': [[r.name, r.kind, r.source] for r in manager.plugin_records(pm)], "
            "'devices': [d.id for d in devices], 'depthai': 'depthai' in sys.modules, "
            "'plugin': 'sssphase_plugins.oak_camera' in sys.modules}))")
    env = {**os.environ, manager.ENV_PLUGINS: "-oak, -nosuch", "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    records = {name: (kind, source) for name, kind, source in out["records"]}
    assert records["oak"] == ("off", "left out by SSS_PLUGINS=-oak"), records
    assert not out["depthai"] and not out["plugin"]  # neither the plugin nor its library imported
    assert records["-nosuch (SSS_PLUGINS)"][0] == "broken" and "no plugin is named 'nosuch'" in records["-nosuch (SSS_PLUGINS)"][1]
    assert records["sim"][0] == "device" and sim_plugin.CAMERA_ID in out["devices"]  # the others as before


def test_a_plugin_whose_hooks_are_not_marked_is_named_with_the_missing_marker(tmp_path, monkeypatch):
    """A plugin author who forgot @hookimpl saw the plugin listed as kind "none" and its devices never appear, with
    nothing said: pluggy passes over unmarked functions."""
    (tmp_path / "acme_unmarked.py").write_text("def sssphase_cameras():\n    return []\n"
                                               "def sssphase_turntables():\n    return []\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(manager.ENV_PLUGINS, "acme_unmarked")
    pm = manager.build_plugin_manager()
    records = {r.name: r for r in manager.plugin_records(pm)}
    assert records["acme_unmarked"].kind == "broken" and records["acme_unmarked"].source == (
        "provides nothing: its sssphase_cameras, sssphase_turntables are not marked @hookimpl (from "
        "sssphase_plugins.api import hookimpl)")
    assert records["sim"].ok and records["example"].ok  # (marked ones as before)
    _, errors = manager.discover_devices(pm)
    assert "not marked @hookimpl" in errors["acme_unmarked"]


def test_sss_devices_shows_each_id_whole_in_a_narrow_terminal(tmp_path):
    """HARDWARE.md has users copy device IDs from `sss devices` into their rig file; at 80 columns the table cut them
    (`example:testpatte…`)."""
    import os

    from sss_process import run_sss

    env = {**os.environ, "SSS_RUNTIME_DIR": str(tmp_path / "rt"), "COLUMNS": "60"}
    res = run_sss(["devices"], env=env, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    for device_id in ("example:testpattern0", "sim:bench-camera", "sim:turntable0"):
        assert device_id in res.stdout, res.stdout


def test_a_plugin_whose_import_blocks_is_named_and_the_others_load(tmp_path):
    """A third-party plugin that blocks at import (a network mount, a device probed at import) hung `sss plugins` and
    `sss devices` for ever, even with SSS_DISCOVERY_TIMEOUT_S set; `sss daemon start` gave up naming no plugin."""
    import os
    import subprocess
    import sys

    (tmp_path / "acme_blocks.py").write_text("import time\ntime.sleep(3600)\n")
    env = {**os.environ, manager.ENV_PLUGINS: "acme_blocks", "PYTHONPATH": str(tmp_path),
           "SSS_DISCOVERY_TIMEOUT_S": "0.5", "SSS_RUNTIME_DIR": str(tmp_path / "rt"), "COLUMNS": "200"}
    for command in ("plugins", "devices"):
        res = subprocess.run([sys.executable, "-m", "sssphase_cli.main", command], capture_output=True, text=True,
                             timeout=60, env=env)
        said = res.stdout + res.stderr
        assert res.returncode == 0 and "Traceback" not in said, said
        assert "importing it did not finish within 0.5 s (it hangs at import)" in said and "sim" in said, said


def test_the_example_plugin_checks_its_options_as_a_plugin_should():
    """The project's own example ignored a misspelt `widht` and failed on `height = "tall"` with Python's
    "invalid literal for int()"."""
    pytest.importorskip("sssphase_example_plugin")
    from sssphase_example_plugin import PatternProvider

    from sssphase_plugins.drivers import DeviceError

    with pytest.raises(DeviceError, match=r"unknown \[options.example\] setting\(s\) widht \(known: height, width\)"):
        PatternProvider().open("example:testpattern0", {"example": {"widht": 160}}, {})
    with pytest.raises(DeviceError, match=r"\[options.example\] height must be a whole number >= 1, got 'tall'"):
        PatternProvider().open("example:testpattern0", {"example": {"height": "tall"}}, {})
    assert PatternProvider().open("example:testpattern0", {"example": {"width": 64}}, {}).grab().data.shape == (240, 64, 3)


def test_a_hook_with_an_argument_its_spec_lacks_says_which_in_one_line(tmp_path, monkeypatch):
    """`sss devices` said only "PluginValidationError: Plugin 'x' for hook 'sssphase_projectors'": the cause (an
    argument the hook spec does not have) was on pluggy's later lines."""
    from sssphase_plugins import manager

    (tmp_path / "misspelt_hook.py").write_text("from sssphase_plugins.api import hookimpl\n@hookimpl\n"
                                               "def sssphase_projectors(device_kind):\n    return []\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("SSS_PLUGINS", "misspelt_hook")
    try:
        error = manager.get_plugin_manager(refresh=True).load_errors["misspelt_hook"]
    finally:
        monkeypatch.delenv("SSS_PLUGINS")
        manager.get_plugin_manager(refresh=True)
    assert "\n" not in error and "Argument(s) {'device_kind'} are declared in the hookimpl but can not be found in " \
        "the hookspec" in error, error


def test_a_provider_reporting_a_device_of_another_kind_is_named_not_listed(monkeypatch):
    """A turntable provider whose discover() reported a projector listed it as a turntable; opening it then said
    "is a projector, not a turntable"."""
    from sssphase_plugins import manager
    from sssphase_plugins.drivers import DeviceInfo

    class Mixed:
        kind = "turntable"

        def discover(self):
            return [DeviceInfo("mixed:x", "projector", "mixed", "a projector", "x")]

    with pytest.raises(TypeError, match=r"a turntable provider's discover\(\) reported mixed:x as a projector"):
        manager._discover(Mixed())


def test_a_device_description_that_is_not_text_is_the_plugins_error_not_the_daemons():
    """A numpy serial passed discovery and failed the daemon's reply: `sss devices` waited 40 s, no plugin named."""
    import numpy as np

    class P:
        kind = "camera"

        def discover(self):
            return [DeviceInfo("acme:1", "camera", "acme", "m", np.int64(42))]

    with pytest.raises(TypeError, match=r"a DeviceInfo whose serial is int64 '42': its fields are text"):
        manager._discover(P())
