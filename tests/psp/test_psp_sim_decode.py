"""Decoding simulated captures against the simulator's exact correspondences."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.processing.patterns import psp_config_for


def test_sim_star_decodes_to_exact_correspondences():
    sim = pytest.importorskip("sssphase_core.sim")
    from sssphase_core.bench.psp_bench import _SimFringes, correspondence_errors
    from sssphase_core.processing.psp import decode

    fringes = _SimFringes(sim.SimScene("star"))
    size = (fringes.wp, fringes.hp)
    config = psp_config_for(*size)
    clean = fringes.clean(config)
    gt_x, gt_y = fringes.scene.proj_xy[..., 0], fringes.scene.proj_xy[..., 1]

    exact = correspondence_errors(decode(clean, config, size), gt_x, gt_y, config.period)
    assert exact["median_px"] < 0.02 and exact["coverage"] > 0.98 and exact["wrong_order"] == 0

    noisy = fringes.captured(clean, 1.0, np.random.default_rng(0), median=False)
    corr = decode(noisy, config, size)
    nominal = correspondence_errors(corr, gt_x, gt_y, config.period)
    assert nominal["median_px"] < 0.1, "acceptance: weakly scattering object at nominal noise"
    assert nominal["coverage"] > 0.95 and nominal["wrong_order"] < 0.005
    # demosaicing bleeds fringes into a 1-px rim of background pixels; they decode like their neighbours
    assert nominal["false_valid"] < 0.05 * corr.mask.sum()
