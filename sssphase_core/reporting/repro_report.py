"""``report.md`` of ``sss repro paper``: our figures beside the paper's Tables 1-2, the time each step took of
the budget, and what was scaled down to fit it."""

from __future__ import annotations

from typing import Any


class _Rows:
    """A Markdown table built row by row (cells already formatted)."""

    def __init__(self, columns: list[str]) -> None:
        self.columns, self.rows = columns, []

    def add(self, row: list[Any]) -> None:
        self.rows.append([str(v) for v in row])

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in self.rows])


def _num(v: Any, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _step_rows(data: dict[str, Any]) -> list[list[Any]]:
    rows = []
    for name, r in data["steps"].items():
        extra = ", ".join(f"{k} {r[k]}" for k in ("epochs", "patches", "batch", "patches_s", "gflop_per_patch") if k in r)
        if r.get("planned_epochs", r.get("epochs")) != r.get("epochs"):  # the step's time limit ended it early
            extra = extra.replace(f"epochs {r['epochs']}", f"epochs {r['epochs']} (of {r['planned_epochs']} planned: "
                                  "its time share was spent)", 1)
        if r.get("mfu") is not None:
            extra += f", MFU {r['mfu']:.1%} (of the datasheet's bf16 peak)"
        status = r.get("status", "?") + (" (an earlier run)" if r.get("resumed") else "")
        rows.append([name, status, f"{float(r.get('seconds', 0.0)):.1f}",
                     extra or str(r.get("reason", ""))[:160]])
    return rows


def repro_markdown(data: dict[str, Any]) -> str:
    """The report from ``report.json``'s content (see :meth:`PaperRepro.write_report`)."""
    cfg, steps, paper = data["config"], data["steps"], data["paper"]
    env = data["environment"]
    out = ["# The paper's Tables 1-2 at its scale (`sss repro paper`)", "",
           f"Device: {env['device']}, torch {env['torch']}, {env['cpu_cores']} CPU cores. Budget of this run "
           f"{data['budget_s']:.0f} s, spent {data['spent_s']:.0f} s (steps resumed from earlier runs: their own seconds below). Rig preset `{cfg['rig_preset']}`, model `{cfg['model']}`; the simulator's "
           "exact footprints are used for scoring only.", ""]

    fp = steps.get("footprints", {})
    out += ["## Table 1: footprints of unseen objects", ""]
    if fp.get("status") == "done":
        t = _Rows(["object", "source", "MSE", "PSNR (dB)", "SSIM", "LPIPS"])
        for obj, by in fp["metrics"].items():
            for b, m in by.items():
                t.add([obj, f"ours, {b}", _num(m.get("mse"), ".2e"), _num(m.get("psnr"), ".2f"), _num(m.get("ssim"), ".3f"),
                       _num(m.get("lpips"), ".3f")])
            if obj in paper["table1"]:
                p = paper["table1"][obj]
                t.add([obj, "paper", f"{p['mse']:.2e}", f"{p['psnr']:.2f}", f"{p['ssim']:.2f}", f"{p['lpips']:.3f}"])
        out += [t.markdown(), "", f"{fp['pixels']} sampled pixels per object; LPIPS: {fp.get('lpips')}. SSIM with the "
                "footprint's own peak as data range (see `sss eval footprints`).", ""]
        if rates := fp.get("seconds_per_pixel"):
            inference = fp.get("inference") or {}  # (absent from reports before bf16 inference: float32)
            out += ["Seconds per footprint (the slowest object, after a warm-up; they time the relights below): "
                    + ", ".join(f"{b} {1e3 * float(v):.2f} ms" + (f" ({inference[b]} inference)" if b in inference else "")
                                for b, v in rates.items()) + ".", ""]
    else:
        out += [f"Not available: {fp.get('reason', 'not run yet')}", ""]

    knn = steps.get("knn", {})
    out += ["## Table 2: kNN accuracy per object (view-level leave-one-out)", ""]
    if knn.get("status") == "done":
        t = _Rows(["object", "ours, PSP (%)", "ours, ImageNet (%)", "paper, PSP (%)", "paper, ImageNet (%)"])
        for obj in cfg["train_objects"]:
            ours = [knn.get(a, {}).get("per_class", {}).get(obj) for a in ("psp", "imagenet")]
            p = paper["table2"].get(obj, {})
            t.add([obj, *(_num(None if v is None else 100 * v, ".2f") for v in ours),
                   _num(p.get("psp"), ".2f"), _num(p.get("imagenet"), ".2f")])
        overall = [knn.get(a, {}).get("overall") for a in ("psp", "imagenet")]
        t.add(["all", *(_num(None if v is None else 100 * v, ".2f") for v in overall), "", ""])
        out += [t.markdown(), "", f"k = {knn['k']}, cosine similarity, majority vote.", ""]
    else:
        out += [f"Not available: {knn.get('reason', 'not run yet')}", ""]

    rel = steps.get("relight", {})
    out += ["## Relighting unseen objects against their reference captures", ""]
    if rel.get("status") in ("done", "running", "partial") and rel.get("rows"):
        t = _Rows(["object", "pattern", "backend", "PSNR (dB)", "SSIM", "s per pattern"])
        for r in rel["rows"]:
            t.add([r["object"], r["pattern"], r["backend"], f"{r['psnr']:.2f}", f"{r['ssim']:.3f}", f"{r['seconds']:.1f}"])
        out += [t.markdown(), ""]
        if rel["status"] == "running":
            out += ["The relight step did not finish (it was running when this report was written, or stopped): the "
                    "relights above are kept, and a rerun relights only the rest.", ""]
        elif rel["status"] == "partial":
            out += [f"Not all relit: {rel.get('reason')} (the relights above are kept).", ""]
        if rel.get("skipped"):
            out += ["Skipped: " + "; ".join(f"{k}: {v}" for k, v in rel["skipped"].items()), ""]
    else:
        out += [f"Not available: {rel.get('reason', 'not run yet')}", ""]

    out += ["## Where the budget went", ""]
    t = _Rows(["step", "status", "seconds", "size or reason"])
    for row in _step_rows(data):
        t.add(row)
    out += [t.markdown(), ""]

    out += ["## Scaled down to fit", ""]
    t = _Rows(["what", "here", "paper"])
    tr = steps.get("pretrain_psp", {})
    dec = steps.get("decoder", {})
    t.add(["training objects", ", ".join(cfg["train_objects"]), "apple, pear, orange, star, shovel"])
    t.add(["views per training object", cfg["train_views"], paper["scale"]["train views per object"]])
    t.add(["unseen objects (Table 1)", ", ".join(cfg["test_objects"]), "apple, orange, crab, hand"])
    t.add(["pixels per view (pretraining)", cfg["pixels_per_view"], paper["scale"]["patches"]])
    t.add(["footprint pixels (dot stride)", f"1/{cfg['dot_stride'] ** 2} of them (stride {cfg['dot_stride']})",
           "every pixel"])
    t.add(["pretraining epochs", tr.get("epochs", "—"), paper["scale"]["pretraining epochs"]])
    t.add(["decoder epochs", dec.get("epochs", "—"), paper["scale"]["decoder epochs"]])
    t.add(["batch", cfg["pretrain_batch"], paper["scale"]["batch"]])
    out += [t.markdown(), ""]
    return "\n".join(out) + "\n"
