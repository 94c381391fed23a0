"""The library calls behind `sss patterns` and `sss decode`, called directly (no CLI)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from sssphase_core.capture.importer import FrameLoader
from sssphase_core.capture.pattern_files import pattern_config, write_patterns
from sssphase_core.capture.psp_folder import read_psp_folder
from sssphase_core.errors import DataError, InputError
from sssphase_core.reporting.decoded import decode_folder


def _captures(pat_dir, cap_dir, scale=1.0):
    """Every pattern of a written folder as the light a camera at the projector would record (float .npy)."""
    plan = json.loads((pat_dir / "plan.json").read_text())
    cap_dir.mkdir()
    for frame in plan["frames"]:
        value = np.asarray(Image.open(pat_dir / f"{frame['key']}.png")).astype(np.float32) / 255
        light = scale * (0.05 + 0.8 * value ** plan["gamma"])
        np.save(cap_dir / (frame["key"].replace("/", "__") + ".npy"), light.astype(np.float32))
    return plan


def test_write_patterns_reports_progress_and_counts_what_it_wrote(tmp_path):
    seen = []
    written = write_patterns(tmp_path / "p", "64x48", hdr="1,4", progress=lambda d, t: seen.append((d, t)))
    plan = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert written.planned == len(plan["frames"]) and written.patterns == len({f["key"] for f in plan["frames"]})
    assert written.planned == 2 * written.patterns  # each key once per exposure
    assert seen[-1] == (written.patterns, written.patterns) and len(seen) == written.patterns
    assert len(list((tmp_path / "p").rglob("*.png"))) == written.patterns
    with pytest.raises(InputError, match=r"already holds \S+: write the patterns into a new folder \(nothing was written\)"):
        write_patterns(tmp_path / "p", "64x48")


def test_pattern_config_checks_the_fringes_against_the_projector(tmp_path):
    config = pattern_config(64, 48, period=8)
    assert config.period == 8 and config.unwrap_periods and config.unwrap_periods[0] >= 64
    with pytest.raises(InputError, match="--period 100 is longer than the 64x48 projector"):
        pattern_config(64, 48, period=100)
    with pytest.raises(InputError, match="--hdr must be comma-separated numbers"):
        write_patterns(tmp_path / "p", "64x48", hdr="1,a")
    assert not (tmp_path / "p").exists()


def test_read_psp_folder_and_decode_folder_scale_float_frames_to_camera_units(tmp_path):
    pat, cap, out = tmp_path / "p", tmp_path / "c", tmp_path / "o"
    write_patterns(pat, "80x60")
    _captures(pat, cap, scale=1e-3)
    view = read_psp_folder(cap, "80x60")
    assert view.size == (80, 60) and view.saturation is None
    assert view.scale == pytest.approx(1 / view.level) and 0.5 < max(f.max() for f in view.frames.values()) < 1.5
    lines, seen = [], []
    result = decode_folder(cap, out, projector="80x60", progress=lambda d, t: seen.append(d), report=lines.append)
    assert len(lines) == 1 and lines[0].startswith("float frames at level 0.000")
    assert seen == list(range(1, len(view.frames) + 1))
    assert result.coverage["VALID"] == result.pixels == 80 * 60
    xp = np.load(out / "xp.npy")
    assert np.abs(xp - np.mgrid[:60, :80][1]).max() < 0.15
    assert json.loads((out / "decode.json").read_text())["coverage"] == result.coverage


def test_frame_loader_refuses_a_second_camera_and_repairs_only_when_asked(tmp_path):
    a = np.full((20, 24, 3), 0.5, np.float32)
    b = a.copy()
    b[3, 4, 1] = np.nan
    np.save(tmp_path / "a.npy", a)
    np.save(tmp_path / "b.npy", b)
    np.save(tmp_path / "small.npy", a[:10, :12])
    loader = FrameLoader(scale=2.0)
    assert loader.read(tmp_path / "a.npy").max() == 1.0
    repaired = loader.read(tmp_path / "b.npy")
    assert np.isfinite(repaired).all() and loader.repaired == 1
    with pytest.raises(InputError, match=r"small.npy is 12x10, the other frames 24x20"):
        loader.read(tmp_path / "small.npy")
    with pytest.raises(InputError, match="NaN or infinite"):
        FrameLoader(repair=False).read(tmp_path / "b.npy")


def test_read_psp_folder_names_the_frame_of_another_camera(tmp_path):
    pat, cap = tmp_path / "p", tmp_path / "c"
    write_patterns(pat, "64x48")
    _captures(pat, cap)
    odd = cap / "psp__y__p11__s2.npy"
    if not odd.exists():
        odd = sorted(cap.glob("psp__y__*__s2.npy"))[0]
    np.save(odd, np.zeros((10, 12), np.float32))
    with pytest.raises(DataError, match=rf"{odd.name} is 12x10, but .* is 64x48: every frame must come from the same"):
        read_psp_folder(cap, "64x48")
