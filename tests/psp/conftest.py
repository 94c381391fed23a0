"""Synthetic fringe captures with known camera -> projector correspondence (until/besides the sim)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from sssphase_core.patterns import PSPConfig, psp_key


def affine_map(shape: tuple[int, int], scale: float = 0.9, offset: tuple[float, float] = (7.3, 4.1), shear: float = 0.05):
    """Projector coordinates (xp, yp) of each camera pixel for a slightly sheared affine view."""
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    return scale * xx + shear * yy + offset[0], scale * yy - shear * xx + offset[1] + shear * shape[1]


def render_fringes(
    config: PSPConfig,
    xp: np.ndarray,
    yp: np.ndarray,
    *,
    offset: float | np.ndarray = 0.3,
    amplitude: float | np.ndarray = 0.25,
    blur: float = 0.0,
    noise: float = 0.0,
    channels: tuple[float, ...] | None = None,
    rng: np.random.Generator | None = None,
) -> dict[str, np.ndarray]:
    """Frames ``A + B cos(2π u / P - 2πn/N)`` (u = xp or yp), Gaussian-blurred (an SSS stand-in whose
    symmetric kernel keeps the phase of a linear ramp), with additive noise; float32."""
    rng = rng or np.random.default_rng(0)
    frames = {}
    for o, u in (("x", xp), ("y", yp)):
        for period in config.periods:
            for n in range(config.n_shifts):
                img = offset + amplitude * np.cos(2 * np.pi * u / period - 2 * np.pi * n / config.n_shifts)
                if blur:
                    img = gaussian_filter(img, blur, mode="nearest")
                if channels is not None:
                    img = img[..., None] * np.asarray(channels)
                if noise:
                    img = img + rng.normal(0.0, noise, img.shape)
                frames[psp_key(o, period, n)] = img.astype(np.float32)
    return frames


@pytest.fixture
def fringes():
    return render_fringes


@pytest.fixture
def camera_map():
    return affine_map
