"""Synthetic fringe captures with known camera -> projector correspondence (until/besides the sim)."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.bench.psp_bench import synthetic_frames
from sssphase_core.processing.patterns import PSPConfig


def affine_map(shape: tuple[int, int], scale: float = 0.9, offset: tuple[float, float] = (7.3, 4.1), shear: float = 0.05):
    """Projector coordinates (xp, yp) of each camera pixel for a slightly sheared affine view."""
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    return scale * xx + shear * yy + offset[0], scale * yy - shear * xx + offset[1] + shear * shape[1]


def render_fringes(config: PSPConfig, xp: np.ndarray, yp: np.ndarray, *, amplitude=0.25, **kwargs) -> dict[str, np.ndarray]:
    """The benchmark's synthetic fringes (float32), with the tests' default amplitude."""
    return synthetic_frames(config, xp, yp, amplitude=amplitude, **kwargs)


@pytest.fixture
def fringes():
    return render_fringes


@pytest.fixture
def camera_map():
    return affine_map
