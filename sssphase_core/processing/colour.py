"""Linear camera values to display values: the sRGB encoding and an exposure for display."""

from __future__ import annotations

import numpy as np


def srgb(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def display_scale(image: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.5) -> float:
    """Exposure that maps the ``percentile`` of the (masked) image to display white."""
    vals = image[mask] if mask is not None and mask.any() else image
    return float(max(np.percentile(np.nan_to_num(vals), percentile), 1e-6))
