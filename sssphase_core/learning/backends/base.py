"""The model-backend protocol shared by built-in and third-party backends.

A backend turns PSP observations into per-pixel footprints. ``predict_footprints`` accepts either
(N, 24, K, K) PSP patches or a (psp (8, H, W, 3), pixels (N, 2) int (y, x)) pair and returns
(N, K, K, 3) float32 footprints in linear camera units. ``pretrain``/``fit`` train whatever the
backend learns (no-ops for a physics baseline). A backend that reads only a small window of each patch
may say so with an ``input_patch`` attribute (S < K; e.g. the analytic model's 5): relighting then gives it
(N, 24, S, S) patches. One that sets ``accepts_tensors = True`` is given them as torch tensors cropped on its
``device`` (the torch backend: a 1080p view's patches are not built on the host) and returns their footprints as a
tensor there (a GPU relight's footprints stay on the GPU). This module does not import torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from sssphase_core.errors import InputError

if TYPE_CHECKING:
    from sssphase_core.learning.data import ViewData

Query = np.ndarray | tuple[np.ndarray, np.ndarray]


@runtime_checkable
class FootprintBackend(Protocol):
    name: str
    patch: int

    def pretrain(self, views: Sequence[ViewData], out_dir: Path, **options: object) -> Path | None: ...

    def fit(self, views: Sequence[ViewData], out_dir: Path, **options: object) -> Path | None: ...

    def predict_footprints(self, query: Query) -> np.ndarray: ...


def as_patches(query: Query, patch: int) -> np.ndarray:
    """(N, 24, K, K) float32 patches from either form of a query."""
    if isinstance(query, tuple):
        from sssphase_core.learning.data import psp_patches

        psp, pixels = query
        return psp_patches(np.asarray(psp, np.float32), np.asarray(pixels), patch)
    q = np.asarray(query, np.float32)
    if q.ndim != 4 or q.shape[1] != 24 or q.shape[2] != q.shape[3]:
        raise InputError(f"PSP patches must be (N, 24, K, K), got {q.shape}")
    return q


def centre_window(patches: object, size: int) -> np.ndarray:
    """(N, C, size, size) NumPy: the window of ``size`` around each (N, C, K, K) patch's centre pixel (K // 2), of
    NumPy patches or of torch tensors on any device (only the window is copied to the host); patches smaller than
    ``size`` as they are (an estimate refuses them, naming the sizes)."""
    k = patches.shape[-1]  # type: ignore[attr-defined]
    if k < size:
        win = patches
    else:
        c, h = k // 2, size // 2
        win = patches[:, :, c - h:c + h + 1, c - h:c + h + 1]  # type: ignore[index]
    return win.cpu().numpy() if hasattr(win, "cpu") else np.asarray(win)
