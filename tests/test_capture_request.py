"""The capture request's checks (CaptureRequest.from_options / validate) and the calibration request, called
directly: what `sss capture` and `sss calibrate projector` refuse before a daemon starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from sssphase_core.capture import DEFAULT_HDR, CaptureRequest, RigSpec
from sssphase_core.capture.calibration import CalibrationRequest, write_rig_response
from sssphase_core.capture.plan import parse_exposures
from sssphase_core.errors import InputError


def test_from_options_builds_the_request_and_draws_a_randomised_rig_once(tmp_path):
    drawn = []
    req = CaptureRequest.from_options("apple", RigSpec(), views=2, hdr=True, out=tmp_path, seed=3,
                                      randomise_rig=True, on_drawn=drawn.append)
    assert req.hdr == DEFAULT_HDR and req.views == 2 and req.out == tmp_path
    assert len(drawn) == 1 and drawn[0] == req.sim_options and "projector_gamma" in req.sim_options
    again = CaptureRequest.from_options("apple", RigSpec(), out=tmp_path, seed=3, randomise_rig=True)
    assert again.sim_options == req.sim_options  # reproducible from the seed and the name
    assert CaptureRequest.from_options("apple", RigSpec(), hdr_exposures="0.5,2", out=tmp_path).hdr == (0.5, 2.0)
    radiative = CaptureRequest.from_options("apple", RigSpec(), out=tmp_path, transport="radiative", anisotropy=0.4)
    assert radiative.transport == "radiative" and radiative.sim_options == {"anisotropy": 0.4}
    assert CaptureRequest.from_options("apple", RigSpec(), out=tmp_path, backdrop=80).sim_options == {"backdrop": 80}


@pytest.mark.parametrize(("kwargs", "expected"), [
    ({"views": 0}, "--views must be >= 1, got 0"),
    ({"seed": -1}, "--seed must be 0 to 9223372036854775807"),
    ({"views": 10**6}, "turntable takes at most"),
    ({"transport": "nonsense"}, "nonsense"),
    ({"anisotropy": 0.5}, "give it with --transport radiative"),  # a phase function for a diffusion model: no effect
    ({"transport": "radiative", "anisotropy": -0.1}, "anisotropy must be a number in .0, 0.85., got -0.1"),
    ({"backdrop": 40.0}, r"backdrop must be a number in \[60, 1000\], got 40.0"),  # inside the object's reach
    ({"backdrop": float("nan")}, "backdrop must be a number"),
    ({"hdr_exposures": "1,,2"}, "--hdr-exposures takes comma-separated numbers"),
    ({"hdr_exposures": "1"}, "HDR exposures must be 2 to 8 distinct numbers"),
    ({"dot_spacing": 0}, "dot"),
    ({"references": ["checkerboard", "no_such_file.png"]}, "no_such_file.png"),
])
def test_from_options_refuses_in_one_line(tmp_path, kwargs, expected):
    with pytest.raises(InputError, match=expected.replace("(", r"\(")):
        CaptureRequest.from_options("apple", RigSpec(), out=tmp_path / "s", **kwargs)
    assert not (tmp_path / "s").exists()


def test_validate_checks_a_request_made_directly(tmp_path):
    CaptureRequest("apple", views=1, out=tmp_path).validate()
    with pytest.raises(InputError, match="applies to the sim rig only"):
        CaptureRequest("apple", transport="burley", out=tmp_path).validate(RigSpec(camera="x:cam", projector="x:proj"))
    with pytest.raises(InputError, match="HDR exposures"):
        CaptureRequest("apple", hdr=(1.0, 1.0), out=tmp_path).validate()
    with pytest.raises(InputError, match="--randomise-rig changes the simulator"):
        CaptureRequest.from_options("apple", RigSpec(camera="x:cam", projector="x:proj"), out=tmp_path,
                                    randomise_rig=True)
    with pytest.raises(InputError, match="--backdrop puts a wall behind the simulator's objects"):
        CaptureRequest.from_options("apple", RigSpec(camera="x:cam", projector="x:proj"), out=tmp_path, backdrop=80)
    # --hdr on a rig whose clipping level is not given failed after the daemon started, 2 frames in, leaving an
    # empty session behind
    with pytest.raises(InputError, match=r"--hdr merges .* give it in the rig file \(\[processing\] saturation"):
        CaptureRequest.from_options("apple", RigSpec(camera="x:cam", projector="x:proj"), out=tmp_path / "h", hdr=True)
    assert not (tmp_path / "h").exists()
    CaptureRequest.from_options("apple", RigSpec(camera="x:cam", projector="x:proj", saturation=0.98),
                                out=tmp_path / "h", hdr=True)


def test_parse_exposures():
    assert parse_exposures(" 0.25, 1 ,4") == (0.25, 1.0, 4.0)
    for bad in ("", "a,b", "1,"):
        with pytest.raises(InputError, match="--hdr-exposures"):
            parse_exposures(bad)


def test_calibration_request_resolves_and_checks_the_target(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    req = CalibrationRequest()
    assert req.target == Path("rig.toml") and req.spec.is_sim and req.ramp[0] == 0 and req.ramp[-1] == 1
    assert len(req.ramp) == 17
    with pytest.raises(InputError, match="is a folder"):
        CalibrationRequest(out=tmp_path)
    (tmp_path / "script.py").write_text("print('x')\n")
    with pytest.raises(InputError, match="exists and is not a rig file"):
        CalibrationRequest(out=tmp_path / "script.py")
    with pytest.raises(InputError, match="script.py is a file, not a folder"):  # was "File exists" after the capture
        CalibrationRequest(out=tmp_path / "script.py" / "rig.toml")
    real = tmp_path / "real.toml"
    real.write_text('[devices]\ncamera = "x:cam"\nprojector = "x:proj"\n')
    with pytest.raises(InputError, match="works on sim rigs only"):
        CalibrationRequest(rig=real, check=True)



@pytest.mark.parametrize(("options", "said"), [
    ("[options]\nexposure_us = 1000\n", r"\[options\] exposure_us outside every plugin's table: a device's settings go "
                                        r"in its plugin's table, e.g. \[options.basler\] exposure_us = ... \(this rig's "
                                        r"plugins: basler, hdmi\)"),
    ("[options]\nbasler = \"fast\"\n", r"\[options\] basler must be a table of basler settings \(\[options.basler\]\), "
                                       r"got str"),
])
def test_a_real_rig_s_option_outside_its_plugin_s_table_is_refused_when_read(tmp_path, options, said):
    """A key under [options] of a rig without simulated devices (only the sim plugin reads bare keys) was ignored:
    the capture ran with the default and exited 0."""
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "basler:0815-0000"\nprojector = "hdmi:display0"\n' + options)
    with pytest.raises(InputError, match=said):
        RigSpec.from_toml(rig)
    rig.write_text('[devices]\ncamera = "basler:0815-0000"\nprojector = "hdmi:display0"\n[options.basler]\ngain = 0\n')
    assert RigSpec.from_toml(rig).options == {"basler": {"gain": 0}}


def test_write_rig_response_writes_a_sim_rig_file_with_the_fit(tmp_path):
    import numpy as np

    from sssphase_core.capture.calibration import fit_response

    levels = tuple(float(v) for v in np.linspace(0, 1, 9))
    light = np.array([0.8 * (0.02 + 0.98 * v ** 2.0) for v in levels], np.float32)
    images = np.broadcast_to(light[:, None, None, None], (9, 8, 8, 3)).copy()
    fitted = fit_response(levels, images)
    target = write_rig_response(CalibrationRequest(out=tmp_path / "rigs" / "r.toml"), fitted)
    spec = RigSpec.from_toml(target)
    assert spec.is_sim and spec.gamma == pytest.approx(2.0, abs=0.05)


def test_dot_spacings_under_half_the_footprints_default_are_warned_about(tmp_path):
    """--dot-spacing 1 captured footprints of one pixel's light (each crop keeps its dot's Voronoi cell) without a word."""
    import warnings

    from sssphase_core.capture.plan import build_frames, dot_spacing_for

    assert dot_spacing_for(32) == 20
    with pytest.warns(UserWarning, match=r"--dot-spacing 9 is under half the 20 px that 32 px footprints .* within 4.5 projector px"):
        build_frames(CaptureRequest.from_options("apple", RigSpec(), footprints=True, dot_spacing=9, out=tmp_path), (64, 48), 32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_frames(CaptureRequest.from_options("apple", RigSpec(), footprints=True, dot_spacing=10, out=tmp_path), (64, 48), 32)
        build_frames(CaptureRequest.from_options("apple", RigSpec(), dot_spacing=1, out=tmp_path), (64, 48), 32)  # no dots
