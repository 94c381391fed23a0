"""Relighting under a pattern sequence (`sss relight SESSION --pattern clip.mp4`): every frame relit as a still of
it is, written as it comes, joined into a video; an interrupted run resumes; sequences that cannot be used are
refused before any work."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
from sss_process import run_sss

from sssphase_core.errors import InputError
from sssphase_core.relight.runner import Narrator, relight_session
from sssphase_core.relight.sequence import relight_sequence
from sssphase_core.store.pattern_sequences import is_sequence, open_sequence

W, H, FRAMES = 256, 192, 6


class Recorder(Narrator):
    def __init__(self):
        self.lines = []

    def say(self, text, warning=""):
        self.lines.append(text)


@pytest.fixture(scope="module")
def session(tmp_path_factory, sim_daemon):
    from sssphase_core.capture import CaptureRequest, run_capture

    return run_capture(sim_daemon, CaptureRequest("sand_rake", views=1, out=tmp_path_factory.mktemp("s"))).path


def _clip(path, frames=FRAMES, size=(W, H), fps=12.0):
    """A bar sweeping across the projector and a rising red wash, as MPEG-4."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    for i in range(frames):
        frame = np.zeros((size[1], size[0], 3), np.uint8)
        x = i * size[0] // frames
        frame[:, x : x + size[0] // 5] = 255
        frame[..., 2] = np.maximum(frame[..., 2], 40 * i)
        writer.write(frame)
    writer.release()
    return path


def _video_frames(path):
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            return frames, capture.get(cv2.CAP_PROP_FPS)
        frames.append(frame)


def test_every_frame_is_relit_as_the_still_of_it_and_joined_into_a_video(session, tmp_path):
    clip = _clip(tmp_path / "clip.mp4")
    said = Recorder()
    res = relight_sequence(session, clip, backend="analytic", out=tmp_path / "out", narrator=said)
    folder = tmp_path / "out" / "sand_rake_v0_clip_analytic"
    assert res.patterns == ["clip"] and len(res.images) == FRAMES
    assert sorted(p.name for p in folder.glob("*_display.png")) == [
        f"sand_rake_v0_clip-{i:06d}_analytic_display.png" for i in range(FRAMES)]
    frames, fps = _video_frames(tmp_path / "out" / "sand_rake_v0_clip_analytic.mp4")
    assert len(frames) == FRAMES and fps == pytest.approx(12.0) and frames[0].shape == (H, W, 3)
    assert f"wrote {FRAMES} frames to" in said.lines[-1]
    # the video's frame 3 as a still, relit from the same cache (the sequence's later frames come from it) and
    # from scratch: the same image, and within the eigen-footprints' error of it
    capture = cv2.VideoCapture(str(clip))
    for _ in range(4):
        ok, still = capture.read()
    cv2.imwrite(str(tmp_path / "still.png"), still)
    relight_session(session, [str(tmp_path / "still.png")], backend="analytic", out=tmp_path / "out")
    relight_session(session, [str(tmp_path / "still.png")], backend="analytic", out=tmp_path / "fresh", cache=False)
    ours = cv2.imread(str(folder / "sand_rake_v0_clip-000003_analytic.png"), cv2.IMREAD_UNCHANGED)
    cached = cv2.imread(str(tmp_path / "out" / "sand_rake_v0_still_analytic.png"), cv2.IMREAD_UNCHANGED)
    fresh = cv2.imread(str(tmp_path / "fresh" / "sand_rake_v0_still_analytic.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(ours, cached)
    assert ours.max() > 1000 and np.abs(ours.astype(float) - fresh).max() < 0.01 * 65535
    # the bar moves: consecutive frames differ
    assert np.abs(frames[1].astype(int) - frames[4]).mean() > 1


def test_an_interrupted_sequence_resumes_and_other_settings_are_not_mixed_in(session, tmp_path):
    clip = _clip(tmp_path / "clip.mp4")
    out = tmp_path / "out"
    relight_sequence(session, clip, backend="none", out=out)
    folder = out / "sand_rake_v0_clip_none"
    kept = folder / "sand_rake_v0_clip-000000_none_display.png"
    before = kept.stat().st_mtime_ns
    for i in (2, 5):  # as a run stopped before these frames were written leaves them
        for suffix in ("", "_display"):
            (folder / f"sand_rake_v0_clip-{i:06d}_none{suffix}.png").unlink()
    said = Recorder()
    relight_sequence(session, clip, backend="none", out=out, narrator=said)
    assert f"4 of {FRAMES} frames already relit" in said.lines[1] and "relighting the rest" in said.lines[1]
    assert len(list(folder.glob("*_display.png"))) == FRAMES and kept.stat().st_mtime_ns == before
    said = Recorder()
    relight_sequence(session, clip, backend="none", out=out, narrator=said)
    assert f"{FRAMES} of {FRAMES} frames already relit in {folder}: none left to relight" in said.lines[1]
    with pytest.raises(InputError, match=r"holds frames relit with other settings \(formats differ\)"):
        relight_sequence(session, clip, backend="none", out=out, formats="png,exr")
    foreign = out / "sand_rake_v0_clip_analytic"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="holds files that no relight of this sequence wrote"):
        relight_sequence(session, clip, backend="analytic", out=out)
    assert (foreign / "notes.txt").read_text() == "mine"


def test_a_sequence_being_relit_is_not_relit_into_by_a_second_process(session, tmp_path):
    """Two relights of one sequence into one folder at once would relight the same frames and write its video
    twice at once: the second is refused while the first holds the folder, and nothing is left of the lock after."""
    import subprocess
    import sys

    clip = _clip(tmp_path / "clip{1}.mp4", frames=2)  # (braces in the name: the message is not a format string)
    out = tmp_path / "out"
    folder = out / "sand_rake_v0_clip{1}_none"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import time\nfrom pathlib import Path\nfrom sssphase_core.store.locks import folder_lock\n"
        f"with folder_lock(Path({str(folder)!r}), 'busy {{holder}}'):\n    print('held', flush=True)\n    time.sleep(60)\n")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=rf"is being relit by pid {holder.pid} \(another `sss relight` of this"):
            relight_sequence(session, clip, backend="none", out=out)
        assert not folder.exists()
    finally:
        holder.kill()
        holder.wait()
    relight_sequence(session, clip, backend="none", out=out)  # the lock freed
    assert len(list(folder.glob("*_display.png"))) == 2 and not list(out.glob(".*.lock"))


def test_an_animated_image_is_a_sequence_and_a_still_is_not(tmp_path):
    from PIL import Image

    frames = [Image.fromarray(np.full((H, W, 3), v, np.uint8)) for v in (0, 128, 255)]
    frames[0].save(tmp_path / "pulse.gif", save_all=True, append_images=frames[1:], duration=200, loop=0)
    frames[0].save(tmp_path / "still.png")
    assert is_sequence(tmp_path / "pulse.gif") and not is_sequence(tmp_path / "still.png")
    assert not is_sequence(tmp_path / "none.mp4")  # no such file: read as a pattern name, which says so
    seq = open_sequence(tmp_path / "pulse.gif", (W, H))
    assert (seq.count, seq.fps, seq.video) == (3, 5.0, False)
    got = list(seq.frames(start=1))
    assert [i for i, _ in got] == [1, 2] and got[0][1].shape == (H, W, 3)
    np.testing.assert_allclose([g.mean() for _, g in got], [128 / 255, 1.0], atol=1e-6)


def test_the_pages_of_a_16_bit_or_float_tiff_are_read_as_a_still_of_them_is(tmp_path):
    """The pages of a multi-page 16-bit TIFF went through Pillow's 8-bit RGB: a mid-grey relit as full white (a float
    one as black). A multi-page TIFF Pillow cannot decode (float RGB) was relit from its first page alone."""
    from PIL import Image

    from sssphase_core.store.imageio import read_pattern

    for name, grey, ramp in (("grey16.tif", np.full((48, 64), 32768, np.uint16), np.arange(64, dtype=np.uint16) * 1000),
                             ("greyf.tif", np.full((48, 64), 0.5, np.float32), np.arange(64, dtype=np.float32) / 64)):
        pages = [Image.fromarray(grey), Image.fromarray(np.ascontiguousarray(np.broadcast_to(ramp, (48, 64))))]
        pages[0].save(tmp_path / name, save_all=True, append_images=pages[1:])
        frames = dict(open_sequence(tmp_path / name, (64, 48)).frames())
        assert frames[0].shape == (48, 64, 3) and abs(frames[0].mean() - 0.5) < 1e-3, (name, frames[0].mean())
        assert len(np.unique(frames[1][0, :, 0])) == 64  # every level of the ramp (8 bits kept 5 of 64 codes apart)
        half = dict(open_sequence(tmp_path / name, (32, 24), resize="fit").frames())[0]
        assert half.shape == (24, 32, 3) and abs(half.mean() - 0.5) < 1e-3
    rgb = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    cv2.imwritemulti(str(tmp_path / "float_rgb.tif"), [rgb, 1 - rgb])
    with pytest.raises(InputError, match=r"float_rgb.tif holds several images \(a multi-page TIFF\): give one image"):
        read_pattern(tmp_path / "float_rgb.tif", (64, 48))


def test_an_animated_image_cut_short_or_with_a_huge_page_is_one_line_at_that_frame(tmp_path):
    """A GIF cut in half failed as "internal error: OSError: image file is truncated"; a multi-page TIFF's 13000 x
    13000 second page (260 kB on disk) was decoded whole (2.2 GB) and resized: only its first page was checked."""
    import resource

    from PIL import Image

    rng = np.random.default_rng(0)
    frames = [Image.fromarray((rng.random((48, 64, 3)) * 255).astype(np.uint8)) for _ in range(5)]
    frames[0].save(tmp_path / "whole.gif", save_all=True, append_images=frames[1:])
    data = (tmp_path / "whole.gif").read_bytes()
    (tmp_path / "cut.gif").write_bytes(data[: len(data) // 2])
    cut = open_sequence(tmp_path / "cut.gif", (W, H), "fit")
    with pytest.raises(InputError, match=rf"cut.gif: frame \d of {cut.count} does not decode \(.*\): the file is "
                                         "damaged or cut short"):
        list(cut.frames())
    frames[0].save(tmp_path / "pages.tif", save_all=True, append_images=[Image.new("L", (13000, 13000)), frames[1]],
                   compression="tiff_adobe_deflate")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match=r"pages.tif: frame 2 is 13000x13000 but the first is 64x48: the frames of a "
                                         "sequence share one size"):
        list(open_sequence(tmp_path / "pages.tif", (W, H), "fit").frames())
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100_000  # kB: the page was never decoded


def test_sequences_that_cannot_be_used_are_refused_from_their_header(tmp_path):
    (tmp_path / "noise.mp4").write_bytes(os.urandom(5000))
    with pytest.raises(InputError, match="noise.mp4: not a video OpenCV's FFmpeg can read"):
        open_sequence(tmp_path / "noise.mp4", (W, H))
    wide = _clip(tmp_path / "wide.mp4", frames=2, size=(640, 360))
    with pytest.raises(InputError, match=r"its frames are 640x360 but the projector is 256x192 \(pass --resize"):
        open_sequence(wide, (W, H))
    (_, first), _ = open_sequence(wide, (W, H), "fit").frames()
    assert first.shape == (H, W, 3) and first[:20].max() == 0 and first[40:150, :40].min() > 0.9  # 16:9 inside 4:3
    # a GIF whose header claims 9000 x 9000 frames (a few hundred bytes): refused before a frame is decoded
    from PIL import Image

    frames = [Image.new("L", (8, 8), v) for v in (0, 255)]
    frames[0].save(tmp_path / "bomb.gif", save_all=True, append_images=frames[1:])
    data = bytearray((tmp_path / "bomb.gif").read_bytes())
    data[6:10] = (9000).to_bytes(2, "little") * 2  # the logical screen's width and height
    (tmp_path / "bomb.gif").write_bytes(bytes(data))
    assert is_sequence(tmp_path / "bomb.gif")
    with pytest.raises(InputError, match="its frames are 9000x9000, far larger than the 256x192 projector: refused"):
        open_sequence(tmp_path / "bomb.gif", (W, H), "fit")


def test_the_cli_relights_a_video_on_its_own_and_says_what_it_cannot_do(session, tmp_path):
    clip = _clip(tmp_path / "clip.mp4", frames=3)
    res = run_sss(["relight", str(session), "--pattern", str(clip), "--out", str(tmp_path / "out")], timeout=180)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "clip.mp4: 3 frames of 256x192 at 12 frames/s; backend analytic" in res.stdout
    assert (tmp_path / "out" / "sand_rake_v0_clip_analytic.mp4").is_file()
    for args, expected in ((["--pattern", "checkerboard"], "is a sequence of frames (a video, an animated image or a folder of images): relight it on its own"),
                           (["--no-cache"], "leave out --no-cache")):
        res = run_sss(["relight", str(session), "--pattern", str(clip), *args, "--out", str(tmp_path / "o2")], timeout=120)
        assert res.returncode == 2 and expected in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert not (tmp_path / "o2" / "sand_rake_v0_clip_analytic").exists()


def test_a_folder_of_pattern_images_is_relit_in_its_names_natural_order(session, tmp_path):
    """frame2 before frame10, 16-bit PNG and EXR frames read as stills are, other files ignored; a frame of another
    size is refused by name; a folder named like a named pattern does not hide it."""
    import cv2

    from sssphase_core.store.exr import write_exr

    folder = tmp_path / "frames"
    folder.mkdir()
    levels = {2: 0.25, 10: 1.0, 1: 0.0}
    for i, level in levels.items():
        cv2.imwrite(str(folder / f"frame{i}.png"), np.full((H, W), round(level * 65535), np.uint16))
    write_exr(folder / "frame11.exr", np.full((H, W, 3), 0.5, np.float32))
    (folder / "notes.txt").write_text("not a frame")
    (folder / ".thumb.png").write_bytes(b"")
    seq = open_sequence(folder, (W, H))
    assert [p.name for p in seq.files] == ["frame1.png", "frame2.png", "frame10.png", "frame11.exr"]
    np.testing.assert_allclose([f.mean() for _, f in seq.frames()], [0.0, 0.25, 1.0, 0.5], atol=1e-4)
    res = relight_sequence(session, folder, backend="none", out=tmp_path / "out")
    means = [cv2.imread(str(tmp_path / "out" / "sand_rake_v0_frames_none" / f"sand_rake_v0_frames-{i:06d}_none.png"),
                        cv2.IMREAD_UNCHANGED).mean() for i in range(4)]
    assert len(res.images) == 4 and means[0] < means[1] < means[3] < means[2]  # the light follows the frames' order
    cv2.imwrite(str(folder / "frame12.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(InputError, match=r"frame12.png is 10x10 but frame1.png is 256x192: the frames of a sequence "
                                         r"share one size"):  # from the headers, before a frame is relit
        open_sequence(folder, (W, H))
    (tmp_path / "named").mkdir()
    (tmp_path / "named" / "checkerboard").mkdir()
    cv2.imwrite(str(tmp_path / "named" / "checkerboard" / "a.png"), np.zeros((H, W), np.uint8))
    (tmp_path / "named" / "stripes_x").write_text("a note, not an image")  # was "cannot identify image file"
    res = run_sss(["relight", str(session), "--pattern", "checkerboard", "--pattern", "stripes_x", "--backend", "none",
                   "--out", str(tmp_path / "o3")], cwd=tmp_path / "named", timeout=120)
    assert res.returncode == 0 and (tmp_path / "o3" / "sand_rake_v0_checkerboard_none.png").is_file(), res.stdout + res.stderr
    assert (tmp_path / "o3" / "sand_rake_v0_stripes_x_none.png").is_file()
    assert "--pattern stripes_x: the named pattern, not the file stripes_x in this folder (give ./stripes_x for that)" in \
        " ".join(res.stdout.split())
    (tmp_path / "named" / "empty").mkdir()
    res = run_sss(["relight", str(session), "--pattern", "empty", "--backend", "none", "--out", str(tmp_path / "o4")],
                  cwd=tmp_path / "named", timeout=120)
    assert res.returncode == 2 and "--pattern 'empty' is a folder with no pattern images in it" in res.stderr, res.stderr


def test_a_sequence_whose_name_cannot_name_files_is_refused_before_any_output(session, tmp_path):
    clip = _clip(tmp_path / "clip.mp4", frames=2)
    for name, expected in (("bad\nname.mp4", "holds a control character"), ("x" * 240 + ".mp4", "rename it to at most")):
        (tmp_path / name).write_bytes(clip.read_bytes())
        with pytest.raises(InputError, match=expected):
            relight_sequence(session, tmp_path / name, backend="none", out=tmp_path / "out")
        assert not (tmp_path / "out").exists()


def test_a_front_ends_own_frame_limit_refuses_a_longer_sequence_before_any_output(session, tmp_path):
    """`sss view` relights an uploaded video only up to its own limit (32 MB of video held 30,000 frames, ~50 minutes
    of work at the CPU preset): a longer one is refused before any frame, pointing at `sss relight`."""
    clip = _clip(tmp_path / "clip.mp4", frames=4)
    with pytest.raises(InputError, match=r"holds 4 frames, more than the 3 relit here: `sss relight SESSION --pattern "
                                         r"FILE` takes up to 90,000"):
        relight_sequence(session, clip, backend="none", out=tmp_path / "out", max_frames=3)
    assert not (tmp_path / "out").exists()
    assert len(relight_sequence(session, clip, backend="none", out=tmp_path / "out", max_frames=4).patterns) == 1
