"""Shared fixtures for the relighting tests."""

import numpy as np
import pytest

from sssphase_core.relight import Projection


def toy_projection(h=40, w=48, wp=60, hp=50, *, scale=1.1, offset=(0.3, 0.7), radius_div=2.5, black=0.0):
    """A disc of valid pixels mapped to the projector by a scaled, shifted identity."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    mask = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (min(h, w) / radius_div) ** 2
    xp = np.where(mask, xx * scale + offset[0], np.nan).astype(np.float32)
    yp = np.where(mask, yy * scale + offset[1], np.nan).astype(np.float32)
    return Projection(xp, yp, mask, (wp, hp), gamma=2.2, black=black)


@pytest.fixture
def make_projection():
    return toy_projection
