"""Projector patterns and capture plans."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import (
    PSPConfig,
    capture_plan,
    checkerboard,
    dot_grid,
    paper_inputs,
    period_ladder,
    phase_shift_patterns,
    psp_config_for,
    stripes,
)


@pytest.mark.parametrize("size,spacing", [((64, 48), 7), ((50, 31), 5), ((23, 40), 1)])
def test_dot_grids_light_every_projector_pixel_exactly_once(size, spacing):
    w, h = size
    total = np.zeros((h, w))
    for sy in range(spacing):
        for sx in range(spacing):
            total += dot_grid(w, h, spacing, sx, sy)
    assert np.array_equal(total, np.ones((h, w)))


def test_dot_grid_places_dots_on_the_lattice():
    img = dot_grid(40, 30, 11, 3, 5)
    ys, xs = np.nonzero(img)
    assert set(ys) == {5, 16, 27} and set(xs) == {3, 14, 25, 36}


@pytest.mark.parametrize("n_shifts", [3, 4, 5, 8])
@pytest.mark.parametrize("orientation", ["x", "y"])
def test_emitted_fringes_are_sinusoids_after_gamma(n_shifts, orientation):
    gamma, period = 2.2, 12.5
    pats = phase_shift_patterns(60, 40, period=period, n_shifts=n_shifts, orientation=orientation, gamma=gamma)
    assert pats.shape == (n_shifts, 40, 60) and pats.dtype == np.float32
    assert pats.min() >= 0 and pats.max() <= 1
    coord = np.arange(60 if orientation == "x" else 40)
    for n, pat in enumerate(pats):
        profile = pat[0, :] if orientation == "x" else pat[:, 0]
        expected = 0.5 + 0.5 * np.cos(2 * np.pi * coord / period - 2 * np.pi * n / n_shifts)
        np.testing.assert_allclose(profile.astype(np.float64) ** gamma, expected, atol=1e-5)
        # constant across the other axis
        assert np.ptp(pat, axis=0 if orientation == "x" else 1).max() == 0


def test_paper_inputs_are_four_x_then_four_y_shifts():
    pats = paper_inputs(32, 24, period=8, gamma=1.0)
    assert pats.shape == (8, 24, 32)
    assert np.ptp(pats[:4], axis=1).max() == 0  # x fringes: constant along rows
    assert np.ptp(pats[4:], axis=2).max() == 0


def test_an_hdr_plan_names_the_same_eight_inputs_as_a_single_exposure_one():
    """Exposure brackets list each pattern once per exposure under one key: the 8 inputs (the patterns the
    view calibration relights) are still found (HDR sessions used to lose the calibration silently)."""
    import json

    from sssphase_core.relight.views import paper_input_patterns

    single = json.loads(capture_plan(64, 48).to_json())
    hdr = json.loads(capture_plan(64, 48, hdr_exposures=(0.25, 1.0, 4.0)).to_json())
    assert len([f for f in hdr["frames"] if f["kind"] == "psp"]) == 3 * len([f for f in single["frames"] if f["kind"] == "psp"])
    expected = paper_input_patterns(single)
    assert expected is not None and expected.shape == (8, 48, 64)
    np.testing.assert_array_equal(paper_input_patterns(hdr), expected)


def test_too_few_shifts_rejected():
    with pytest.raises(InputError):
        phase_shift_patterns(10, 10, period=4, n_shifts=2)
    with pytest.raises(InputError):
        PSPConfig(period=10, n_shifts=2)
    with pytest.raises(InputError):
        PSPConfig(period=10, unwrap_periods=(5,))


@pytest.mark.parametrize("size", [(256, 256), (320, 240), (1920, 1080), (3840, 2160), (64, 48)])
def test_preset_ladder_reaches_screen_with_bounded_ratio(size):
    cfg = psp_config_for(*size)
    periods = cfg.periods
    assert periods[0] >= max(size), "coarsest period must span the screen"
    ratios = np.array(periods[:-1]) / np.array(periods[1:])
    assert (ratios > 1).all() and (ratios <= 8).all()
    assert list(periods) == sorted(periods, reverse=True)


def test_preset_periods_suit_resolution():
    assert 10 <= psp_config_for(256, 256).period <= 12
    assert 16 <= psp_config_for(1920, 1080).period <= 24


def test_period_ladder_empty_when_period_spans_screen():
    assert period_ladder(400, 300) == ()


def test_plan_without_footprints_or_references_has_only_psp():
    cfg = PSPConfig(period=10, n_shifts=4, unwrap_periods=(300, 60))
    plan = capture_plan(256, 200, psp=cfg)
    assert len(plan) == 2 * 3 * 4
    assert {f.kind for f in plan} == {"psp"}
    assert plan[0].key == "psp/x/p300/s0" and plan[-1].key == "psp/y/p10/s3"
    assert len(set(plan.keys())) == len(plan)
    no_unwrap = capture_plan(256, 200, psp=cfg, unwrap=False)
    assert [f.key for f in no_unwrap] == [f"psp/{o}/p10/s{n}" for o in "xy" for n in range(4)]


def test_plan_with_footprints_and_references():
    plan = capture_plan(40, 30, psp=PSPConfig(period=8, unwrap_periods=(50,)), footprints=True, dot_spacing=5,
                        references=["checkerboard", "white"])
    kinds = [f.kind for f in plan]
    assert kinds.count("dots") == 25
    assert "black" in kinds and "white" in kinds and plan.keys().count("ref/checkerboard") == 1
    lit = sum(f.pattern() for f in plan if f.kind == "dots")
    assert np.array_equal(lit, np.ones((30, 40)))
    frame = next(f for f in plan if f.key == "dots/2_3")
    assert frame.params["shift_x"] == 2 and frame.params["shift_y"] == 3


def test_plan_hdr_brackets_repeat_each_pattern_with_unique_names():
    plan = capture_plan(32, 24, psp=PSPConfig(period=8, unwrap_periods=(40,)), references=["white"],
                        hdr_exposures=(1.0, 4.0))
    assert len(plan) == 2 * (2 * 2 * 4 + 1)
    assert len({f.name for f in plan}) == len(plan)
    assert {f.exposure for f in plan} == {1.0, 4.0}
    assert plan.keys().count("white") == 1


def test_plan_frames_render_lazily_and_to_json():
    import json

    plan = capture_plan(48, 32, psp=PSPConfig(period=8, unwrap_periods=(64, 20)), references=["stripes_y"])
    frame = next(f for f in plan if f.key == "psp/y/p20/s1")
    expected = phase_shift_patterns(48, 32, period=20, n_shifts=4, orientation="y")[1]
    np.testing.assert_array_equal(frame.pattern(), expected)
    data = json.loads(plan.to_json())
    assert data["projector"] == [48, 32] and len(data["frames"]) == len(plan)


def test_unknown_reference_rejected():
    with pytest.raises(InputError, match="checkerboard"):
        capture_plan(32, 24, references=["zebra"])


def test_a_capture_reference_that_is_no_file_lists_the_named_patterns(tmp_path):
    """`sss capture --reference checkerbaord` said only "cannot read checkerbaord: No such file"."""
    from sssphase_core.capture import CaptureRequest, RigSpec

    with pytest.raises(InputError, match="'checkerbaord' is neither an image file nor one of white, black, checkerboard"
                                         r".*: did you mean checkerboard\?"):
        CaptureRequest.from_options("apple", RigSpec(), references=["checkerbaord"], out=tmp_path / "s")
    # a path that is not there is no such file (it was "neither an image file nor one of white, ...")
    with pytest.raises(InputError, match=r"^--reference pats/logo.png: no such file$"):
        CaptureRequest.from_options("apple", RigSpec(), references=["pats/logo.png"], out=tmp_path / "s")


def test_checkerboard_and_stripes():
    cb = checkerboard(8, 6, 2)
    assert cb[0, 0] == 1 and cb[0, 2] == 0 and cb[2, 0] == 0 and cb[2, 2] == 1
    assert cb.mean() == pytest.approx(0.5)
    st = stripes(12, 4, 4, "x")
    np.testing.assert_array_equal(st[0], [1, 1, 0, 0] * 3)
    sty = stripes(3, 8, 4, "y")
    np.testing.assert_array_equal(sty[:, 0], [1, 1, 0, 0] * 2)


def test_a_pattern_name_that_is_no_image_file_says_what_it_is(tmp_path):
    """A FIFO, /dev/zero and a folder given as --pattern or --reference were each "no such file"."""
    import os

    from sssphase_core.processing.patterns import unknown_pattern

    os.mkfifo(tmp_path / "fifo.png")
    assert unknown_pattern("--pattern", str(tmp_path / "fifo.png")).endswith("fifo.png is a FIFO, not an image file")
    assert unknown_pattern("--pattern", "/dev/zero") == "--pattern /dev/zero is a device, not an image file"
    assert unknown_pattern("--reference", str(tmp_path)) == f"--reference {tmp_path} is a folder, not an image file"
    assert unknown_pattern("--pattern", str(tmp_path / "none.png")) == f"--pattern {tmp_path / 'none.png'}: no such file"
    assert "did you mean checkerboard?" in unknown_pattern("--pattern", "checkerbord")
