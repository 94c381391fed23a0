"""`sss repro paper` at the tiny preset: sessions captured through daemons (two at once, each its own), both
pretrainings, the decoder, Tables 1-2 beside the paper's, relighting, and the budget; sparse dot grids."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
from sss_process import run_sss

from sssphase_core.capture import CaptureRequest, RigSpec
from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import capture_plan


def test_a_dot_stride_keeps_every_sth_shift():
    full = capture_plan(256, 192, footprints=True, dot_spacing=20)
    sparse = capture_plan(256, 192, footprints=True, dot_spacing=20, dot_stride=3)
    dots = [f.key for f in sparse.frames if f.kind == "dots"]
    assert len([f for f in full.frames if f.kind == "dots"]) == 400
    assert len(dots) == 7 * 7 and "dots/0_0" in dots and "dots/18_3" in dots and "dots/1_0" not in dots
    with pytest.raises(InputError, match="dot stride must be 1"):
        capture_plan(256, 192, footprints=True, dot_spacing=20, dot_stride=21)
    with pytest.raises(InputError, match="dot stride must be 1"):
        CaptureRequest.from_options("apple", RigSpec(), footprints=True, dot_stride=0, out=Path("x"))


def test_device_on_a_rig_file_or_unknown_is_one_line(tmp_path):
    with pytest.raises(InputError, match="unknown device"):
        CaptureRequest.from_options("apple", RigSpec(), device="tpu", out=tmp_path)
    rig = RigSpec(camera="uvc:cam0", projector="hdmi:1", turntable=None)  # not the sim rig
    with pytest.raises(InputError, match="sim rig only"):
        CaptureRequest.from_options("apple", rig, device="cuda", out=tmp_path)


@pytest.fixture(scope="module")
def repro(tmp_path_factory):
    """`sss repro paper --preset tiny --device cpu --workers 2` as a user runs it (a subprocess)."""
    out = tmp_path_factory.mktemp("repro") / "run"
    done = run_sss(["repro", "paper", "--preset", "tiny", "--device", "cpu", "--workers", "2", "--out", str(out)], timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return out, done.stdout


@pytest.mark.slow
def test_repro_runs_every_step_and_reports_beside_the_paper(repro):
    out, stdout = repro
    data = json.loads((out / "report.json").read_text())
    assert {n: s["status"] for n, s in data["steps"].items()} == dict.fromkeys(
        ("train_sessions", "test_sessions", "pretrain_psp", "pretrain_imagenet", "decoder", "footprints", "knn", "relight",
         "report"), "done")
    steps = data["steps"]
    for name in ("pretrain_psp", "pretrain_imagenet"):  # the two augmentation sets, each a run of its own
        ckpt = Path(steps[name]["checkpoint"])
        assert ckpt.is_file() and f"pretrain_{name.split('_')[1]}" in str(ckpt)
        assert steps[name]["patches_s"] > 0 and steps[name]["gflop_per_patch"] > 0
    knn = steps["knn"]
    for aug in ("psp", "imagenet"):
        assert set(knn[aug]["per_class"]) == {"apple", "star"} and 0 <= knn[aug]["overall"] <= 1
    table1 = steps["footprints"]["metrics"]["sand_rake"]
    assert set(table1) == {"analytic", "torch"} and all(math.isfinite(m["psnr"]) for m in table1.values())
    from sssphase_core.compute import inference_precision

    said = inference_precision("cpu")  # the decoder's (auto): bf16 where this CPU computes it natively
    assert steps["footprints"]["inference"] == {"torch": said}
    assert {r["backend"] for r in steps["relight"]["rows"]} == {"none", "analytic", "torch"}
    md = (out / "report.md").read_text()
    assert "| apple | " in md and "99.60" in md and "99.95" in md  # the paper's Table 2 beside ours (apple, star)
    assert "Where the budget went" in md and "Scaled down to fit" in md and "1/16 of them (stride 4)" in md
    assert re.search(rf"torch [0-9.]+ ms \({said} inference\)", md), md  # the decoder's seconds per footprint, in that precision
    assert "## Table 1: footprints of unseen objects" in stdout and "report.md" in stdout  # printed at the end


def test_repro_sessions_are_sparse_dot_grids_that_the_measured_backend_refuses(repro):
    from sssphase_core.relight import load_view, make_source
    from sssphase_core.store.session import Session

    out, _ = repro
    s = Session.open(out / "sessions" / "train" / "apple")
    info = s.manifest["views"]["0"]["footprints"]
    assert info["dot_stride"] == 4 and info["count"] > 0
    assert "transport/crops" not in s.arrays(0)  # a sparse lattice is no light transport
    plan_dots = [f for f in s.manifest["plan"]["frames"] if f["kind"] == "dots"]
    assert len(plan_dots) == 5 * 5  # spacing 20, stride 4
    with pytest.raises(InputError, match="--dot-stride 4"):
        make_source("measured", load_view(s, 0))


def test_rerunning_resumes_and_a_spent_budget_runs_nothing(repro, tmp_path):
    from sssphase_core.reporting.repro import run_repro

    out, _ = repro
    logs: list[str] = []
    run_repro(out, lambda reqs: pytest.fail("a finished step was captured again"), preset="tiny", device="cpu", log=logs.append)
    assert sum("already done" in m for m in logs) == 8
    empty = tmp_path / "none"
    run_repro(empty, lambda reqs: pytest.fail("nothing may run"), preset="tiny", device="cpu", budget_s=1e-9, log=logs.append)
    data = json.loads((empty / "report.json").read_text())
    assert all("budget" in s.get("reason", "") for n, s in data["steps"].items() if n != "report")
    assert "not run: the budget of 0 s was spent" in (empty / "report.md").read_text()


def test_repro_refuses_bad_options_in_one_line(tmp_path):
    from sssphase_core.reporting.repro import run_repro

    for kwargs, message in (({"preset": "huge"}, "unknown repro preset"), ({"budget_s": float("nan")}, "--budget"),
                            ({"device": "gpu"}, "unknown device")):
        with pytest.raises(InputError, match=message):
            run_repro(tmp_path / "x", lambda reqs: [], **{"preset": "tiny", **kwargs})


def test_epochs_fit_the_time_left():
    from sssphase_core.reporting.repro import epochs_within

    assert epochs_within(100.0, 1000, 50.0, 20) == 5
    assert epochs_within(0.0, 1000, 50.0, 20) == 1  # at least one
    assert epochs_within(1e6, 1000, 50.0, 20) == 20  # at most the preset's


def test_a_relight_starts_only_if_its_estimate_fits(tmp_path):
    """Each relight is estimated before it starts: from a finished relight with the same backend (per lit pixel),
    else from its model's seconds per footprint in the footprints step (a blend: both models), else from the
    longest relight so far. On the H200 a 1080p torch relight was let start after the relight with no
    scattering, and the call's deadline cut it off with nothing kept."""
    from sssphase_core.reporting.repro import PRESETS, RELIGHT_MIN_S, RELIGHT_OVER_FOOTPRINTS, PaperRepro

    repro = PaperRepro(tmp_path, PRESETS["tiny"], capture=lambda requests: [], device="cpu", budget_s=1000.0,
                       log=lambda line: None)
    assert repro.relight_estimate_s("torch", 100_000) == RELIGHT_MIN_S  # nothing known yet
    repro.results["footprints"] = {"status": "done", "metrics": {}, "pixels": 256,
                                   "seconds_per_pixel": {"torch": 1e-3, "analytic": 2e-4}}
    over = RELIGHT_OVER_FOOTPRINTS["cpu"]  # (a GPU's relight batches are larger than the step's: its factor is lower)
    assert RELIGHT_OVER_FOOTPRINTS["cuda"] < over
    assert repro.relight_estimate_s("torch", 100_000) == pytest.approx(over * 100.0)
    assert repro.relight_estimate_s("blend", 100_000) == pytest.approx(over * 120.0)
    import torch

    import sssphase_core.compute as compute

    with pytest.MonkeyPatch.context() as mp:  # the same run on a GPU (its device asked for, not touched)
        mp.setattr(compute, "compute_device", lambda device=None: torch.device("cuda"))
        assert repro.relight_estimate_s("torch", 100_000) == pytest.approx(RELIGHT_OVER_FOOTPRINTS["cuda"] * 100.0)
    rows = [{"seconds": 40.0, "lit_pixels": 50_000, "psnr": 30.0, "ssim": 0.9, "object": "crab", "pattern": p,
             "backend": "torch"} for p in ("checkerboard", "stripes_x")]
    repro._relight_progress({"crab/torch": rows}, {})
    assert repro.relight_estimate_s("torch", 100_000) == pytest.approx(160.0)  # 80 s for 50,000 pixels, measured
    assert repro.relight_estimate_s("none", 100_000) == pytest.approx(80.0)  # no model: the longest so far
    assert repro._may_relight("torch", 100_000) is None  # plenty left
    repro.budget_s = repro.spent_s() + 100.0
    why = repro._may_relight("torch", 100_000)
    assert why is not None and "with torch of 100,000 pixels would take about 160 s" in why
    md = (tmp_path / "report" / "report.md").read_text()  # the finished relight is in the report at once
    assert "| crab | checkerboard | torch | 30.00 |" in md and "did not finish" in md
    assert "Seconds per footprint (the slowest object" in md and "torch 1.00 ms, analytic 0.20 ms" in md


@pytest.mark.slow
def test_a_stopped_relight_step_keeps_what_it_relit_and_resumes(repro, tmp_path):
    """Each object x backend is kept as it finishes: a rerun relights only the rest, and a decoder trained
    again makes its own relights stale, not the model-free ones."""
    import shutil

    from sssphase_core.reporting.repro import run_repro

    src, _ = repro
    out = tmp_path / "run"
    shutil.copytree(src, out)
    done = json.loads((out / "steps" / "relight.json").read_text())
    (out / "steps" / "relight.json").unlink()  # as if the step had been stopped after two of its relights
    kept = {f"sand_rake/{b}": [r for r in done["rows"] if r["backend"] == b] for b in ("none", "analytic")}
    kept["sand_rake/none"][0]["psnr"] = 123.0  # marks the row that must come back unrelit
    (out / "steps" / "relight_partial.json").write_text(json.dumps({"decoder": "another decoder", "units": kept}))
    logs: list[str] = []
    run_repro(out, lambda reqs: pytest.fail("nothing is captured again"), preset="tiny", device="cpu", log=logs.append)
    assert any("2 relight(s) kept from an earlier run: sand_rake/none, sand_rake/analytic" in m for m in logs)
    relit = [m for m in logs if m.startswith("  relit ")]
    assert len(relit) == 1 and "relit sand_rake with torch" in relit[0]
    rows = json.loads((out / "steps" / "relight.json").read_text())["rows"]
    assert [r["backend"] for r in rows] == [r["backend"] for r in done["rows"]]  # the configured order
    assert 123.0 in [r["psnr"] for r in rows]
    partial = json.loads((out / "steps" / "relight_partial.json").read_text())
    assert set(partial["units"]) == {"sand_rake/none", "sand_rake/analytic", "sand_rake/torch"}
    partial["decoder"] = "a decoder trained since"  # a torch relight of another decoder is not reused ...
    (out / "steps" / "relight_partial.json").write_text(json.dumps(partial))
    (out / "steps" / "relight.json").unlink()
    logs.clear()
    run_repro(out, lambda reqs: pytest.fail("nothing is captured again"), preset="tiny", device="cpu", log=logs.append)
    assert [m for m in logs if m.startswith("  relit ")] == [m for m in logs if "relit sand_rake with torch" in m]
    assert sum(m.startswith("  relit ") for m in logs) == 1  # ... the model-free ones are


@pytest.mark.slow
def test_relights_the_budget_left_out_are_done_by_the_next_run(repro, tmp_path, monkeypatch):
    """A relight step whose budget left relights out is "partial", not done: the next run (a budget of its own)
    relights only those, keeping the others, and then it is done."""
    import shutil

    from sssphase_core.reporting.repro import BUDGET_SPENT, PaperRepro, run_repro

    src, _ = repro
    out = tmp_path / "run"
    shutil.copytree(src, out)
    for name in ("relight.json", "relight_partial.json"):
        (out / "steps" / name).unlink(missing_ok=True)
    with monkeypatch.context() as patched:  # this run's budget has no room for the torch relight
        patched.setattr(PaperRepro, "_may_relight", lambda self, b, n: f"{BUDGET_SPENT} (test)" if b == "torch" else None)
        run_repro(out, lambda reqs: pytest.fail("nothing is captured again"), preset="tiny", device="cpu", log=lambda m: None)
    step = json.loads((out / "steps" / "relight.json").read_text())
    assert step["status"] == "partial" and "sand_rake/torch left to the budget" in step["reason"]
    assert {r["backend"] for r in step["rows"]} == {"none", "analytic"}
    assert "Not all relit: sand_rake/torch left to the budget" in (out / "report.md").read_text()
    logs: list[str] = []
    run_repro(out, lambda reqs: pytest.fail("nothing is captured again"), preset="tiny", device="cpu", log=logs.append)
    assert [m for m in logs if m.startswith("  relit ")] == [m for m in logs if "relit sand_rake with torch" in m] != []
    step = json.loads((out / "steps" / "relight.json").read_text())
    assert step["status"] == "done" and {r["backend"] for r in step["rows"]} == {"none", "analytic", "torch"}


def test_a_damaged_or_foreign_relight_record_is_relit_not_read(tmp_path):
    """The kept relights are reused only when every row holds what the report reads; otherwise they are done
    again, with one line saying so."""
    from sssphase_core.reporting.demo import ROW_KEYS
    from sssphase_core.reporting.repro import PRESETS, PaperRepro

    logs: list[str] = []
    repro = PaperRepro(tmp_path, PRESETS["tiny"], capture=lambda requests: [], device="cpu", budget_s=10.0,
                       log=logs.append)
    path = repro.steps_dir / repro.RELIT_SO_FAR
    good = dict.fromkeys(ROW_KEYS, 1.0)
    path.write_text(json.dumps({"decoder": None, "units": {"crab/none": [good]}}))
    assert repro._relit_so_far(None) == {"crab/none": [good]}
    for bad in ("{not json", json.dumps({"units": {"crab/none": [{"psnr": 30.0}]}}), json.dumps({"units": ["crab"]}),
                json.dumps({"units": {"crab/none": []}}), json.dumps([1, 2])):
        path.write_text(bad)
        logs.clear()
        assert repro._relit_so_far(None) == {}
        assert len(logs) == 1 and "is unreadable: its relights are done again" in logs[0]
