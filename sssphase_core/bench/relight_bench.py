"""`sss bench relight`: relit error against run time, cost against lit fraction, splat throughput.

Everything runs on simulated views, so the reference is the simulator's noise-free render under
the same pattern. Backends: ``none`` (no scattering), ``analytic`` (physics baseline from the PSP
modulation), ``exact`` (the simulator's exact footprints: the upper bound, ground truth no lab has), ``torch`` when a decoder
checkpoint is given. Swept: footprint truncation radius, chunk size and the splat's precision (fp32, bf16), and
for the decoder its inference's precision (fp32, bf16). Times are the footprint time (network / model / simulator, measured once per backend) plus the splat.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sssphase_core.bench.output import Table, machine_info, median_seconds, write_bench_report
from sssphase_core.relight import Projection, emitted_light, lit_pixels, make_source, relight
from sssphase_core.relight.choices import BLENDS
from sssphase_core.relight.evaluation import relight_metrics
from sssphase_core.store.files import save_figure

Progress = Callable[[str], None]


@dataclass
class SimView:
    """A simulated view with everything relighting needs and noise-free references."""

    object: str
    view: int
    scene: Any
    proj: Projection
    psp: np.ndarray  # (8, H, W, 3) noisy PSP captures
    white: np.ndarray  # the image under full white: noise-free, or captured (``sim_view(white_exposure=...)``)
    patch: int
    references: dict[str, np.ndarray]  # pattern name -> projector pattern
    captured: dict[str, np.ndarray]  # pattern name -> noise-free render
    sim: dict | None = None
    session: object | None = None
    saturation: float | None = None  # the PSP frames' clipping level (linear units)
    white_saturation: float | None = None  # None: the white does not clip (noise-free)
    psp_patterns: np.ndarray | None = None  # (8, Hp, Wp) projector images of ``psp``


def sim_view(obj: Any, view: int = 0, *, n_views: int = 4, seed: int = 0, rig: str = "cpu", exposure: float = 1.0,
             patterns: dict[str, np.ndarray] | None = None, white_exposure: float | None = None) -> SimView:
    """Simulate one view: noisy PSP inputs (at ``exposure``), exact correspondences, references.
    ``white_exposure``: the white frame captured through the sensor at this exposure, as a session captures
    it (its noise and clipping: what ``none`` and the energy repairs read in a lab); None: its noise-free
    render."""
    from sssphase_core.processing.patterns import paper_inputs, psp_config_for
    from sssphase_core.sim import SimScene, rig_preset

    cfg = rig_preset(rig)
    scene = SimScene(obj, rig=cfg, view=view, n_views=n_views, seed=seed)
    hp, wp = scene.shape_projector
    if patterns is None:
        from sssphase_core.processing.patterns import reference_pattern

        patterns = {n: reference_pattern(n, wp, hp) for n in ("checkerboard", "stripes_x")}
    pats = patterns
    names = list(pats)
    images = scene.render(np.stack([np.ones((hp, wp), np.float32), *(pats[n] for n in names)]))
    rng = np.random.default_rng(seed + 1000 * view)
    # The developed frames are already in linear camera units whatever the exposure (the ISP divides by
    # the sensor's DN per unit at that exposure): only clipping and noise change with it.
    inputs = paper_inputs(wp, hp, period=psp_config_for(wp, hp).period)
    psp = scene.capture(inputs, rng, exposure=exposure)
    white = images[0] if white_exposure is None else scene.sense(images[:1], rng, white_exposure)[0]
    valid = scene.mask & np.isfinite(scene.proj_xy).all(axis=-1)
    proj = Projection(scene.proj_xy[..., 0], scene.proj_xy[..., 1], valid, (wp, hp), cfg.projector.gamma, cfg.projector.black)
    name = scene.obj.name
    return SimView(name, view, scene, proj, np.asarray(psp, np.float32), np.asarray(white, np.float32), cfg.patch,
                   dict(pats), dict(zip(names, images[1:], strict=True)),
                   {"object": name, "preset": rig, "n_views": n_views, "seed": seed}, None, cfg.sensor.saturation(exposure),
                   None if white_exposure is None else cfg.sensor.saturation(white_exposure), inputs)


def source_for(backend: str, sv: SimView, checkpoint: Path | str | None, precision: str = "auto") -> tuple[Callable, int]:
    """The footprint source of ``backend`` for a simulated view (``exact``: the simulator's footprints), a decoder's
    inferring in ``precision``."""
    if backend == "exact":
        return sv.scene.footprints, sv.patch
    return make_source(backend, sv, checkpoint=checkpoint, precision=precision)  # type: ignore[arg-type]


class InMemorySource:
    """Footprints of a fixed pixel set computed once (timed), then looked up: sweeps of the splat
    settings then time only the splat, and each row adds the one-off footprint time."""

    def __init__(self, source: Callable, pixels: np.ndarray, shape: tuple[int, int], chunk: int = 1024):
        t0 = time.perf_counter()
        parts = [source(pixels[i : i + chunk]) for i in range(0, len(pixels), chunk)]
        parts = [p.float().cpu().numpy() if torch.is_tensor(p) else np.asarray(p, np.float32) for p in parts]
        self.fps = np.concatenate(parts) if parts else np.zeros((0, 1, 1, 3), np.float32)
        self.seconds = time.perf_counter() - t0
        self.width = shape[1]
        self.slot = np.full(shape[0] * shape[1], -1, np.int64)
        self.slot[pixels[:, 0] * shape[1] + pixels[:, 1]] = np.arange(len(pixels))

    def __call__(self, px: np.ndarray) -> np.ndarray:
        return self.fps[self.slot[px[:, 0] * self.width + px[:, 1]]]


def work_precision(sv: SimView, backends: Sequence[str], *, checkpoint: Path | str | None, radii: Sequence[int],
                   chunks: Sequence[int], dtypes: Sequence[str], default_chunk: int = 1024,
                   progress: Progress | None = None) -> list[dict[str, Any]]:
    """Relit PSNR (mean over the reference patterns) and run time per backend and configuration.

    ``seconds`` = footprint time (once per backend, and for the decoder once per inference precision: ``inference``)
    + the configuration's splat time. The decoder's bf16 inference is relit with the default splat only."""
    names = sorted(sv.references)
    pats = [sv.references[n] for n in names]
    pixels, _ = lit_pixels(sv.proj, emitted_light(np.stack(pats), sv.proj.gamma))
    rows = []
    runs = [(b, inference) for b in backends for inference in (("fp32", "bf16") if b == "torch" else ("-",))]
    for backend, inference in runs:
        if backend in BLENDS:  # several models weighed by the view calibration: relit as `sss relight` does, once
            rows.append(blend_row(sv, backend, pats, names, checkpoint, len(pixels), default_chunk, progress))
            continue
        if progress:
            progress(f"{sv.object}: {backend} footprints of {len(pixels)} lit pixels"
                     + (f" ({inference} inference)" if inference != "-" else ""))
        source, patch = source_for(backend, sv, checkpoint, "fp32" if inference == "-" else inference)
        cached = InMemorySource(source, pixels, sv.proj.shape)
        configs = [("fp32", default_chunk, None)]
        if backend != "none" and inference in ("-", "fp32"):
            configs += [("fp32", default_chunk, r) for r in radii if r < patch // 2]
            configs += [("fp32", c, None) for c in chunks if c != default_chunk]
            configs += [(d, default_chunk, None) for d in dtypes if d != "fp32"]
        for dtype, chunk, radius in configs:
            if progress:
                progress(f"{sv.object}: {backend} {dtype} chunk {chunk} radius {radius if radius is not None else 'full'}")
            t0 = time.perf_counter()
            out = relight(cached, sv.proj, pats, patch, white=sv.white, chunk=chunk, radius=radius,
                          dtype=torch.bfloat16 if dtype == "bf16" else torch.float32)
            splat = time.perf_counter() - t0
            mets = [relight_metrics(o, sv.captured[n], sv.proj.mask) for o, n in zip(out, names, strict=True)]
            rows.append({"object": sv.object, "backend": backend, "inference": inference, "dtype": dtype, "chunk": chunk,
                         "radius": radius if radius is not None else patch // 2, "seconds": cached.seconds + splat,
                         "footprint_seconds": cached.seconds, "splat_seconds": splat, "lit_pixels": len(pixels),
                         "psnr": float(np.mean([m["psnr"] for m in mets])), "ssim": float(np.mean([m["ssim"] for m in mets])),
                         "finite": bool(np.isfinite(out).all())})
    return rows


def blend_row(sv: SimView, backend: str, pats: list[np.ndarray], names: list[str], checkpoint: Path | str | None,
              lit: int, chunk: int, progress: Progress | None = None) -> dict[str, Any]:
    """One row for a blend (:data:`~sssphase_core.relight.choices.BLENDS`): its members' footprints predicted and
    weighed by the view calibration in one pass (:func:`~sssphase_core.relight.pipeline.relight_view`, widened as
    ``sss relight`` widens it), timed whole; the splat settings are not swept (its members' rows sweep them)."""
    from sssphase_core.relight.backends import make_sources
    from sssphase_core.relight.choices import widen_for
    from sssphase_core.relight.pipeline import relight_view

    if progress:
        progress(f"{sv.object}: {backend} (its members' footprints and the view calibration)")
    t0 = time.perf_counter()
    (source, patch), *also = make_sources(backend, sv, checkpoint=checkpoint)  # type: ignore[arg-type]
    out, _ = relight_view(source, patch, sv, pats, calibrate=True, also=also, chunk=chunk,  # type: ignore[arg-type]
                          widen=widen_for(backend, None))
    seconds = time.perf_counter() - t0
    decoder = getattr(source, "backend", None)
    mets = [relight_metrics(o, sv.captured[n], sv.proj.mask) for o, n in zip(out, names, strict=True)]
    return {"object": sv.object, "backend": backend, "inference": getattr(decoder, "precision", "-"), "dtype": "fp32",
            "chunk": chunk, "radius": patch // 2, "seconds": seconds, "footprint_seconds": seconds, "splat_seconds": 0.0,
            "lit_pixels": lit, "psnr": float(np.mean([m["psnr"] for m in mets])),
            "ssim": float(np.mean([m["ssim"] for m in mets])), "finite": bool(np.isfinite(out).all())}


def lit_fraction_patterns(width: int, height: int) -> dict[str, np.ndarray]:
    """Patterns lighting about 100 %, 50 %, 25 % and 10 % of the projector."""
    from sssphase_core.processing.patterns import checkerboard, stripes

    quarter = np.zeros((height, width), np.float32)
    quarter[: height // 2, : width // 2] = 1
    tenth = (stripes(width, height, 20, "x") * (np.arange(width) % 20 < 2)).astype(np.float32)
    return {"white": np.ones((height, width), np.float32), "checkerboard": checkerboard(width, height, 16),
            "quarter": quarter, "tenth": tenth}


def cost_vs_lit(sv: SimView, source: Callable, patch: int, *, repeats: int = 3) -> list[dict[str, Any]]:
    """Run time against the number of lit valid pixels, relative to full white."""
    hp, wp = sv.proj.projector_size[1], sv.proj.projector_size[0]
    rows = []
    for name, pat in lit_fraction_patterns(wp, hp).items():
        n_lit = len(lit_pixels(sv.proj, emitted_light(pat[None], sv.proj.gamma))[0])
        sec = median_seconds(lambda p=pat: relight(source, sv.proj, p[None], patch, white=sv.white), repeats=repeats)
        rows.append({"pattern": name, "lit_pixels": n_lit, "seconds": sec})
    white = rows[0]
    for r in rows:
        r["lit_fraction"] = r["lit_pixels"] / max(white["lit_pixels"], 1)
        r["time_fraction"] = r["seconds"] / white["seconds"]
    return rows


def matmul_flops(n: int = 1024, repeats: int = 5) -> float:
    """Measured float32 dense matrix-multiply FLOP/s (torch, this process's threads)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    return 2 * n**3 / median_seconds(lambda: a @ b, repeats=repeats)


def splat_throughput(sv: SimView, *, n_patterns: int = 2, repeats: int = 3) -> list[dict[str, Any]]:
    """Splat-only FLOP/s (2 flops per footprint entry and pattern) per kernel, footprints in memory."""
    pixels, _ = lit_pixels(sv.proj, emitted_light(np.ones((1, *sv.proj.projector_size[::-1]), np.float32), sv.proj.gamma))
    fps = sv.scene.footprints(pixels)
    slot = np.full(sv.proj.mask.size, -1, np.int64)
    slot[pixels[:, 0] * sv.proj.shape[1] + pixels[:, 1]] = np.arange(len(pixels))

    def source(px: np.ndarray) -> np.ndarray:
        return fps[slot[px[:, 0] * sv.proj.shape[1] + px[:, 1]]]

    pats = np.ones((n_patterns, *sv.proj.projector_size[::-1]), np.float32)
    flops = 2.0 * fps.size * n_patterns
    rows = []
    for method in ("csc", "index", "fold"):
        sec = median_seconds(lambda m=method: relight(source, sv.proj, pats, sv.patch, chunk=2048, method=m), repeats=repeats)
        rows.append({"method": method, "seconds": sec, "flops": flops / sec, "lit_pixels": len(pixels)})
    return rows


def plot(rows: list[dict[str, Any]], lit: list[dict[str, Any]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    colours = {"none": "tab:gray", "analytic": "tab:orange", "exact": "tab:green", "torch": "tab:blue", "blend": "tab:purple"}
    for backend in dict.fromkeys(r["backend"] for r in rows):
        rs = [r for r in rows if r["backend"] == backend]
        a.scatter([r["seconds"] for r in rs], [r["psnr"] for r in rs], label=backend, color=colours.get(backend))
        for r in rs:
            net = f"net {r['inference']} " if r.get("inference", "-") != "-" else ""
            a.annotate(f"{net}{r['dtype']} c{r['chunk']} r{r['radius']}", (r["seconds"], r["psnr"]), fontsize=6, alpha=0.7)
    a.set_xscale("log")
    a.set_xlabel("run time (s, footprints + splat)")
    a.set_ylabel("relit PSNR vs noise-free reference (dB)")
    a.set_title("work-precision")
    a.legend()
    b.plot([r["lit_fraction"] for r in lit], [r["time_fraction"] for r in lit], "o-", label="exact")
    b.plot([0, 1], [0, 1], "k--", lw=0.8, label="proportional")
    b.set_xlabel("lit valid pixels (fraction of full white)")
    b.set_ylabel("run time (fraction of full white)")
    b.set_title("cost against lit pixels")
    b.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def run(out: Path, *, objects: Sequence[str] = ("soap",), checkpoint: Path | str | None = None,
        backends: Sequence[str] = ("none", "analytic", "exact", "torch"), radii: Sequence[int] = (4, 8),
        chunks: Sequence[int] = (256, 4096), dtypes: Sequence[str] = ("fp32", "bf16"), repeats: int = 3,
        progress: Progress | None = None) -> dict[str, Any]:
    """The whole benchmark; writes ``out`` (JSON), ``out.md`` and ``out.png``. Returns the result."""
    out = Path(out)
    use = [b for b in backends if (b != "torch" and b not in BLENDS) or checkpoint is not None]
    rows: list[dict[str, Any]] = []
    views = []
    for obj in objects:
        if progress:
            progress(f"simulating {obj}")
        sv = sim_view(obj)
        views.append(sv)
        rows += work_precision(sv, use, checkpoint=checkpoint, radii=radii, chunks=chunks, dtypes=dtypes, progress=progress)
    sv = views[0]
    if progress:
        progress("cost against lit fraction")
    lit = cost_vs_lit(sv, sv.scene.footprints, sv.patch, repeats=repeats)
    if progress:
        progress("splat throughput and matmul FLOP/s")
    peak = matmul_flops()
    splats = splat_throughput(sv, repeats=repeats)
    for s in splats:
        s["ratio_to_matmul"] = s["flops"] / peak
    figure = plot(rows, lit, out.with_suffix(".png"))
    skipped = [b for b in backends if b not in use]
    tables = [
        Table("Work-precision: relit PSNR against run time", ["object", "backend", "inference", "dtype", "chunk", "radius",
                                                              "PSNR (dB)", "SSIM", "footprints (s)", "time (s)"],
              [[r["object"], r["backend"], r["inference"], r["dtype"], r["chunk"], r["radius"], r["psnr"], r["ssim"],
                r["footprint_seconds"], r["seconds"]] for r in rows],
              note="PSNR (peak 1.0, linear camera units) on the object mask, mean over the checkerboard and stripe patterns. "
              "Time = footprints (once per backend; the decoder's once per inference precision, bf16 relit with the "
              "default splat only) + splat; `dtype` is the splat's precision; `exact` footprints come from the simulator's cache "
              "(filled when the references were rendered), so its time is lookup + splat."
              + (f" Skipped: {', '.join(skipped)} (no --checkpoint)." if skipped else "")),
        Table("Cost against lit valid pixels (exact footprints)", ["pattern", "lit pixels", "lit fraction", "time (s)", "time fraction"],
              [[r["pattern"], r["lit_pixels"], r["lit_fraction"], r["seconds"], r["time_fraction"]] for r in lit]),
        Table("Splat throughput against dense matmul", ["kernel", "time (s)", "GFLOP/s", "ratio to matmul"],
              [[s["method"], s["seconds"], s["flops"] / 1e9, s["ratio_to_matmul"]] for s in splats],
              note=f"Dense float32 matmul measured in the same run: {peak / 1e9:.1f} GFLOP/s."),
    ]
    result = {"machine": machine_info(), "objects": list(objects), "work_precision": rows, "cost_vs_lit": lit,
              "splat": splats, "matmul_flops": peak, "figure": str(figure), "skipped": skipped}
    write_bench_report(result, tables, out, md=out.with_suffix(".md"), title="Relighting: error against run time")
    return result
