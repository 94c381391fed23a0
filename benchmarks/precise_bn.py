"""The demo's kNN of pretraining runs with their saved BatchNorm statistics and with precise ones (issue 42, item 4).

    python benchmarks/precise_bn.py DEMO_OUT RUN [RUN ...]

``DEMO_OUT`` is a finished ``sss demo --out DEMO_OUT``; each ``RUN`` a pretraining run folder (``last.pt``), e.g.
``DEMO_OUT/runs/pretrain`` or those of ``benchmarks/pretrain_seeds.py`` (seed from the folder's ``seedN_`` name).
Runs made before pretraining recomputed the statistics at each epoch's end hold torch's exponential averages; for
runs made since, both figures are equal (the recomputation is the same). One JSON line per run: the demo's kNN
(k = 20, view-level leave-one-out on its 4,000 patches) and its apple class, before and after.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import torch

from sssphase_core.learning.data import PatchDataset, session_views
from sssphase_core.learning.evaluation import knn_of_views
from sssphase_core.learning.training import load_encoder
from sssphase_core.learning.training.pretrain import PRECISE_BN_PATCHES, precise_batchnorm
from sssphase_core.reporting.demo import PRESETS


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    c = PRESETS["lite"]
    objects = list(c.train_objects)
    views = session_views(Path(sys.argv[1]) / "sessions" / "train", c.train_objects, pixels_per_view=c.pixels_per_view,
                          footprints=False, seed=c.seed)
    for run in map(Path, sys.argv[2:]):
        encoder = load_encoder(run / "last.pt")
        saved = knn_of_views(encoder, views, objects, ks=(20,))[20]
        seed = int(m.group(1)) if (m := re.match(r"seed(\d+)", run.name)) else c.seed
        precise_batchnorm(encoder, PatchDataset(views, encoder.preset.patch, objects), PRECISE_BN_PATCHES,
                          c.pretrain_batch, seed, torch.device("cpu"))
        precise = knn_of_views(encoder, views, objects, ks=(20,))[20]
        print(json.dumps({"run": str(run), "knn_saved": round(100 * saved["overall"], 2),
                          "apple_saved": round(100 * saved["per_class"]["apple"], 1),
                          "knn_precise_bn": round(100 * precise["overall"], 2),
                          "apple_precise_bn": round(100 * precise["per_class"]["apple"], 1)}), flush=True)


if __name__ == "__main__":
    main()
