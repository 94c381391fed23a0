"""`sss sim`'s library call (reporting.sim_views.run_sim), called directly."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.reporting.sim_views import run_sim, spread_pixels, tonemap


def test_run_sim_writes_a_view_and_reports_its_progress_and_decoding(tmp_path):
    events, lines = [], []
    run = run_sim("apple", 1, tmp_path, progress=lambda v, d, t: events.append((v, d, t)), report=lines.append)
    assert run.name == "apple" and json.loads((tmp_path / "scene.json").read_text()) == json.loads(json.dumps(run.info))
    assert events[0] == (None, 0, 1) and events[-1] == (None, 1, 1)
    pixel_events = [e for e in events if e[0] == 0]
    assert pixel_events and pixel_events[-1][1] == pixel_events[-1][2]  # the view's lit pixels all rendered
    decoded = run.info["views"][0]["decode"]
    assert decoded["valid_fraction"] > 0.5 and decoded["median_error_px"] < 0.5
    assert len(lines) == 1 and lines[0].startswith("view 0: decoded ")
    for png in ("white", "mask", "decoded_x", "decode_error", "footprints"):
        assert (tmp_path / "view0" / f"{png}.png").is_file()


def test_run_sim_refuses_options_before_writing(tmp_path):
    with pytest.raises(InputError, match="--seed must be 0 to"):
        run_sim("apple", 1, tmp_path / "o", seed=-1)
    with pytest.raises(InputError, match="turntable takes at most"):
        run_sim("apple", 10**9, tmp_path / "o")
    assert not (tmp_path / "o").exists()


def test_tonemap_and_spread_pixels():
    img = np.array([[[0.0, 0.5, np.nan]]], np.float32)
    out = tonemap(img, 0.5)
    assert out[0, 0, 0] == 0 and out[0, 0, 2] == 0 and out[0, 0, 1] == pytest.approx(1.055 * 0.9 ** (1 / 2.4) - 0.055)
    lit = np.zeros((4, 5), bool)
    lit[1, 1:4] = True
    assert spread_pixels(lit, 1).tolist() == [[1, 2]]
    with pytest.raises(InputError, match="no surface pixel is lit"):
        spread_pixels(np.zeros((3, 3), bool), 2)
