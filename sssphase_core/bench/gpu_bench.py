"""``sss bench gpu``: the accelerator path measured in one command, rerunnable on any GPU.

1. **Training**: the loops users run (:func:`~sssphase_core.learning.training.pretrain`, then
   :func:`~sssphase_core.learning.training.train_decoder` on that encoder) for a fixed number of steps at the
   preset's patch size, with mixed precision (bf16 autocast on CUDA): patches/s, peak device memory,
   the loss per epoch (finite, and falling from the first epoch to the last).
2. **Agreement**: one fixed batch through the trained encoder + decoder on the CPU (float32) and on
   the device (float32, and bf16 autocast): max |difference| relative to the CPU output's peak.
3. **Relighting**: one view relit on the device with the ``index`` and ``fold`` splats against the
   CPU's ``csc``: time and max relative difference.
4. **DDP**: ``torchrun --nproc_per_node=G`` with NCCL when G >= 2 GPUs are visible; with fewer it is
   recorded as skipped, with the reason (DDP over gloo on the CPU is exercised by the test suite).

The data are synthetic flat views (``bench.synthetic.synthetic_views``: fringes blurred by a known kernel), so the
command needs no session and no network; the figures measure the device, not accuracy.
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sssphase_core.compute import compute_device
from sssphase_core.errors import InputError

OBJECTS = ("a", "b", "c")
VIEWS = (0, 1)


def _dataset(patch: int, patches: int, seed: int = 0):
    from sssphase_core.bench.synthetic import synthetic_views
    from sssphase_core.learning.data import PatchDataset

    per_view = -(-patches // (len(OBJECTS) * len(VIEWS)))
    side = 2 * patch + max(16, int(math.isqrt(per_view)) + 8)  # enough inner pixels for per_view samples
    views, _ = synthetic_views(OBJECTS, VIEWS, size=(side, side), patch=patch, period=8.0,
                               pixels_per_view=per_view, seed=seed)
    return PatchDataset(views, patch, list(OBJECTS), with_targets=True)


def _peak_memory(dev: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None


def _epoch_losses(run: Path, key: str) -> list[float]:
    from sssphase_core.learning.runlog import METRICS, read_rows

    return [float(r[key]) for r in read_rows(run / METRICS) if key in r]


#: the variants compared by :func:`training`: today's default (next batch built on a worker thread, patches
#: cropped on the device where the stacks fit; deterministic kernels for the decoder, not for SimSiam), the
#: plain host loader as the same-run baseline, and the default with the other kernel choice (``kernels``:
#: what determinism costs each stage).
LOADERS = {"default": {}, "host": {"prefetch": False, "stacks_on_device": False}, "kernels": {}}
LOADER_LABELS = {"default": "default", "host": "host loader (baseline)", "kernels": "other kernels"}


def training(preset: str, dev: torch.device, out: Path, *, steps: int, batch: int, epochs: int) -> dict[str, Any]:
    """Pretraining and decoder fitting for ``steps`` steps each (``epochs`` epochs, for the loss curve), once
    with each of :data:`LOADERS` (``result[stage]`` the default, ``result[stage + "_host"]`` etc. the others)."""
    from sssphase_core.learning.models import get_preset
    from sssphase_core.learning.runlog import METRICS, read_rows
    from sssphase_core.learning.training import DecoderConfig, PretrainConfig, pretrain, train_decoder

    p = get_preset(preset)
    per_epoch = max(1, steps // epochs)
    ds = _dataset(p.patch, per_epoch * batch)
    result: dict[str, Any] = {"preset": preset, "patch": p.patch, "batch": batch, "patches": len(ds)}
    for loader, options in LOADERS.items():
        pre, dec = out / f"pre_{loader}", out / ("dec" if loader == "default" else f"dec_{loader}")
        pre_cfg = PretrainConfig(preset=preset, epochs=epochs, batch_size=batch, device=str(dev), ckpt_every=0,
                                 knn_monitor=0, warmup_epochs=0.5, **options)
        dec_cfg = DecoderConfig(epochs=epochs, batch_size=batch, device=str(dev), ckpt_every=0, val_samples=0, **options)
        if loader == "kernels":
            pre_cfg = replace(pre_cfg, deterministic=not pre_cfg.deterministic)
            dec_cfg = replace(dec_cfg, deterministic=not dec_cfg.deterministic)
        result[f"deterministic_{loader}"] = {"pretrain": pre_cfg.deterministic, "decoder": dec_cfg.deterministic}
        runs = {"pretrain": partial(pretrain, pre_cfg, ds, pre, resume=False, progress=False),
                "decoder": partial(train_decoder, dec_cfg, pre, ds, dec, resume=False, progress=False)}
        for name, run in runs.items():
            if dev.type == "cuda":
                torch.cuda.reset_peak_memory_stats(dev)
                torch.cuda.synchronize(dev)
            t0 = time.perf_counter()
            run()
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            seconds = time.perf_counter() - t0
            rows = read_rows((pre if name == "pretrain" else dec) / METRICS)  # the run's epoch rows
            losses = [float(r["loss"]) for r in rows]
            n_steps = per_epoch * epochs
            result[name if loader == "default" else f"{name}_{loader}"] = {
                "steps": n_steps, "seconds": seconds, "patches_s": n_steps * batch / seconds,
                "steady_patches_s": _steady_rate(rows, per_epoch * batch), "data_wait_share": _data_wait_share(rows),
                "peak_memory_mb": _peak_memory(dev), "loss_per_epoch": losses,
                "finite": bool(losses) and all(math.isfinite(v) for v in losses),
                "falling": len(losses) > 1 and losses[-1] < losses[0]}
    return result


def _steady_rate(rows: list[dict[str, Any]], patches_per_epoch: int) -> float:
    """Patches/s of the training loop after its first epoch (which pays for warm-up: kernel selection, caches),
    from the run's epoch rows; NaN with a single epoch."""
    walls = [r["wall_s"] for r in rows]
    return patches_per_epoch * (len(walls) - 1) / (walls[-1] - walls[0]) if len(walls) > 1 and walls[-1] > walls[0] else float("nan")


def _data_wait_share(rows: list[dict[str, Any]]) -> float:
    """Share of the training loop's time spent waiting for batches, from the run's epoch rows."""
    return sum(r["data_wait_s"] for r in rows) / rows[-1]["wall_s"] if rows and rows[-1]["wall_s"] > 0 else float("nan")


@torch.no_grad()
def agreement(decoder_run: Path, dev: torch.device, *, batch: int = 16) -> dict[str, Any]:
    """One fixed batch on the CPU and on ``dev``: max |difference| / peak of the CPU output."""
    from sssphase_core.learning.training import FootprintNet, load_decoder

    enc, dec = load_decoder(decoder_run)
    net = FootprintNet(enc, dec).eval()
    ds = _dataset(enc.preset.patch, batch, seed=1)
    psp = ds.batch(np.arange(min(batch, len(ds))))["psp"]
    ref_fp, _ = net(psp)
    ref_z = enc(psp)
    net_d = net.to(dev)
    rows: dict[str, Any] = {}
    for label, amp in (("float32", False), ("bf16 autocast", True)):
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp and dev.type == "cuda"):
            fp, _ = net_d(psp.to(dev))
            z = net_d.encoder(psp.to(dev))
        rows[label] = {"footprint": float((fp.float().cpu() - ref_fp).abs().max() / ref_fp.abs().max().clamp_min(1e-12)),
                       "embedding": float((z.float().cpu() - ref_z).abs().max() / ref_z.abs().max().clamp_min(1e-12)),
                       "autocast": amp and dev.type == "cuda"}
    net.to("cpu")
    return rows


def relighting(dev: torch.device, *, size: int = 192, patch: int = 31, n_patterns: int = 2) -> dict[str, Any]:
    """A flat view relit on ``dev`` (index, fold) against the CPU csc splat: time and max relative difference."""
    from sssphase_core.relight import Projection, relight

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size, :size].astype(np.float32)
    mask = (yy - size / 2) ** 2 + (xx - size / 2) ** 2 < (0.45 * size) ** 2
    proj = Projection(np.where(mask, xx, np.nan), np.where(mask, yy, np.nan), mask, (size, size), gamma=1.0)
    r = np.hypot(*np.mgrid[:patch, :patch] - patch // 2)
    fp = np.exp(-r / 3.0)[..., None] * np.array([0.5, 0.3, 0.2]) / np.exp(-r / 3.0).sum()
    fp = fp.astype(np.float32)
    pats = rng.random((n_patterns, size, size)).astype(np.float32)

    def source(px: np.ndarray) -> np.ndarray:
        return np.broadcast_to(fp, (len(px), *fp.shape))

    t0 = time.perf_counter()
    ref = relight(source, proj, pats, patch, method="csc")
    rows: dict[str, Any] = {"camera": f"{size}x{size}", "patch": patch, "lit_pixels": int(mask.sum()),
                            "csc_cpu_s": time.perf_counter() - t0}
    for method in ("index", "fold"):
        relight(source, proj, pats, patch, method=method, device=str(dev))  # warm-up (kernels, allocator)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t0 = time.perf_counter()
        out = relight(source, proj, pats, patch, method=method, device=str(dev))
        rows[method] = {"seconds": time.perf_counter() - t0, "max_rel_diff": float(np.abs(out - ref).max() / np.abs(ref).max())}
    return rows


DDP_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    import torch
    from sssphase_core.bench.gpu_bench import _dataset
    from sssphase_core.learning.training import PretrainConfig, pretrain

    out, preset, batch, steps = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    from sssphase_core.learning.models import get_preset
    world = torch.distributed.get_world_size() if torch.distributed.is_initialized() else int(__import__("os").environ["WORLD_SIZE"])
    ds = _dataset(get_preset(preset).patch, steps * batch * world)
    pretrain(PretrainConfig(preset=preset, epochs=1, batch_size=batch, device="cuda", ckpt_every=0, knn_monitor=0),
             ds, out, resume=False, progress=False)
    """
)


def ddp(preset: str, out: Path, *, steps: int, batch: int) -> dict[str, Any]:
    """torchrun with one process per visible GPU (NCCL); skipped below two GPUs."""
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if gpus < 2:
        return {"skipped": f"{gpus} GPU(s) visible: NCCL DDP needs at least 2 (gloo DDP on the CPU is in the test suite)"}
    script = out / "ddp_run.py"
    script.write_text(DDP_SCRIPT)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(gpus),
                           str(script), str(out / "ddp"), preset, str(batch), str(steps)], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"gpus": gpus, "failed": proc.stderr[-2000:]}
    losses = _epoch_losses(out / "ddp", "loss")
    return {"gpus": gpus, "seconds": seconds, "patches_s": steps * batch * gpus / seconds, "loss": losses}


def run(out: Path, *, device: str = "auto", preset: str = "paper", steps: int = 200, batch: int = 32,
        epochs: int = 4, relight_size: int = 192, progress: Any = None) -> dict[str, Any]:
    """The whole benchmark; returns the result (written by the caller)."""
    from sssphase_core.bench.output import machine_info

    dev = compute_device(device)
    if steps < epochs:
        raise InputError(f"--steps must be at least --epochs ({epochs}), got {steps}")
    result: dict[str, Any] = {"machine": machine_info(), "device": str(dev),
                              "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU",
                              "torch": torch.__version__}
    with tempfile.TemporaryDirectory(prefix="sss-gpu-") as tmp:
        work = Path(tmp)
        for name, step in (("flops", lambda: flops(preset, dev, result["device_name"])),
                           ("training", lambda: training(preset, dev, work, steps=steps, batch=batch, epochs=epochs)),
                           ("agreement", lambda: agreement(work / "dec", dev)),
                           ("relight", lambda: relighting(dev, size=relight_size)),
                           ("ddp", lambda: ddp(preset, work, steps=max(1, steps // epochs), batch=batch))):
            if progress:
                progress(name)
            result[name] = step()
    return result


def flops(preset: str, dev: torch.device, device_name: str) -> dict[str, Any]:
    """Model FLOPs per training patch of both stages (counted on one step) and the device's bf16 peak: the
    datasheet's and a dense matrix product's measured in this run (the baseline MFU is read against)."""
    from sssphase_core.learning.flops import datasheet_peak, measured_matmul_peak, training_flops_per_patch

    return {"pretrain": training_flops_per_patch(preset, "pretrain"), "decoder": training_flops_per_patch(preset, "decoder"),
            "datasheet_peak": datasheet_peak(device_name), "matmul_peak": measured_matmul_peak(dev)}


def mfu_lines(r: dict[str, Any]) -> list[str]:
    """The model-FLOPs utilisation of each stage's default run (patches/s after epoch 1) against both peaks."""
    f, t = r.get("flops"), r["training"]
    if not f:
        return []
    lines = ["", "| stage | model GFLOP per patch (one step) | TFLOP/s reached | of the datasheet's bf16 peak | of a bf16 "
             "matrix product measured here |", "|---|---|---|---|---|"]
    for name in ("pretrain", "decoder"):
        rate = t.get(name, {}).get("steady_patches_s", float("nan"))
        reached = f[name] * rate
        sheet = f"{reached / f['datasheet_peak']:.1%} of {f['datasheet_peak'] / 1e12:.0f}" if f.get("datasheet_peak") else "unknown device"
        lines.append(f"| {name} | {f[name] / 1e9:.1f} | {reached / 1e12:.1f} | {sheet} | "
                     f"{reached / f['matmul_peak']:.1%} of {f['matmul_peak'] / 1e12:.0f} |")
    return lines


def markdown(r: dict[str, Any]) -> str:
    t = r["training"]
    lines = [f"`sss bench gpu` on {r['device_name']} ({r['device']}), torch {r['torch']}, preset `{t['preset']}` "
             f"(K = {t['patch']}), batch {t['batch']}", "",
             "| stage | loader | steps | patches/s (all) | patches/s (after epoch 1) | waiting for data | peak device memory "
             "| loss per epoch | finite, falling |", "|---|---|---|---|---|---|---|---|---|"]
    for name in ("pretrain", "decoder"):
        for key, loader in ((name if v == "default" else f"{name}_{v}", label) for v, label in LOADER_LABELS.items()):
            if key not in t:
                continue
            s = t[key]
            mem = f"{s['peak_memory_mb']:,.0f} MB" if s["peak_memory_mb"] is not None else "n/a (CPU)"
            lines.append(f"| {name} | {loader} | {s['steps']} | {s['patches_s']:.1f} | {s.get('steady_patches_s', float('nan')):.1f} | "
                         f"{s.get('data_wait_share', float('nan')):.0%} | "
                         f"{mem} | {' → '.join(f'{v:.4g}' for v in s['loss_per_epoch'])} | {s['finite']}, {s['falling']} |")
    ratios = [f"{name} {t[name]['steady_patches_s'] / t[name + '_host']['steady_patches_s']:.2f}×"
              for name in ("pretrain", "decoder") if name + "_host" in t]
    if ratios:
        lines += ["", "Default loader against the host loader (patches/s after epoch 1), same run: " + ", ".join(ratios) + "."]
    if "deterministic_kernels" in t:
        det = t["deterministic_default"]
        costs = []
        for name in ("pretrain", "decoder"):
            fast, slow = (name + "_kernels", name) if det[name] else (name, name + "_kernels")
            costs.append(f"{name} {t[slow]['steady_patches_s'] / t[fast]['steady_patches_s']:.2f}× "
                         f"({'default' if det[name] else 'other'})")
        same = {name: t[name]["loss_per_epoch"] == t[name + "_host"]["loss_per_epoch"] for name in ("pretrain", "decoder")}
        lines += ["", "Deterministic kernels against CUDA's default ones (patches/s after epoch 1), same run: "
                  + ", ".join(costs) + ". Loss per epoch identical with the host loader (same batches and kernels, "
                  "other cropping): " + ", ".join(f"{k} {v}" for k, v in same.items()) + "."]
    lines += mfu_lines(r)
    lines += ["", "| CPU vs device, fixed batch | footprint max rel. diff | embedding max rel. diff |", "|---|---|---|"]
    for label, a in r["agreement"].items():
        lines.append(f"| {label}{'' if a['autocast'] or label == 'float32' else ' (not applied off CUDA)'} | "
                     f"{a['footprint']:.2e} | {a['embedding']:.2e} |")
    rl = r["relight"]
    lines += ["", f"Relighting ({rl['camera']}, K = {rl['patch']}, {rl['lit_pixels']:,} lit pixels; CPU csc "
              f"{rl['csc_cpu_s']:.2f} s):", "", "| splat | time (s) | max rel. diff to CPU csc |", "|---|---|---|"]
    for method in ("index", "fold"):
        lines.append(f"| {method} | {rl[method]['seconds']:.3f} | {rl[method]['max_rel_diff']:.2e} |")
    d = r["ddp"]
    lines += ["", "DDP (NCCL, torchrun): " + (d["skipped"] if "skipped" in d else
              f"failed: {d['failed'][-300:]}" if "failed" in d else
              f"{d['gpus']} GPUs, {d['patches_s']:.1f} patches/s, loss {d['loss']}")]
    return "\n".join(lines) + "\n"
