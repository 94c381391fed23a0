"""Which part of a model's footprints costs it the relit image: energy, radial profile or angular detail.

    python benchmarks/footprint_parts.py SESSION [--checkpoint C] [--view 0]

For one view of a *simulated* session with reference patterns (``sss capture ... --reference NAME``), each model's
footprints (the analytic model's, and the decoder's with ``--checkpoint``) are relit beside the simulator's exact
ones (ground truth, for evaluation only) and beside hybrids that take one part from the model and the rest from the
truth, or from the other model:

* ``M energy``: the exact footprints scaled to the model's energy per colour (the model's energy, the true shape);
* ``M shape``: the model's footprints scaled to the exact energy;
* ``M ring profile``: the exact footprints' angular detail on the model's ring profile (each 1 px ring's mean light),
  and ``M angular detail`` the converse;
* with a decoder: ``torch angular detail, analytic ring profile``.

Every source goes through ``sss relight``'s own pipeline (:func:`~sssphase_core.relight.pipeline.relight_view`,
calibrated as ``sss relight`` calibrates, and uncalibrated); PSNR (dB) against the simulator's render of each
reference pattern on the decoded mask / >= 2 px inside it, averaged over the patterns, then the margin over the
analytic model. Prints Markdown. (`sss bench gap` swaps a model's parts for the truth's too, on the images relit
without the white-consistent gain and its per-pixel fit; this script goes through ``sss relight``'s own pipeline and
sets two models' ring profiles and angular detail against each other.)
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sssphase_core.bench.gap_bench import hybrid, ring_average

Hybrid = Callable[[dict[str, np.ndarray]], np.ndarray]


def with_energy(fp: np.ndarray, of: np.ndarray) -> np.ndarray:
    """(N, K, K, 3) ``fp`` scaled per footprint and colour to the energy of ``of`` (N, K, K, 3)."""
    return hybrid("energy", of, fp)


def with_profile(fp: np.ndarray, of: np.ndarray) -> np.ndarray:
    """(N, K, K, 3) ``fp``'s angular detail on the ring profile of ``of``: ``fp`` times ``of``'s ring means over its own."""
    mine, theirs = ring_average(fp), ring_average(of)
    return fp * np.where(mine > 0, theirs / np.where(mine > 0, mine, 1.0), 0.0)


def hybrids(models: list[str]) -> dict[str, Hybrid]:
    """The sources to relight, each a function of {name: (N, K, K, 3) footprints} with ``exact`` among them."""
    out: dict[str, Hybrid] = {"exact": lambda f: f["exact"]}
    for m in models:
        out[m] = lambda f, m=m: f[m]
        out[f"{m} energy"] = lambda f, m=m: with_energy(f["exact"], f[m])
        out[f"{m} shape"] = lambda f, m=m: with_energy(f[m], f["exact"])
        out[f"{m} ring profile"] = lambda f, m=m: with_profile(f["exact"], f[m])
        out[f"{m} angular detail"] = lambda f, m=m: with_profile(f[m], f["exact"])
    if {"analytic", "torch"} <= set(models):
        out["torch angular detail, analytic ring profile"] = lambda f: with_profile(f["torch"], f["analytic"])
    return out


def main() -> None:
    from sssphase_core.learning.metrics import psnr
    from sssphase_core.relight.backends import make_source
    from sssphase_core.relight.evaluation import edge_band
    from sssphase_core.relight.pipeline import relight_view
    from sssphase_core.relight.views import load_view
    from sssphase_core.store.session import Session

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--view", type=int, default=0)
    a = ap.parse_args()
    rv = load_view(Session.open(a.session), a.view)
    if rv.sim is None or not rv.references:
        raise SystemExit(f"{a.session}: a simulated session with reference patterns is needed (exact footprints)")
    names = sorted(rv.references)
    patterns, truth = [rv.references[n] for n in names], [rv.captured[n] for n in names]
    mask = rv.proj.mask
    inner = mask & ~edge_band(mask)
    models = ["analytic", *(["torch"] if a.checkpoint else [])]
    sources = {n: make_source(n, rv, checkpoint=a.checkpoint, calibrate=False) for n in ["exact", *models]}
    k = max(p for _, p in sources.values())
    cache: dict[bytes, dict[str, np.ndarray]] = {}

    def footprints(px: np.ndarray) -> dict[str, np.ndarray]:
        key = np.asarray(px).tobytes()
        if key not in cache:  # every source's footprints at these pixels, zero-padded to one size, kept for every
            cache[key] = {}  # hybrid (a CPU-preset view's ~10,000 pixels: ~0.5 GB)
            for n, (src, p) in sources.items():
                f = src(px)
                f = np.asarray(f.detach().cpu() if hasattr(f, "detach") else f, np.float32)
                pad = (k - p) // 2
                cache[key][n] = np.pad(f, ((0, 0), (pad, k - p - pad), (pad, k - p - pad), (0, 0)))
        return cache[key]

    def score(images: np.ndarray) -> tuple[float, float]:
        d = [np.nan_to_num(i.astype(np.float64)) - t for i, t in zip(images, truth, strict=True)]
        return (float(np.mean([psnr(float(np.mean(x[mask] ** 2)), 1.0) for x in d])),
                float(np.mean([psnr(float(np.mean(x[inner] ** 2)), 1.0) for x in d])))

    rows = {}
    for label, part in hybrids(models).items():
        source = lambda px, part=part: part(footprints(px))  # noqa: E731
        rows[label] = [score(relight_view(source, k, rv, patterns, calibrate=cal)[0]) for cal in (True, False)]
    base = rows["analytic"]
    print(f"{rv.object} view {rv.view}, patterns {', '.join(names)}: PSNR (dB) against the render, whole mask / "
          "inside, mean over the patterns (margin over the analytic model)\n")
    print("| source | calibrated (`sss relight`) | uncalibrated |\n|---|---|---|")
    for label, cells in rows.items():
        print(f"| {label} | " + " | ".join(f"{w:.2f} / {i:.2f} ({w - b[0]:+.2f} / {i - b[1]:+.2f})"
                                           for (w, i), b in zip(cells, base, strict=True)) + " |")


if __name__ == "__main__":
    main()
