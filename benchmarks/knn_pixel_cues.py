"""How far six numbers per pixel separate the demo's training objects (issue 42, item 4): a baseline for its kNN.

    python benchmarks/knn_pixel_cues.py DEMO_OUT

``DEMO_OUT`` is a finished ``sss demo --out DEMO_OUT``. Each of the demo's kNN pixels (its training sessions, the
same 400 pixels per view) is described, with no training, by the chromaticity of its PSP offset A (3 numbers) and each
colour's modulation over offset B / A averaged over the two fringe orientations (3 numbers), standardised; then the
demo's kNN (k = 20, cosine, majority vote, view-level leave-one-out). Prints the overall and per-object accuracy and
the confusion matrix (rows: true object).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sssphase_core.learning.data import PatchDataset, session_views
from sssphase_core.learning.evaluation import knn_leave_one_view_out
from sssphase_core.learning.models import get_preset
from sssphase_core.reporting.demo import PRESETS


def pixel_cues(psp: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(8, H, W, 3) PSP stack, (N, 2) pixels -> (N, 6): offset chromaticity and per-colour B / A."""
    s = psp[:, pixels[:, 0], pixels[:, 1], :].astype(np.float64)  # (8, N, 3)
    offset = s.mean(axis=0)

    def modulation(four: np.ndarray) -> np.ndarray:
        return 0.5 * np.hypot(four[0] - four[2], four[1] - four[3])

    b = 0.5 * (modulation(s[:4]) + modulation(s[4:]))
    chroma = offset / np.maximum(offset.sum(axis=1, keepdims=True), 1e-9)
    return np.concatenate([chroma, b / np.maximum(offset, 1e-6)], axis=1)  # float64: psp.modulation_ratio rounds to float32


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path)
    args = ap.parse_args()
    c = PRESETS["lite"]
    objects = list(c.train_objects)
    views = session_views(args.demo / "sessions" / "train", objects, pixels_per_view=c.pixels_per_view, seed=c.seed)
    labels = PatchDataset(views, get_preset(c.model).patch, objects)
    obj, view = labels.labels("object"), labels.labels("view")
    cues = np.concatenate([pixel_cues(v.psp, v.pixels) for v in views])
    cues = (cues - cues.mean(axis=0)) / cues.std(axis=0)
    res = knn_leave_one_view_out(cues, obj, view, k=20, class_names=objects)
    print(f"kNN of six per-pixel cues: {100 * res['overall']:.2f}%")
    print("  " + ", ".join(f"{name} {100 * acc:.1f}%" for name, acc in res["per_class"].items()))
    confusion = np.zeros((len(objects), len(objects)), int)
    np.add.at(confusion, (obj, res["pred"]), 1)
    for name, row in zip(objects, confusion, strict=True):
        print(f"  {name:>8s}: {' '.join(f'{n:5d}' for n in row)}")


if __name__ == "__main__":
    main()
