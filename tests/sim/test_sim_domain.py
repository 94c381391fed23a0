"""Domain randomisation of the sim rig: camera options (lens blur, read noise, exposure, demosaicing),
the projector's true response and the transport model, drawn per object and recorded in the session."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.sim import (
    ANISOTROPY_RANGE,
    RANDOMISED_RANGES,
    TRANSPORTS,
    SimScene,
    randomised_rig_options,
    rig_from_options,
)


def test_draws_are_reproducible_within_their_ranges_and_differ_between_objects():
    draws = [randomised_rig_options(0, name) for name in ("apple", "pear", "star", "dragon", "bunny", "soap")]
    assert randomised_rig_options(0, "apple") == draws[0]
    assert randomised_rig_options(1, "apple") != draws[0]
    for d in draws:
        for k, (lo, hi) in RANDOMISED_RANGES.items():
            assert lo <= d[k] <= hi
        assert d["transport"] in TRANSPORTS and d["demosaic"] in ("malvar", "opencv")
        rig = rig_from_options(d)
        assert rig.sensor.lens_blur == d["lens_blur"] and rig.sensor.white_fraction == d["white_fraction"]
        assert rig.projector.gamma == d["projector_gamma"] and rig.transport == d["transport"]
    assert len({d["projector_gamma"] for d in draws}) == len(draws)
    assert len({d["transport"] for d in draws}) >= 2 and len({d["demosaic"] for d in draws}) == 2
    assert all(rig_from_options(d).anisotropy == d["anisotropy"] for d in draws)
    more = [randomised_rig_options(0, name)["transport"] for name in ("orange", "shovel", "crab", "leaf", "lego", "hand")]
    assert set(more + [d["transport"] for d in draws]) == set(TRANSPORTS)  # radiative transfer among them
    assert ANISOTROPY_RANGE == RANDOMISED_RANGES["anisotropy"]


def test_a_camera_draw_is_the_rig_draw_without_its_transport():
    full, camera = randomised_rig_options(4, "pear"), randomised_rig_options(4, "pear", what="camera")
    assert camera == {k: v for k, v in full.items() if k not in ("transport", "anisotropy")}
    with pytest.raises(ValueError, match="unknown randomisation 'lens'"):
        randomised_rig_options(4, "pear", what="lens")


@pytest.mark.parametrize(("option", "value"), [("lens_blur", -1.0), ("read_noise", float("nan")),
                                               ("white_fraction", 2.0), ("demosaic", "nearest"),
                                               ("projector_gamma", "2.2")])
def test_a_bad_camera_option_is_one_error_naming_it(option, value):
    with pytest.raises(InputError, match=option):
        rig_from_options({option: value})


def test_the_lens_blurs_the_image_and_keeps_its_light():
    sharp = SimScene("star", rig=rig_from_options({}))
    blurred = SimScene("star", rig=rig_from_options({"lens_blur": 1.0}))
    img = np.zeros((1, 192, 256, 3), np.float32)
    img[:, :, 128:] = 0.5  # a vertical edge
    a, b = sharp.sense_noise_free(img)[0], blurred.sense_noise_free(img)[0]
    rows = slice(20, 170)
    assert np.abs(a[rows, 126:130] - b[rows, 126:130]).max() > 0.05  # the edge is spread
    assert np.abs(a[rows, 100:120] - b[rows, 100:120]).max() < 1e-3  # flat regions are not
    assert b[rows].mean() == pytest.approx(a[rows].mean(), rel=1e-3)  # a PSF moves light, never loses it


def test_exposure_and_demosaicing_reach_the_camera():
    img = np.full((1, 192, 256, 3), 0.01, np.float32)  # dark: read noise dominates
    dim = SimScene("star", rig=rig_from_options({"white_fraction": 0.3}))
    assert dim.rig.sensor.saturation() == pytest.approx(1 / 0.3)  # a white target fills 30% of the well
    noisy = SimScene("star", rig=rig_from_options({"read_noise": 40.0}))
    quiet = SimScene("star", rig=rig_from_options({"read_noise": 1.0}))
    rng = lambda: np.random.default_rng(0)  # noqa: E731
    assert noisy.sense(img, rng())[0, 10:180, 10:240].std() > 2 * quiet.sense(img, rng())[0, 10:180, 10:240].std()
    edge = np.zeros((1, 192, 256, 3), np.float32)
    edge[..., ::7, :, 0] = 1.0  # colour detail that demosaicing methods treat differently
    malvar = SimScene("star", rig=rig_from_options({})).sense_noise_free(edge)
    opencv = SimScene("star", rig=rig_from_options({"demosaic": "opencv"})).sense_noise_free(edge)
    assert np.abs(malvar - opencv).max() > 0.01


def test_a_three_chip_camera_sees_every_colour_at_every_pixel():
    """``demosaic = "none"``: no colour filter array, so the camera's image of colour detail is the image itself
    (a Bayer camera's differs at every edge), and its noise is the photosites' own (no demosaicing correlates
    it); raw Bayer frames are refused."""
    from sssphase_plugins.drivers import DeviceError
    from sssphase_plugins.sim_plugin import SimCamera, SimRigState

    edge = np.zeros((1, 192, 256, 3), np.float32)
    edge[..., ::7, :, 0] = 0.8
    edge[..., 1::5, 2] = 0.3
    three = SimScene("star", rig=rig_from_options({"demosaic": "none"}))
    np.testing.assert_allclose(three.sense_noise_free(edge), edge, atol=2e-4)  # (quantised black level only)
    assert np.abs(SimScene("star", rig=rig_from_options({})).sense_noise_free(edge) - edge).max() > 0.1
    flat = np.full((1, 192, 256, 3), 0.4, np.float32)
    noisy = three.sense(flat, np.random.default_rng(0))[0] - 0.4
    assert abs(np.corrcoef(noisy[:, :-1, 1].ravel(), noisy[:, 1:, 1].ravel())[0, 1]) < 0.05  # neighbours independent
    with pytest.raises(DeviceError, match="three-chip"):
        SimCamera(SimRigState({"demosaic": "none"}), {"raw": True})


@pytest.mark.slow
def test_a_randomised_capture_records_its_rig_and_evaluation_rebuilds_it(sim_daemon, tmp_path):
    """The drawn options travel with the session: the exact footprints of evaluation come from the
    same rig the frames were captured with."""
    from sssphase_core.capture import CaptureRequest, run_capture
    from sssphase_core.relight import load_view

    drawn = randomised_rig_options(3, "star")
    session = run_capture(sim_daemon, CaptureRequest("star", views=1, out=tmp_path, sim_options=drawn))
    assert {k: session.manifest["rig"]["options"][k] for k in drawn} == drawn
    rig = load_view(session, 0).scene().rig
    assert rig.sensor.lens_blur == drawn["lens_blur"] and rig.transport == drawn["transport"]
    gt = np.asarray(session.load(0, "gt/proj_xy"))
    xp, mask = np.asarray(session.load(0, "corr/xp")), np.asarray(session.load(0, "corr/mask")).astype(bool)
    ok = mask & np.isfinite(gt[..., 0])
    assert ok.sum() > 1000 and np.median(np.abs(xp - gt[..., 0])[ok]) < 0.5  # still decodes


@pytest.mark.slow
@pytest.mark.parametrize("rigs", ["camera", "randomised"])
def test_the_demo_captures_each_training_object_on_its_own_rig(sim_daemon, tmp_path, rigs):
    """`sss demo --training-rigs camera` (each training object its own camera and projector) and `randomised` (the
    transport too): training sessions carry their draws, and the folder remembers it."""
    from sssphase_core.reporting.demo import Demo, DemoConfig
    from sssphase_core.store.session import Session

    # one dot grid a view (the largest stride the plan takes): what is checked is what the sessions record
    cfg = DemoConfig(("star", "shovel"), ("sand_rake",), train_views=1, dot_stride=20)
    demo = Demo(tmp_path, cfg, sim_daemon, log=lambda _: None, training_rigs=rigs)
    assert ("randomised camera" if rigs == "camera" else "randomised rig") in demo.report_rig  # what it trained on
    demo.train_sessions()
    camera_keys = [k for k in RANDOMISED_RANGES if k != "anisotropy"] + ["demosaic"]
    for obj in cfg.train_objects:
        options = Session.open(tmp_path / "sessions" / "train" / obj).manifest["rig"]["options"]
        full = randomised_rig_options(0, obj)  # the camera draw is the full draw's camera
        assert {k: options[k] for k in camera_keys} == {k: full[k] for k in camera_keys}
        if rigs == "randomised":
            assert options["transport"] == full["transport"] and options["anisotropy"] == full["anisotropy"]
        else:
            assert options["transport"] == "burley" and "anisotropy" not in options
    with pytest.raises(InputError, match=f"training {'cameras' if rigs == 'camera' else 'rigs'} randomised"):
        Demo(tmp_path, cfg, sim_daemon, log=lambda _: None)  # resuming it as a nominal demo would mix the two
