"""``sss bench learn`` (:func:`learn_bench`: the measurements and their tables) and its loader half: patches/s of the training loader at each preset's scale, to set next to
the model's patches/s measured in the same run.

The loader is the one training uses (:class:`sssphase_core.learning.data.PatchDataset`): PSP patches cropped on the
fly from a view-level stack held in memory (``(24, H, W)``, the preset's camera size: 256x192 for ``lite``,
1920x1080 for ``paper``) and footprint targets streamed from a chunked store on disk (written with the
session codec, read by sorted row indices), for random batches.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import numpy as np

CAMERA = {32: (256, 192), 90: (1920, 1080)}  # patch K -> the camera size of the rig preset that uses it


def loader_throughput(preset: str, *, batch: int, repeats: int = 3, footprints: int = 1024, seed: int = 0) -> dict[str, float]:
    """Patches/s of ``PatchDataset.batch`` without and with streamed footprint targets."""
    import zarr

    from sssphase_core.learning.data import PatchDataset, ViewData
    from sssphase_core.learning.models import get_preset
    from sssphase_core.store.session import _zarr_write

    k = get_preset(preset).patch
    w, h = CAMERA.get(k, (256, 192))
    rng = np.random.default_rng(seed)
    psp = rng.random((8, h, w, 3), dtype=np.float32)
    pixels = np.stack([rng.integers(0, h, footprints), rng.integers(0, w, footprints)], axis=1)
    with tempfile.TemporaryDirectory(prefix="sss-loader-") as tmp:
        _zarr_write(Path(tmp) / "crops", rng.random((footprints, k, k, 3), dtype=np.float32) * 0.01)
        store = zarr.open_array(str(Path(tmp) / "crops"), mode="r")
        view = ViewData("bench", 0, psp, pixels, np.full(footprints, -1), footprints=store)
        rates = {}
        for name, targets in (("loader_psp_patches_s", False), ("loader_patches_s", True)):
            ds = PatchDataset([view], k, ["bench"], with_targets=targets)
            ds.batch(rng.integers(0, footprints, batch))  # warm-up
            times = []
            for _ in range(repeats):
                idx = rng.integers(0, footprints, batch)
                t0 = time.perf_counter()
                ds.batch(idx)
                times.append(time.perf_counter() - t0)
            rates[name] = batch / float(np.median(times))
    return {**rates, "camera": f"{w}x{h}", "patch": k}


def measure_throughput(preset: str, *, batch: int, repeats: int = 3, device: str = "cpu") -> dict[str, float]:
    """Patches/s of footprint inference (encoder + decoder forward) and of one SimSiam training step."""
    import torch

    from sssphase_core.learning.augment import two_views
    from sssphase_core.learning.models import Decoder, SimSiam, get_preset

    p = get_preset(preset)
    torch.manual_seed(0)
    model, dec = SimSiam(p).to(device), Decoder(p).to(device).eval()
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9)
    x = torch.rand(batch, 24, p.patch, p.patch, device=device)

    def infer() -> None:
        with torch.no_grad():
            model.encoder.eval()
            dec(*model.encoder.features(x), x)

    def train_step() -> None:
        model.train()
        loss = model(*two_views(x))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()

    def rate(fn) -> float:
        fn()  # warm-up
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        return batch / float(np.median(times))

    return {"infer_patches_s": rate(infer), "train_patches_s": rate(train_step),
            "encoder_params": sum(q.numel() for q in model.encoder.parameters()),
            "decoder_params": sum(q.numel() for q in dec.parameters())}


#: The batch each preset is measured with (`sss bench learn`).
BENCH_BATCHES = {"paper": 8, "lite": 64}


def learn_bench(*, repeats: int = 3, device: str = "cpu", status: Callable[[str], AbstractContextManager[Any]] | None = None
                ) -> tuple[dict[str, dict[str, Any]], list[Any]]:
    """``sss bench learn``: each preset's inference and SimSiam-step throughput and its training loader's, with
    the tables (ratios to the paper preset measured in the same run). ``status(text)``: the context each
    measurement runs in."""
    from sssphase_core.bench.output import Table

    results = {}
    for name, batch in BENCH_BATCHES.items():
        with status(f"measuring the {name} preset (batch {batch})") if status else contextlib.nullcontext():
            results[name] = {"batch": batch, **measure_throughput(name, batch=batch, repeats=repeats, device=device),
                             **loader_throughput(name, batch=batch, repeats=repeats)}
    base = results["paper"]
    table = Table("Learning throughput (patches/s); baseline: the paper preset, same run",
                  ["preset", "batch", "encoder params", "decoder params", "inference", "x paper", "SimSiam step", "x paper"])
    loader = Table("Training loader against the model (patches/s, same run): PSP patches cropped from a view stack in "
                   "memory, footprint targets streamed from a chunked store on disk",
                   ["preset", "camera", "K", "loader, PSP only", "loader, with targets", "SimSiam step",
                    "loader / SimSiam step", "loader / inference"])
    for name, r in results.items():
        table.rows.append([name, r["batch"], f"{r['encoder_params'] / 1e6:.2f}M", f"{r['decoder_params'] / 1e6:.2f}M",
                           r["infer_patches_s"], r["infer_patches_s"] / base["infer_patches_s"],
                           r["train_patches_s"], r["train_patches_s"] / base["train_patches_s"]])
        loader.rows.append([name, r["camera"], r["patch"], r["loader_psp_patches_s"], r["loader_patches_s"], r["train_patches_s"],
                            r["loader_patches_s"] / r["train_patches_s"], r["loader_patches_s"] / r["infer_patches_s"]])
    return results, [table, loader]
