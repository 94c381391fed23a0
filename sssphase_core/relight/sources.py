"""Footprint sources: where each lit pixel's (K, K, 3) footprint comes from: no scattering, a model
backend's predictions from the PSP patches, the captured dot-grid crops (:func:`nearest_measured_source`).
Which source a backend name gives a view: :mod:`~sssphase_core.relight.backends`; the captured light
transport: :mod:`~sssphase_core.relight.transport`."""

from __future__ import annotations

import numpy as np
import torch

from sssphase_core.errors import InputError
from sssphase_core.relight.engine import FootprintSource


def no_scattering_source(white: np.ndarray, patch: int = 1) -> FootprintSource:
    """The no-scattering baseline: a delta footprint carrying the pixel's white-image value
    (``patch`` 1 splats it at no cost; a larger patch gives the same image)."""
    img = np.asarray(white, np.float32)
    img = np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img

    def source(pixels: np.ndarray) -> np.ndarray:
        fp = np.zeros((len(pixels), patch, patch, 3), np.float32)
        fp[:, patch // 2, patch // 2] = np.nan_to_num(img[pixels[:, 0], pixels[:, 1]])
        return fp

    return source


def backend_source(backend: object, psp: np.ndarray, chunk: int = 256) -> FootprintSource:
    """Footprints predicted by a model backend from the (N, 24, S, S) PSP patches of the asked pixels,
    cropped from the view's stack padded once (a 1080p stack is 200 MB) and given to
    ``predict_footprints`` ``chunk`` at a time (a K = 90 patch is 0.8 MB, and backends work on copies).
    S is the backend's ``input_patch`` where it reads less than its footprint's K x K (the analytic model:
    a 5 x 5 window; cropping K = 90 patches for it took 160 of the 323 s of a 1080p relight), else K. A backend
    that ``accepts_tensors`` (torch) gets them as tensors cropped on its ``device``, the stack moved there once."""
    from sssphase_core.learning.data import crop_patches, pad_for_patches, to_channels_first

    k = int(backend.patch)  # type: ignore[attr-defined]
    size = int(getattr(backend, "input_patch", k))
    stack = pad_for_patches(to_channels_first(np.asarray(psp, np.float32)), size)
    as_tensors = bool(getattr(backend, "accepts_tensors", False))
    if as_tensors:  # the stack goes to the model's device once and patches are cropped there (a 1080p view's
        stack = stack.to(getattr(backend, "device", "cpu"))  # K = 90 patches are 141 GB to crop and copy)

    def patches(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        crops = crop_patches(stack, pixels, size, padded=True)
        return crops if as_tensors else crops.numpy()

    def predicted(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        fp = backend.predict_footprints(patches(pixels))  # type: ignore[attr-defined]
        if tuple(fp.shape) != (len(pixels), k, k, 3):  # (a plugin's: named, not "the footprint source")
            kind = type(backend)
            raise InputError(f"model backend {kind.__name__} ({kind.__module__}) returned footprints of shape "
                             f"{tuple(fp.shape)} for {len(pixels)} pixels: expected ({len(pixels)}, {k}, {k}, 3) "
                             "(its patch is K)")
        return fp

    def source(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        parts = [predicted(pixels[i:i + chunk]) for i in range(0, len(pixels), chunk)]
        if not parts:
            return np.zeros((0, k, k, 3), np.float32)
        if len(parts) == 1:  # (a backend's footprints are its own new array: no copy)
            return parts[0]
        if torch.is_tensor(parts[0]):
            return torch.cat(parts)
        return np.concatenate(parts)

    return source


WHITE_FLOOR = 1e-3  # white values below this (linear camera units) are noise: no ratio is taken


def nearest_measured_source(pixels: np.ndarray, crops: np.ndarray, white: np.ndarray,
                            weights: np.ndarray | None = None) -> FootprintSource:
    """Captured footprints (dot-grid crops ``(N, K, K, 3)`` at ``pixels`` ``(N, 2)`` yx), each times its
    ``weights`` entry (``(N,)``, default 1): a pixel with its own crop gets it; any other pixel takes
    its nearest captured footprint, rescaled by the ratio of their white-image values (only where
    both are above the noise floor, at most 4x)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(pixels, np.float64))
    img = np.asarray(white, np.float32)
    img = np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img
    px_ref = np.asarray(pixels, np.int64)
    fps = np.asarray(crops, np.float32)  # read once: every relit pixel needs its crop
    if weights is not None:
        fps = fps * np.asarray(weights, np.float32)[:, None, None, None]

    def source(query: np.ndarray) -> np.ndarray:
        query = np.asarray(query, np.int64)
        _, idx = tree.query(query.astype(np.float64))
        wq, wr = img[query[:, 0], query[:, 1]], img[px_ref[idx, 0], px_ref[idx, 1]]
        ratio = np.where(wr > WHITE_FLOOR, np.clip(wq / np.maximum(wr, WHITE_FLOOR), 0.0, 4.0), 1.0)
        ratio[(px_ref[idx] == query).all(axis=1)] = 1.0
        return fps[idx] * ratio[:, None, None, :]

    return source
