"""Ground-truth footprints from dot-grid captures (numpy only).

Dot-grid frame ``(sx, sy)`` lights projector pixels ``(sx + i*s, sy + j*s)``. A camera pixel p whose
rounded projector coordinate is one of them receives light in that frame, so the ``K x K`` crop of
the frame centred on p is p's footprint (spacing large enough that neighbouring dots' footprints do
not overlap). Frames arrive one at a time; only the crops are kept.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from sssphase_core.errors import InputError


class DotGridExtractor:
    """Collects the ``K x K x C`` footprint of every valid camera pixel from streamed dot-grid frames.

    ``xp, yp, mask``: the correspondence maps ``(H, W)``; ``spacing``: dot spacing s in projector
    pixels; ``patch``: K. Crops are centred on the pixel (index ``K // 2``) and zero-padded at the
    image border. Storage is preallocated lazily (``np.zeros``) as ``(N, K, K, C)`` ``dtype``.
    """

    def __init__(
        self,
        xp: np.ndarray,
        yp: np.ndarray,
        mask: np.ndarray,
        spacing: int,
        patch: int,
        *,
        channels: int = 3,
        dtype: np.dtype = np.float32,
    ) -> None:
        if xp.shape != yp.shape or xp.shape != mask.shape or xp.ndim != 2:
            raise InputError(f"xp, yp and mask must share one (H, W) shape, got {xp.shape}, {yp.shape}, {mask.shape}")
        if spacing < 1 or patch < 1:
            raise InputError(f"spacing and patch must be >= 1, got {spacing}, {patch}")
        self.shape, self.spacing, self.patch, self.channels = xp.shape, int(spacing), int(patch), int(channels)
        valid = mask & np.isfinite(xp) & np.isfinite(yp)
        ys, xs = np.nonzero(valid)
        self.pixels = np.stack([ys, xs], axis=1).astype(np.int64)
        rx = np.floor(xp[ys, xs].astype(np.float64) + 0.5).astype(np.int64)
        ry = np.floor(yp[ys, xs].astype(np.float64) + 0.5).astype(np.int64)
        inside = (rx >= 0) & (ry >= 0)
        # shift index of the frame that lights each pixel (-1: never lit)
        self._shift = np.where(inside, (ry % spacing) * spacing + rx % spacing, -1)
        order = np.argsort(self._shift, kind="stable")
        bounds = np.searchsorted(self._shift[order], np.arange(spacing * spacing + 1))
        self._groups = [order[bounds[i] : bounds[i + 1]] for i in range(spacing * spacing)]
        self._footprints = np.zeros((len(ys), patch, patch, channels), dtype)
        self._lit = np.zeros(len(ys), bool)

    def add(self, shift_x: int, shift_y: int, frame: np.ndarray) -> int:
        """Crop the footprints lit by dot-grid frame ``(shift_x, shift_y)``; returns how many were stored."""
        s = self.spacing
        if not (0 <= shift_x < s and 0 <= shift_y < s):
            raise InputError(f"dot-grid shift ({shift_x}, {shift_y}) outside [0, {s})")
        frame = frame[..., None] if frame.ndim == 2 else frame
        if frame.shape != (*self.shape, self.channels):
            raise InputError(f"dot-grid frame must be {(*self.shape, self.channels)}, got {frame.shape}")
        idx = self._groups[shift_y * s + shift_x]
        if len(idx) == 0:
            return 0
        k, half = self.patch, self.patch // 2
        ys, xs = self.pixels[idx, 0], self.pixels[idx, 1]
        y0, y1 = ys.min(), ys.max()
        x0, x1 = xs.min(), xs.max()
        # pad only the bounding box of the pixels lit by this frame
        region = np.zeros((y1 - y0 + k, x1 - x0 + k, self.channels), frame.dtype)
        sy0, sx0 = max(0, y0 - half), max(0, x0 - half)
        sy1, sx1 = min(self.shape[0], y1 - half + k), min(self.shape[1], x1 - half + k)
        region[sy0 - (y0 - half) : sy1 - (y0 - half), sx0 - (x0 - half) : sx1 - (x0 - half)] = frame[sy0:sy1, sx0:sx1]
        windows = sliding_window_view(region, (k, k), axis=(0, 1))  # (h, w, C, K, K)
        self._footprints[idx] = windows[ys - y0, xs - x0].transpose(0, 2, 3, 1)
        self._lit[idx] = True
        return len(idx)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (N, 2) int yx, footprints (N, K, K, C))`` of the pixels lit so far."""
        if self._lit.all():
            return self.pixels, self._footprints
        return self.pixels[self._lit], self._footprints[self._lit]

    def missing(self) -> np.ndarray:
        """Valid pixels ``(M, 2)`` yx that no added frame has lit yet."""
        return self.pixels[~self._lit]
