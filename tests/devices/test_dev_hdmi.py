"""HDMI projector: the real pygame window process on SDL's dummy video driver."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pygame")
from sssphase_plugins import hdmi_projector as hp  # noqa: E402
from sssphase_plugins.drivers import DeviceError, DeviceNotFound  # noqa: E402


@pytest.fixture
def projector(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    provider = hp.HdmiProvider()
    (info,) = provider.discover()
    proj = provider.open(info.id, {"hdmi": {"verify": True, "latency_s": 0.0}}, {})
    yield proj
    proj.close()


def test_show_confirms_the_image_is_on_screen(projector):
    w, h = projector.resolution
    rng = np.random.default_rng(0)
    first = projector.show(rng.random((h, w), dtype=np.float32), tag="a")
    second = projector.show(rng.random((h, w, 3), dtype=np.float32), tag="b")  # verify: screen read back, crc compared
    assert (first.frame_id, second.frame_id, second.tag) == (1, 2, "b")
    assert second.on_screen_ns > first.on_screen_ns
    projector.show(np.zeros((h, w)), confirm=False)
    assert projector.show(np.ones((h, w))).frame_id == 4  # the unconfirmed frame's reply is collected too
    with pytest.raises(DeviceError, match=r"of the projector.s 1024x768, got shape \(769, 1024\)"):
        projector.show(np.zeros((h + 1, w)))


def test_window_process_death_is_a_clear_error(projector):
    w, h = projector.resolution
    projector.show(np.zeros((h, w)))
    projector.window.proc.kill()
    projector.window.proc.wait()
    with pytest.raises(DeviceError, match="projector window process exited"):
        projector.show(np.zeros((h, w)))


def test_to_uint8():
    out = hp.to_uint8(np.array([[0.0, 0.5, 1.2]], np.float32))
    assert out.shape == (1, 3, 3) and out[0, :, 0].tolist() == [0, 128, 255]


def test_headless_fallback_is_not_a_display(monkeypatch):
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(DeviceNotFound, match="no device found"):
        hp.HdmiProvider().discover()


def test_unconfirmed_frame_replies_are_drained(projector):
    import select

    w, h = projector.resolution
    for _ in range(3):
        projector.show(np.zeros((h, w)), confirm=False)
    assert select.select([projector.window.proc.stdout], [], [], 10)[0]  # the first reply has arrived
    projector.show(np.ones((h, w)), confirm=False)
    assert 1 not in projector.window.pending and 4 in projector.window.pending
    assert projector.show(np.zeros((h, w))).frame_id == 5 and not projector.window.pending


def test_looking_for_displays_without_one_prints_nothing_of_sdls_own(tmp_path):
    """On a machine without a display, `sss devices` ended with libwayland's "error: XDG_RUNTIME_DIR is invalid or
    not set in the environment." on stderr (SDL's Wayland probe): the probe is skipped where no Wayland display is
    named, and the plugin's own line says why no display was found."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("XDG_RUNTIME_DIR", "WAYLAND_DISPLAY", "DISPLAY",
                                                           "SDL_VIDEODRIVER")}
    code = ("from sssphase_plugins import hdmi_projector as hp\ntry:\n    hp.list_displays()\n"
            "except Exception as exc:\n    print(exc)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert "no device found: SDL" in res.stdout, res.stdout + res.stderr
    assert "XDG_RUNTIME_DIR" not in res.stderr and "error" not in res.stderr, res.stderr
