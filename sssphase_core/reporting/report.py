"""The demo's HTML report (``report/index.html``): relit vs ground truth, tables, maps, timings.

A self-contained static page: images are files next to it (``img/``), tables are plain HTML. Steps
that did not run are listed as *not available* with their reason, never silently left out.
"""

from __future__ import annotations

import html
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.relight.choices import DECODER_WIDEN
from sssphase_core.store.files import save_figure, write_text

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: .6em 0; font-size: .92em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; text-align: right; }
th { background: #f2f2f2; } td.l, th.l { text-align: left; }
.na { background: #fff3cd; border: 1px solid #e0c46c; padding: .5em .8em; margin: .5em 0; }
.ok { color: #1a7f37; } .bad { color: #b42318; font-weight: bold; }
img { max-width: 100%; border: 1px solid #ddd; margin: .3em 0; }
.note { color: #555; font-size: .9em; }
"""
#: Records on <body> how many images decoded (checked by the headless-browser test).
LOAD_CHECK = ("<script>window.addEventListener('load', () => { const imgs = [...document.images]; "
              "document.body.dataset.imagesTotal = imgs.length; "
              "document.body.dataset.imagesLoaded = imgs.filter(i => i.complete && i.naturalWidth > 0).length; });</script>")


def _esc(v: Any) -> str:
    return html.escape(str(v))


def _fmt(v: Any, digits: int = 3) -> str:
    if isinstance(v, float | np.floating):  # a column's figures alike: 0.990 beside 0.989, 49.0; no 1.23e+03 s
        if not np.isfinite(v):
            return "n/a"
        if abs(v) >= 10**digits:
            return f"{v:.0f}"
        text = f"{v:#.{digits}g}"
        return text if "e" in text else text.rstrip(".")
    return _esc(v)


def html_table(columns: Sequence[str], rows: Sequence[Sequence[Any]], left: int = 1) -> str:
    """A table; the first ``left`` columns are left-aligned labels."""
    head = "".join(f"<th class='l'>{_esc(c)}</th>" if i < left else f"<th>{_esc(c)}</th>" for i, c in enumerate(columns))
    body = "".join(
        "<tr>" + "".join(f"<td class='l'>{_fmt(v)}</td>" if i < left else f"<td>{_fmt(v)}</td>" for i, v in enumerate(r)) + "</tr>"
        for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _not_available(step: str, result: dict[str, Any] | None) -> str:
    reason = (result or {}).get("reason", "the step did not run")
    return f"<div class='na'><b>{_esc(step)}: not available</b> &mdash; {_esc(reason)}</div>"


#: Each built-in backend's colour in the report's plots (a blend beside torch was drawn in torch's blue).
BACKEND_COLOURS = {"none": "tab:gray", "analytic": "tab:orange", "measured": "tab:olive", "exact": "tab:green",
                   "torch": "tab:blue", "blend": "tab:purple"}


def backend_colours(backends: list[str]) -> dict[str, str]:
    """A colour per backend, in order: the built-ins' own (:data:`BACKEND_COLOURS`), any other a colour none of
    them has (matplotlib's cycle would start again at torch's blue)."""
    spare = ("tab:red", "tab:brown", "tab:pink", "tab:cyan")  # none of the built-ins'
    others = [b for b in backends if b not in BACKEND_COLOURS]
    extra = {b: spare[i % len(spare)] for i, b in enumerate(others)}
    return {b: BACKEND_COLOURS.get(b) or extra[b] for b in backends}


def error_vs_runtime_plot(rows: Sequence[dict[str, Any]], path: Path) -> Path:
    """Relit PSNR against run time, one point per (object, pattern, backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    colours = backend_colours(list(dict.fromkeys(r["backend"] for r in rows)))
    for backend in colours:
        rs = [r for r in rows if r["backend"] == backend]
        ax.scatter([max(r["seconds"], 1e-4) for r in rs], [r["psnr"] for r in rs], label=backend, color=colours[backend])
    ax.set_xscale("log")
    ax.set_xlabel("run time per relit image (s): footprints + splat")
    ax.set_ylabel("PSNR vs noise-free GT (dB)")
    ax.set_title("error against run time (unseen objects)")
    ax.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def _relight_section(result: dict[str, Any], out: Path) -> str:
    from sssphase_core.relight.evaluation import aggregate, lpips_note

    rows = result["rows"]
    parts = []
    backends = list(dict.fromkeys(r["backend"] for r in rows))
    objects = list(dict.fromkeys(r["object"] for r in rows))
    per_obj = {(a["object"], a["backend"]): a for a in aggregate(rows, by=("object", "backend"))}
    cols = ["object"] + [f"{b} {m}" for b in backends for m in ("PSNR", "SSIM")]
    body = [[o] + [v for b in backends for v in ((per_obj[(o, b)]["psnr"], per_obj[(o, b)]["ssim"]) if (o, b) in per_obj else ("n/a", "n/a"))]
            for o in objects]
    means = {a["backend"]: a for a in aggregate(rows, by=("backend",))}
    body.append(["mean"] + [v for b in backends for v in (means[b]["psnr"], means[b]["ssim"])])
    parts.append("<h3>Relit images against their references (paper-style table)</h3>")
    parts.append(html_table(cols, body))
    parts.append("<p class='note'>The reference of a simulated session is the simulator's noise-free render of the "
                 "pattern (its ground truth); of a captured or imported one, the camera's capture of it.</p>")
    if result.get("training_overlap"):  # views the decoder was trained on: not unseen objects
        parts.append(f"<p class='note'>{_esc(result['training_overlap'])}</p>")
    for key, heading, note in (
            ("psnr_interior", "Relit images against their references, away from the silhouette",
             "PSNR on the object mask less the 2 px next to its edge: there a camera mixes object and background "
             "(blur, demosaicing), which bounds every source that takes its light from captures, "
             "<code>none</code> included; inside, the footprints decide."),
            ("psnr_capture", "Relit images against the camera's own capture of the pattern",
             "The capture carries sensor noise, which bounds every backend"
             + (" (also <code>exact</code>)" if "exact" in backends else "") + "; the relit images "
             "are compared as the camera would record them (its Bayer sampling and demosaicing, where the session "
             "records them)."),
            ("psnr_camera", "Relit images against the camera's image of the pattern without noise",
             "The noise-free render seen through the camera's Bayer sampling and demosaicing: what the camera records "
             "on average, so what relighting from captured data can reach.")):
        if all(key in r for r in rows):
            parts.append(f"<h3>{heading}</h3>")
            parts.append(html_table(["object"] + [f"{b} PSNR" for b in backends],
                                    [[o] + [per_obj[(o, b)][key] if (o, b) in per_obj else "n/a" for b in backends]
                                     for o in objects]))
            parts.append(f"<p class='note'>{note}</p>")
    said = {"exact": "<code>exact</code> splats the simulator's exact footprints (ground truth no lab has)",
            "measured": "<code>measured</code> splats the session's captured light transport (one crop per projector dot)",
            "none": "<code>none</code> keeps each pixel's own light (no scattering)",
            "blend": "<code>blend</code> weighs torch and analytic pixel by pixel by how well they relight the view's "
                     "own fringe captures (<code>sss relight</code>'s default with a decoder)"}
    decoders = [f"<code>{b}</code>" for b in ("torch", "blend") if b in backends]
    widened = (f" For {' and '.join(decoders)} that fit may also widen the decoder's footprints (they join it stretched "
               f"{DECODER_WIDEN:g} × along x, y and both, and softened, <code>sss relight --widen</code>'s default for "
               "them)." if decoders else "")
    parts.append(f"<p class='note'>PSNR in dB with peak 1.0 (linear camera units: a white Lambertian reference reads 1.0), "
                 f"SSIM (11 px Gaussian window), both on the object mask, mean over the view's reference patterns. "
                 f"{_esc(lpips_note())}. " + "; ".join(text for b, text in said.items() if b in backends)
                 + ("." if any(b in backends for b in said) else "") + widened
                 + (f" <code>analytic</code> integrates each footprint pixel at {int(result['analytic_supersample'])}"
                    f" × {int(result['analytic_supersample'])} points here (<code>sss relight</code> and <code>sss eval "
                    "relight</code>: 4 × 4), so their figures for it can differ slightly."
                    if "analytic" in backends and result.get("analytic_supersample") else "") + "</p>")
    for name, why in result.get("skipped", {}).items():
        parts.append(_not_available(f"relighting with the {name} backend", {"reason": why}))
    if "torch" in means:
        margins = {b: means["torch"]["psnr"] - means[b]["psnr"] for b in ("none", "analytic") if b in means}
        txt = ", ".join(f"{'beats' if d > 0 else 'does NOT beat'} {b} ({d:+.2f} dB)" for b, d in margins.items())
        parts.append(f"<p>Torch backend (mean PSNR {means['torch']['psnr']:.2f} dB) {txt}.</p>")
    plot = error_vs_runtime_plot(rows, out / "img" / "error_vs_runtime.png")
    parts.append("<h3>Error against run time</h3>")
    parts.append(f"<img src='{plot.relative_to(out).as_posix()}' alt='error against run time'>")
    parts.append("<h3>GT / relit / |difference|</h3>")
    for r in rows:
        parts.append(f"<div><b>{_esc(r['object'])}</b>, {_esc(r['pattern'])}, {_esc(r['backend'])}: "
                     f"PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.3f}<br>"
                     f"<img src='{_esc(r['figure'])}' alt='{_esc(r['object'])} {_esc(r['pattern'])} {_esc(r['backend'])}'></div>")
    return "\n".join(parts)


def _knn_section(result: dict[str, Any]) -> str:
    start = result.get("initial")  # the same table for the encoder pretraining started from
    if start is None:
        rows = [[c, 100 * a] for c, a in result["per_class"].items()]
        rows += [["overall", 100 * result["overall"]], ["mean per view", 100 * result["mean_per_view"]]]
        header = ["object", "kNN accuracy (%)"]
    else:
        rows = [[c, 100 * a, 100 * start["per_class"].get(c, float("nan"))] for c, a in result["per_class"].items()]
        rows += [["overall", 100 * result["overall"], 100 * start["overall"]],
                 ["mean per view", 100 * result["mean_per_view"], ""]]
        header = ["object", "kNN accuracy (%)", "initial encoder (%)"]
    note = (f"k = {result['k']}, {result['vote']} vote, cosine similarity, view-level leave-one-out over the training "
            "objects' views (the paper's Table 2 protocol).")
    if start is not None:
        note += (" Initial encoder: the same table for the encoder pretraining started from (its seeded random "
                 "initialisation), the baseline measured in the same run.")
    if result.get("unscored"):
        note += (f" Not scored: {', '.join(map(str, result['unscored']))}, in one view only (leaving that view out "
                 "leaves nothing of it to match).")
    return html_table(header, rows) + f"<p class='note'>{note}</p>"


def write_report(out: Path | str, results: dict[str, dict[str, Any]], config: dict[str, Any], *,
                 title: str = "sssphase demo report", rig: str = "Simulated rig (CPU preset)") -> Path:
    """Write ``out/index.html`` from the demo's (or ``sss report``'s) step results; returns its path."""
    out = Path(out)
    (out / "img").mkdir(parents=True, exist_ok=True)
    sections = [f"<h1>{_esc(title)}</h1><p class='note'>Generated {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}. "
                f"{_esc(rig)}, model preset <code>{_esc(config.get('model'))}</code>; training objects "
                f"{_esc(', '.join(config.get('train_objects', ())) or 'none given')}; test objects "
                f"{_esc(', '.join(config.get('test_objects', ())))}.</p>"]
    missing = [n for n, r in results.items() if r.get("status") != "done" and n != "report"]
    if missing:
        sections.append(_not_available("steps " + ", ".join(missing), {"reason": "see the timings table below for each reason"}))
    sections.append("<h2>Relighting unseen objects</h2>")
    rel = results.get("relight", {})
    sections.append(_relight_section(rel, out) if rel.get("status") == "done" and rel.get("rows") else _not_available("relighting", rel))
    sections.append("<h2>Footprint reconstruction (paper's Table 1)</h2>")
    fpr = results.get("footprints", {})
    if fpr.get("status") == "done" and fpr.get("backends"):
        bs = fpr["backends"]
        cols = ["object"] + [f"{b} {m}" for b in bs for m in ("MSE x1e-5", "PSNR", "SSIM")]
        body = [[o] + [v for b in bs for v in (1e5 * m[b]["mse"], m[b]["psnr"], m[b]["ssim"])] for o, m in fpr["metrics"].items()]
        inference = "".join(f"; the {_esc(b)} decoder inferred in {_esc(v)}" for b, v in (fpr.get("inference") or {}).items())
        sections.append(html_table(cols, body) + f"<p class='note'>{fpr['pixels']} sampled valid pixels per unseen object, "
                        "against the simulator's exact footprints; PSNR peak 1.0, SSIM data range = each footprint's peak"
                        f"{inference}.</p>")
    else:
        sections.append(_not_available("footprint table", fpr))
    sections.append("<h2>kNN classification of the embeddings</h2>")
    knn = results.get("knn", {})
    sections.append(_knn_section(knn) if knn.get("status") == "done" else _not_available("kNN table", knn))
    sections.append("<h2>PCA-RGB maps</h2>")
    pca = results.get("pca", {})
    if pca.get("status") == "done":
        sections.append(f"<p class='note'>First three principal components of the frozen encoder's per-pixel embeddings "
                        f"({_esc(', '.join(pca['objects']))}, jointly), shown as RGB.</p><img src='{_esc(pca['figure'])}' alt='PCA-RGB'>")
    else:
        sections.append(_not_available("PCA-RGB maps", pca))
    sections.append("<h2>Configuration</h2>")
    sections.append(html_table(["setting", "value"], [[k, ", ".join(map(str, v)) if isinstance(v, list | tuple) else v]
                                                      for k, v in config.items()], left=2))
    sections.append("<h2>Timings</h2>")
    trows = [[n, "given (not run here)", "", r.get("reason", "")] if r.get("given") else
             [n, r.get("status", "?") + (" (resumed: skipped)" if r.get("resumed") else ""),
              float(r.get("seconds", float("nan"))), r.get("reason", "")] for n, r in results.items() if n != "report"]
    sections.append(html_table(["step", "status", "seconds", "note"], trows, left=2))
    sections.append(f"<p class='note'>Total {sum(float(r.get('seconds', 0)) for r in results.values()):.1f} s of step time "
                    "(skipped steps show the time of the run that did them; the sessions and runs given to `sss "
                    "report` were made elsewhere: their own records hold their times).</p>")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_esc(title)}</title><style>{STYLE}</style></head>"
            f"<body>{''.join(sections)}{LOAD_CHECK}</body></html>")
    path = out / "index.html"
    write_text(path, page)
    return path
