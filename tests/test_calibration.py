"""`sss calibrate projector`: the projector's response is recovered from a grey ramp captured through the
daemon, and patterns made for it bring the correspondence error back to the nominal figure."""

from __future__ import annotations

import os
import re
import tomllib

import numpy as np
import pytest
from sss_process import run_sss

from sssphase_core.capture.calibration import RAMP_LEVELS, fit_response, rig_file_with_response
from sssphase_core.errors import DataError


def _ramp(gammas, black, *, noise=0.0, seed=0, levels=RAMP_LEVELS):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 0.9, size=(40, 50, 3))
    v = np.asarray(levels)[:, None, None, None]
    light = black + (1 - black) * v ** np.asarray(gammas)
    return albedo * light + rng.normal(0, noise, size=(len(levels), 40, 50, 3))


@pytest.mark.parametrize(("gammas", "black"), [((2.2, 2.2, 2.2), 0.002), ((1.8, 2.2, 2.6), 0.01), ((1.0, 1.0, 1.0), 0.0)])
def test_the_fit_recovers_gamma_and_black_per_colour(gammas, black):
    fit = fit_response(RAMP_LEVELS, _ramp(gammas, black, noise=1e-3))
    np.testing.assert_allclose(fit.gamma_rgb, gammas, atol=0.02)
    np.testing.assert_allclose(fit.black_rgb, black, atol=2e-3)
    assert fit.rms < 0.01 and fit.gamma == pytest.approx(np.mean(gammas), abs=0.02)


def test_a_response_that_is_no_power_law_shows_in_the_rms():
    images = _ramp((2.2, 2.2, 2.2), 0.0)
    v = np.asarray(RAMP_LEVELS)[:, None, None, None]
    s_curve = np.where(v < 0.5, 2 * v**2, 1 - 2 * (1 - v) ** 2)  # not v**gamma
    fit = fit_response(RAMP_LEVELS, images / (v ** 2.2 + 1e-12) * s_curve)
    assert fit.rms > 0.02


def test_a_dark_or_clipped_view_is_one_clear_error():
    with pytest.raises(DataError, match="well exposed"):
        fit_response(RAMP_LEVELS, _ramp((2.2,) * 3, 0.0) * 10)  # every white pixel clipped


def test_the_rig_file_keeps_its_comments_and_gets_one_projector_table():
    text = "# my rig\n[devices]\ncamera = \"uvc:0\"  # the left camera\nprojector = \"hdmi:1\"\n\n[projector]\ngamma = 9\n\n[processing]\npatch = 48\n"
    fit = fit_response(RAMP_LEVELS, _ramp((1.9,) * 3, 0.003))
    once = rig_file_with_response(text, fit)
    twice = rig_file_with_response(once, fit)
    assert "# the left camera" in twice and twice.count("[projector]") == 1
    cfg = tomllib.loads(twice)
    assert cfg["processing"]["patch"] == 48 and cfg["projector"]["gamma"] == pytest.approx(1.9, abs=0.02)


@pytest.mark.slow
def test_calibrating_a_linear_projector_restores_the_nominal_correspondence_error(sim_daemon, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text("# a DLP projector in linear mode\n[devices]\ncamera = \"sim:camera0\"\nprojector = \"sim:projector0\"\n\n"
                   "[options]\nprojector_gamma = 1.0\nprojector_black = 0.004\n")
    res = run_sss(["calibrate", "projector", "--rig", str(rig), "--check"], timeout=600, env={**os.environ, "COLUMNS": "200"})
    assert res.returncode == 0, res.stdout + res.stderr
    cfg = tomllib.loads(rig.read_text())
    assert cfg["projector"]["gamma"] == pytest.approx(1.0, abs=0.02) and cfg["projector"]["black"] == pytest.approx(0.004, abs=1e-3)
    assert cfg["options"]["projector_gamma"] == 1.0 and "# a DLP projector" in rig.read_text()
    errors = [float(e) for e in re.findall(r"median ([0-9.]+) projector px", res.stdout)]
    wrong, fitted, nominal = errors
    assert wrong > fitted + 0.02 and abs(fitted - nominal) < 0.01, res.stdout
    from sssphase_core.capture import CaptureRequest, RigSpec, run_capture

    session = run_capture(sim_daemon, CaptureRequest("leaf", views=1, out=tmp_path / "s"), RigSpec.from_toml(rig))
    assert session.manifest["plan"]["gamma"] == pytest.approx(cfg["projector"]["gamma"])
