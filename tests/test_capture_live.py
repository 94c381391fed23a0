"""What a live view computes (sssphase_core.capture.live), without a browser: the patterns it may put on the
projector, refusals before a daemon sees them, and a frame's exposure statistics."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.capture.live import HIST_BINS, LIVE_PATTERNS, frame_stats, pattern_spec, psp_set
from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import PlannedFrame, frame_params_problem


@pytest.mark.parametrize("name", list(LIVE_PATTERNS))
def test_every_live_pattern_is_a_frame_the_daemon_accepts_and_renders(name):
    spec = pattern_spec(name, (64, 48), exposure=0.5)
    assert frame_params_problem(spec["kind"], spec["params"]) is None and spec["exposure"] == 0.5
    image = PlannedFrame(spec["key"], spec["kind"], spec["params"]).pattern()
    assert image.shape == (48, 64) and 0 <= image.min() <= image.max() <= 1


def test_the_psp_set_is_the_captures_and_each_frame_can_be_shown_alone():
    frames = psp_set((256, 192))
    assert {f["kind"] for f in frames} == {"psp", "white", "black"} and len(frames) > 8
    assert pattern_spec("psp", (256, 192), psp_frame=3)["key"] == frames[3]["key"]
    with pytest.raises(InputError, match=f"the PSP set has frames 0..{len(frames) - 1}, got {len(frames)}"):
        pattern_spec("psp", (256, 192), psp_frame=len(frames))


def test_refusals_name_the_problem():
    with pytest.raises(InputError, match="unknown pattern 'plaid'; choose white, black"):
        pattern_spec("plaid", (64, 48))
    for bad in (0.0, -1.0, float("nan"), 1e9):
        with pytest.raises(InputError, match="exposure must be a number in"):
            pattern_spec("white", (64, 48), exposure=bad)
    with pytest.raises(InputError, match="an image to project must be 64x48"):
        pattern_spec("image", (64, 48), image=np.zeros((10, 10), np.float32))
    spec = pattern_spec("image", (64, 48), image=np.full((48, 64, 3), 0.25, np.float32))
    assert spec["kind"] == "image" and spec["image"]["shape"] == [48, 64, 3]


def test_frame_statistics_count_the_clipped_pixels_and_fill_the_histogram():
    image = np.zeros((10, 20, 3), np.float32)
    image[:5] = 0.5
    image[0, :4, 1] = 1.0  # 4 pixels clipped in green only
    stats = frame_stats(image)
    assert stats.clipped == pytest.approx(4 / 200)
    assert len(stats.histogram) == 3 and all(len(h) == HIST_BINS and sum(h) == 200 for h in stats.histogram)
    assert stats.mean[0] == pytest.approx(0.25) and stats.mean[1] > stats.mean[0]


def test_a_cameras_colour_frames_are_light_whatever_their_type_and_other_shapes_are_refused():
    """uint16 RGB frames were taken as linear units (65535x too bright, `sss validate` content); RGBA frames made a
    session `sss validate` refused."""
    from sssphase_core.capture.plan import RigSpec
    from sssphase_core.capture.processing import develop_frame
    from sssphase_core.errors import DataError

    rig = RigSpec(camera="fake:cam0", projector="sim:projector0")
    codes = np.full((4, 5, 3), 32768, np.uint16)
    assert develop_frame(codes, rig).max() == pytest.approx(32768 / 65535)
    assert develop_frame(codes // 16, rig, meta={"bit_depth": 12}).max() == pytest.approx(2048 / 4095)
    assert develop_frame(np.full((4, 5, 3), 0.25, np.float32), rig).max() == 0.25  # floats as sent
    with pytest.raises(DataError, match=r"the camera fake:cam0 sends frames of shape \(4, 5, 4\): a colour frame is "
                                        r"\(H, W, 3\) RGB"):
        develop_frame(np.zeros((4, 5, 4), np.float32), rig)
    # a mono camera's float (H, W) frame was taken for a Bayer mosaic; a raw frame without its levels named no camera
    with pytest.raises(DataError, match=r"the camera fake:cam0 sends float32 frames of shape \(4, 6\): an \(H, W\) "
                                        r"frame is a raw Bayer mosaic of integer codes; a mono camera's plugin sends"):
        develop_frame(np.zeros((4, 6), np.float32), rig)
    with pytest.raises(DataError, match=r"the camera fake:cam0 sends raw frames without its black level and bit depth"):
        develop_frame(np.zeros((4, 6), np.uint16), rig)
