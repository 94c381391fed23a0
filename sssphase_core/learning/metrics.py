"""Image-quality figures shared by every evaluation (SSIM comes from kornia, LPIPS from ``lpips``)."""

from __future__ import annotations

import numpy as np

#: The smallest MSE a training log records (a PSNR of 200 dB at data range 1): JSON has no infinity.
MSE_FLOOR = 1e-20


def psnr(mse: float | np.ndarray, data_range: float = 1.0) -> float | np.ndarray:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range^2 / mse)``; inf where ``mse`` is 0."""
    m = np.asarray(mse, np.float64)
    with np.errstate(divide="ignore"):
        out = 10 * np.log10(data_range**2 / m)
    return float(out) if out.ndim == 0 else out
