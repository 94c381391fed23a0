"""Hardware libraries load only when a plugin is used; missing ones give a clear reason, not a traceback."""

from __future__ import annotations

import json
import subprocess
import sys

HARDWARE_LIBS = ["depthai", "hid", "usb", "serial", "pygame", "cv2"]
PLUGIN_MODULES = ["uvc_camera", "oak_camera", "hdmi_projector", "lightcrafter", "serial_devices", "usb_util"]


def run_python(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_sim_only_daemon_imports_no_hardware_library():
    code = f"""
import json, sys
from sssphase_plugins import manager
pm = manager.build_plugin_manager()
for name in {PLUGIN_MODULES}:
    module = __import__("sssphase_plugins." + name, fromlist=["_"])
    if not pm.is_registered(module):  # installed entry points register them already
        pm.register(module, name="dev-" + name)
providers = manager.device_providers(pm)
loaded = [m for m in {HARDWARE_LIBS} if m in sys.modules]
sim = [p for plugin, p in providers if plugin == "sim"]
camera = next(p for p in sim if p.kind == "camera").open("sim:camera0", {{}}, shared := {{}})
camera.grab()  # the sim's ISP uses OpenCV: cv2 is fair game from here on
print(json.dumps({{"kinds": sorted({{p.kind for _, p in providers}}), "loaded": loaded,
                  "after_grab": [m for m in {HARDWARE_LIBS[:-1]} if m in sys.modules]}}))
"""
    result = run_python(code)
    assert result["kinds"] == ["camera", "projector", "trigger", "turntable"]
    assert result["loaded"] == [] and result["after_grab"] == []


def test_missing_libraries_are_reported_per_plugin():
    code = f"""
import json, sys
for lib in {HARDWARE_LIBS[:-1]}:
    sys.modules[lib] = None  # as if not installed
from sssphase_plugins import manager
pm = manager.build_plugin_manager()
names = {{}}
for name in {PLUGIN_MODULES[:-1]}:
    module = __import__("sssphase_plugins." + name, fromlist=["_"])
    if not pm.is_registered(module):  # installed entry points register them already
        pm.register(module, name="dev-" + name)
    names[name] = pm.get_name(module)
devices, errors = manager.discover_devices(pm)
print(json.dumps({{"errors": {{m: errors.get(n, "") for m, n in names.items()}}, "devices": [d.id for d in devices]}}))
"""
    result = run_python(code)
    errors = result["errors"]
    assert "sim:camera0" in result["devices"]
    assert "depthai not installed (pip install sssphase[depthai])" in errors["oak_camera"]
    assert "hidapi not installed (pip install sssphase[hid])" in errors["lightcrafter"]
    assert "pygame not installed (pip install sssphase[hdmi])" in errors["hdmi_projector"]
    assert "pyserial not installed (pip install sssphase[serial])" in errors["serial_devices"]
    assert "no device found" in errors["uvc_camera"] or "uvc:" in " ".join(result["devices"])
    assert all("Traceback" not in e for e in errors.values())


def test_usb_util_reports_missing_backend_or_no_device():
    import pytest

    pytest.importorskip("usb.core")
    from sssphase_plugins.drivers import DeviceError, DeviceNotFound
    from sssphase_plugins.usb_util import find_usb, reset_usb

    try:
        found = find_usb(0x0451, 0x6401)
    except DeviceError as exc:
        assert "libusb-1.0" in str(exc)
    else:
        assert found == []
        with pytest.raises(DeviceNotFound, match="no device found: no USB device 0451:6401"):
            reset_usb(0x0451, 0x6401)
