"""The demo's pretraining and kNN over several seeds and decorrelation weights (issue 42, item 4).

    python benchmarks/pretrain_seeds.py DEMO_OUT [--seeds 0,1,2,3] [--decorrelate 0,1] [--out runs_dir]

``DEMO_OUT`` is a finished ``sss demo --out DEMO_OUT``. Each run pretrains as the demo does (its ``lite`` preset:
``PretrainConfig(epochs=2, batch_size=32, warmup_epochs=1)`` on the same 4,000 patches of its training sessions)
with one seed and one ``decorrelate`` weight, on one CPU thread, then measures the demo's kNN (k = 20, view-level
leave-one-out on those patches). One JSON line per run: the final kNN, its apple class, the per-epoch monitor and
the embeddings' effective rank. Run two at once on a 2-core machine (``--seeds 0,1`` and ``--seeds 2,3``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from sssphase_core.learning.backends import get_backend
from sssphase_core.learning.data import session_views
from sssphase_core.learning.evaluation import knn_of_views
from sssphase_core.learning.training import load_encoder
from sssphase_core.reporting.demo import PRESETS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path)
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--decorrelate", default="0,1")
    ap.add_argument("--out", type=Path, default=Path("pretrain_seeds"))
    ap.add_argument("--pixels-per-view", type=int, default=None, help="training patches per view (default: the demo's)")
    ap.add_argument("--epochs", type=int, default=None, help="default: the demo's")
    ap.add_argument("--warmup-epochs", type=float, default=None, help="default: the demo's")
    ap.add_argument("--lr", type=float, default=None, help="default: the demo's")
    ap.add_argument("--no-phase-shift", action="store_true", help="the strong view without the fringes' phase move")
    args = ap.parse_args()
    torch.set_num_threads(1)
    c = PRESETS["lite"]
    views = session_views(args.demo / "sessions" / "train", c.train_objects, pixels_per_view=c.pixels_per_view,
                          footprints=False, seed=c.seed)  # the demo's kNN patches
    train = views if args.pixels_per_view is None else session_views(
        args.demo / "sessions" / "train", c.train_objects, pixels_per_view=args.pixels_per_view, footprints=False,
        seed=c.seed)
    changes = {k: v for k, v in (("epochs", args.epochs), ("warmup_epochs", args.warmup_epochs), ("lr", args.lr))
               if v is not None} | ({"phase_shift": False} if args.no_phase_shift else {})
    for weight in (float(w) for w in args.decorrelate.split(",")):
        for seed in (int(s) for s in args.seeds.split(",")):
            cfg = c.pretrain_config(seed=seed, decorrelate=weight, **changes)
            run = args.out / f"seed{seed}_decorrelate{weight:g}"
            t0 = time.perf_counter()
            path = get_backend("torch").pretrain(train, run, config=cfg, progress=False)
            knn = knn_of_views(load_encoder(path), views, list(c.train_objects), ks=(20,))[20]
            rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
            print(json.dumps({"seed": seed, "decorrelate": weight, "knn": round(100 * knn["overall"], 1),
                              "apple": round(100 * knn["per_class"]["apple"], 1),
                              "monitor": [round(100 * r["knn_acc"], 1) for r in rows],
                              "eff_rank": [round(r["eff_rank"], 1) for r in rows],
                              "seconds": round(time.perf_counter() - t0)}), flush=True)


if __name__ == "__main__":
    main()
