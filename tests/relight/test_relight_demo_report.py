"""`sss demo --preset tiny` end to end, resumed, and its report rendered in headless Chromium."""

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from sssphase_core.reporting.demo import STEPS, run_demo
from sssphase_core.store.session import Session

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory, sim_daemon):
    out = tmp_path_factory.mktemp("demo")
    lines: list[str] = []
    report = run_demo(out, sim_daemon, preset="tiny", log=lines.append)
    return out, report, lines, sim_daemon


@pytest.mark.slow
def test_demo_runs_every_step_and_resumes(demo):
    out, report, lines, client = demo
    assert report == out / "report" / "index.html" and report.exists()
    for kind in ("train", "test"):  # the demo's sessions are captured sessions: they validate
        for session in (out / "sessions" / kind).iterdir():
            assert Session.open(session).validate() == [], session
    assert "footprints/crops" in Session.open(out / "sessions" / "train" / "apple").arrays(0)
    for step in STEPS:
        assert any(line.startswith(f"[{step}] done") for line in lines), (step, lines)
    page = report.read_text()
    assert "not available" not in page
    knn = json.loads((out / "steps" / "knn.json").read_text())  # beside the pretrained encoder's, the one it started from
    assert 0 <= knn["initial"]["overall"] <= 1 and knn["initial"]["per_class"].keys() == knn["per_class"].keys()
    assert "initial encoder (%)" in page
    from sssphase_core.compute import inference_precision

    assert f"the torch decoder inferred in {inference_precision('cpu')}" in page  # Table 1's note: bf16 or float32
    for backend in ("none", "torch", "exact"):
        assert f"sand_rake_v0_checkerboard_{backend}_compare.png" in page
    again: list[str] = []
    run_demo(out, client, preset="tiny", log=again.append)
    skipped = [s for s in STEPS if any(line.startswith(f"[{s}] already done") for line in again)]
    assert skipped == [s for s in STEPS if s != "report"]  # only the report is rewritten
    assert any(line.startswith("[report] done") for line in again), again
    resumed = report.read_text()
    assert "resumed: skipped" in resumed and "sand_rake_v0_checkerboard_torch_compare.png" in resumed


def test_the_footprints_step_reads_a_devices_footprints_without_numpy(demo, monkeypatch):
    """On a GPU (`sss repro paper --device cuda`) the decoder's footprints arrive as tensors on the device, which NumPy
    cannot read (``np.asarray`` of a CUDA tensor is a TypeError). Emulated on the CPU: tensors refuse NumPy's implicit
    conversion as CUDA ones do; Table 1's step scores the same footprints as the demo's run did."""
    import torch

    from sssphase_core.reporting.demo import PRESETS, Demo

    out, _, _, client = demo
    again = Demo(out, PRESETS["tiny"], client, log=lambda line: None)
    for name in ("test_sessions", "decoder"):
        again.results[name] = json.loads((out / "steps" / f"{name}.json").read_text())

    def refuse(self, *args, **kwargs):
        raise TypeError(f"can't convert {self.device} device type tensor to numpy (as a cuda:0 tensor)")

    monkeypatch.setattr(torch.Tensor, "__array__", refuse)
    got = again.footprints()
    want = json.loads((out / "steps" / "footprints.json").read_text())
    assert got["backends"] == want["backends"] and "torch" in got["backends"]
    for obj, rows in want["metrics"].items():
        for backend, row in rows.items():
            assert got["metrics"][obj][backend] == pytest.approx(row, rel=1e-6), (obj, backend)


@pytest.mark.slow
def test_report_renders_with_its_images_in_headless_chromium(demo, tmp_path):
    if not CHROMIUM.exists() or shutil.which(str(CHROMIUM)) is None:
        pytest.skip("/usr/bin/chromium is not installed (Debian package `chromium`: apt-get install -y chromium)")
    _, report, _, _ = demo
    url = report.resolve().as_uri()
    common = [str(CHROMIUM), *FLAGS, f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run([*common, "--virtual-time-budget=5000", "--dump-dom", url], capture_output=True, text=True,
                         timeout=60).stdout
    srcs = re.findall(r"<img[^>]*src=\"([^\"]+)\"", dom)
    assert len(srcs) >= 6 and all((report.parent / s).exists() for s in srcs)
    loaded = re.search(r'data-images-loaded="(\d+)"', dom)
    total = re.search(r'data-images-total="(\d+)"', dom)
    assert loaded and total and loaded.group(1) == total.group(1) == str(len(srcs))
    shot = tmp_path / "shot.png"
    subprocess.run([*common, f"--screenshot={shot}", "--window-size=1200,1600", url], capture_output=True, timeout=60)
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"), np.float32)
    assert img.shape == (1600, 1200) and img.std() > 10  # not blank: text, tables and figures


def test_the_report_says_how_finely_its_analytic_footprints_were_integrated(tmp_path):
    """`sss report` scored analytic at 2 x 2 points per footprint pixel and `sss relight` at 4 x 4: the same view
    read 32.44 and 32.36 dB with nothing to say why."""
    from sssphase_core.reporting.report import _relight_section

    rows = [{"object": "crab", "view": 0, "pattern": p, "backend": b, "psnr": 30.0 + i, "ssim": 0.9, "mse": 1e-3,
             "seconds": 1.0, "lit_pixels": 100, "figure": "x.png"}
            for i, b in enumerate(("none", "analytic")) for p in ("checkerboard", "stripes_x")]
    page = _relight_section({"rows": rows, "skipped": {}, "analytic_supersample": 2}, tmp_path)
    assert "integrates each footprint pixel at 2 × 2 points here" in page
    assert "integrates" not in _relight_section({"rows": rows[:2], "skipped": {}, "analytic_supersample": 2}, tmp_path)
    seen = "note: the decoder was trained on crab view 0: the torch and blend figures there measure how it fits"
    assert seen in _relight_section({"rows": rows, "skipped": {}, "analytic_supersample": 2, "training_overlap": seen},
                                    tmp_path)
    assert "trained on" not in page  # (a decoder of unseen objects, or none)


def test_the_reports_knn_table_names_the_objects_it_could_not_score():
    """An object of one view has nothing of it left when that view is left out: it read 0% and pulled the overall
    figure down; it is now left out of the scores, and the report says which and why."""
    from sssphase_core.reporting.report import _knn_section

    result = {"per_class": {"apple": 0.9, "star": 0.8}, "overall": 0.85, "mean_per_view": 0.85, "k": 20, "vote": "majority"}
    assert "Not scored" not in _knn_section(result)
    page = _knn_section({**result, "unscored": {"pear": 40, "soap": 40}})
    assert "Not scored: pear, soap, in one view only" in page and ">pear<" not in page


def test_every_backend_in_the_error_against_run_time_plot_has_a_colour_of_its_own():
    """The blend was drawn in the torch backend's blue (matplotlib's cycle restarted for a backend without a colour)."""
    from sssphase_core.reporting.report import backend_colours

    names = ["none", "analytic", "torch", "blend", "exact", "measured", "plugin_a", "plugin_b"]
    colours = backend_colours(names)
    assert list(colours) == names and len(set(colours.values())) == len(names)


def test_report_figures_keep_their_digits_and_long_times_read_whole():
    """A column showed 0.99 beside 0.989 and 49 beside 23.4; 1,234 s read 1.23e+03."""
    from sssphase_core.reporting.report import _fmt

    assert [_fmt(v) for v in (0.99, 0.989, 49.0, 23.36, 1234.5, float("nan"))] == \
        ["0.990", "0.989", "49.0", "23.4", "1234", "n/a"]
