"""The relighting benchmarks on small configurations: finiteness, work-precision ordering, lit counts."""

import json

import numpy as np

from sssphase_core.bench import relight_bench, stability_bench


def test_stability_cases_stay_finite_and_exact_footprints_win(tmp_path):
    res = stability_bench.run(tmp_path / "stab.json", cases=["wide"], backends=("none", "exact"))
    rows = {(r["case"], r["backend"]): r for r in res["rows"]}
    assert res["non_finite"] == [] and all(r["finite"] for r in rows.values())
    assert rows[("wide", "exact")]["psnr"] > rows[("wide", "none")]["psnr"] + 10
    saved = json.loads((tmp_path / "stab.json").read_text())
    assert len(saved["rows"]) == 2 and (tmp_path / "stab.md").read_text().count("| wide |") == 2


def test_work_precision_truncation_costs_accuracy_and_lit_counts_follow_patterns():
    sv = relight_bench.sim_view(stability_bench.case_object(stability_bench.CASES[1]))  # wide footprints
    rows = relight_bench.work_precision(sv, ["exact"], checkpoint=None, radii=(3,), chunks=(), dtypes=("bf16",))
    by = {(r["dtype"], r["radius"]): r for r in rows}
    full, cut, bf16 = by[("fp32", 16)], by[("fp32", 3)], by[("bf16", 16)]
    assert full["psnr"] > 100 and cut["psnr"] < full["psnr"] - 20 and 40 < bf16["psnr"] < full["psnr"]
    assert all(r["finite"] for r in rows)
    lit = relight_bench.cost_vs_lit(sv, sv.scene.footprints, sv.patch, repeats=1)
    frac = {r["pattern"]: r["lit_fraction"] for r in lit}
    assert frac["white"] == 1 and 0.3 < frac["checkerboard"] < 0.7 and frac["tenth"] < frac["quarter"] < frac["checkerboard"]
    assert np.isfinite([r["seconds"] for r in lit]).all()
