"""Where commands write and what they read first: no command overwrites captured frames, writes into a
session's folders, reads another session's cache or leaves a previous run's files beside its own; a wrong
--out or --views is one line before any work."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sss_process import run_sss

from sssphase_core.capture import import_folder
from sssphase_core.errors import InputError

W, H = 64, 48


def _sss(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return run_sss([*args], timeout=300, cwd=cwd)


def _one_line(res: subprocess.CompletedProcess[str], expected: str) -> None:
    out = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in out, out
    assert out.strip().splitlines() == [f"error: {expected}"] or (len(out.strip().splitlines()) == 1 and expected in out), out


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    sys.path.insert(0, str(Path(__file__).parent))
    from test_import import _float_frames

    root = tmp_path_factory.mktemp("out")
    return import_folder(_float_frames(root / "frames", 1.0), root / "sessions", "obj", (W, H), patch=16).path


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def test_patterns_never_overwrite_a_folder_of_frames(tmp_path):
    """`sss patterns --out` into a folder of captured frames replaced every 16-bit capture by an 8-bit pattern of
    the same name; into an earlier pattern set, it left the old set's files beside the new plan."""
    import cv2

    frames = tmp_path / "captured"
    (frames / "psp" / "x" / "p5").mkdir(parents=True)
    cv2.imwrite(str(frames / "psp" / "x" / "p5" / "s0.png"), np.full((H, W), 40000, np.uint16))
    cv2.imwrite(str(frames / "white.png"), np.full((H, W), 50000, np.uint16))
    before = _digest(frames)
    _one_line(_sss("patterns", "--projector", f"{W}x{H}", "--out", str(frames)),
              f"--out {frames} already holds white.png: write the patterns into a new folder (nothing was written)")
    assert _digest(frames) == before
    (frames / "white.png").unlink()  # a frame in the nested layout `sss patterns` writes
    _one_line(_sss("patterns", "--projector", f"{W}x{H}", "--out", str(frames)), "already holds psp/x/p5/s0.png")
    assert _digest(frames) == {k: v for k, v in before.items() if k != "white.png"}
    assert _sss("patterns", "--projector", f"{W}x{H}", "--out", str(tmp_path / "p")).returncode == 0
    _one_line(_sss("patterns", "--projector", f"{W}x{H}", "--period", "10", "--out", str(tmp_path / "p")),
              "already holds")
    _one_line(_sss("patterns", "--projector", f"{W}x{H}", "--period", "1000000", "--out", str(tmp_path / "q")),
              f"--period 1e+06 is longer than the {W}x{H} projector: the fringes need at least one period across it")


def test_interrupted_patterns_leave_no_half_set_and_run_again(tmp_path):
    """Ctrl-C while `sss patterns` wrote left PNGs and no plan.json: the next run was refused ("already holds
    white.png") until the user found and deleted them. The half set is removed; the user's own file stays."""
    from sssphase_core.capture.pattern_files import write_patterns

    def stop_at_the_third(done, total):
        if done == 3:
            raise KeyboardInterrupt

    for out in (tmp_path / "new" / "patterns", tmp_path / "mine"):
        if out.name == "mine":
            out.mkdir()
            (out / "notes.txt").write_text("mine")
        before = _digest(tmp_path)
        with pytest.raises(KeyboardInterrupt):
            write_patterns(out, f"{W}x{H}", progress=stop_at_the_third)
        assert _digest(tmp_path) == before and (out.name == "mine") == (tmp_path / out.relative_to(tmp_path).parts[0]).exists()
        written = write_patterns(out, f"{W}x{H}")
        assert (out / "plan.json").is_file() and len(list(out.rglob("*.png"))) == written.patterns


@pytest.mark.parametrize("command", [
    ["import", "{frames}", "--object", "o2", "--projector", f"{W}x{H}", "--out", "{inside}"],
    ["capture", "--object", "apple", "--views", "1", "--out", "{inside}"],
    ["sim", "--object", "apple", "--views", "1", "--out", "{inside}"],
    ["decode", "{frames}", "--projector", f"{W}x{H}", "--out", "{inside}"],
    ["patterns", "--projector", f"{W}x{H}", "--out", "{inside}"],
])
def test_no_command_writes_into_a_session(session, command):
    """A session's folders hold only what its manifest lists: a session created inside another one's view
    folder passed `sss validate` and was then found by `sss eval relight` as a second session."""
    inside = session / "view_000" / "nested"
    args = [a.format(frames=session.parent.parent / "frames", inside=inside) for a in command]
    res = _sss(*args)
    _one_line(res, f"would write into the session {session.resolve()}")
    assert "started a local" not in res.stdout + res.stderr and not inside.exists()


@pytest.mark.parametrize("command", [
    ["relight", "{session}", "--pattern", "checkerboard", "--out", "{file}"],
    ["eval", "relight", "{session}", "--backend", "none", "--out", "{file}"],
    ["export", "{session}", "--out", "{file}"],
    ["geometry", "{session}", "--backend", "analytic", "--out", "{file}"],
    ["report", "{session}", "--backend", "none", "--out", "{file}"],
    ["capture", "--object", "apple", "--views", "1", "--out", "{file}"],
    ["sim", "--object", "apple", "--views", "1", "--out", "{file}"],
])
def test_an_out_that_is_a_file_is_one_line(session, tmp_path, command):
    (tmp_path / "afile").write_text("mine\n")
    args = [a.format(session=session, file=tmp_path / "afile") for a in command]
    _one_line(_sss(*args), f"--out {tmp_path / 'afile'} is a file")
    assert (tmp_path / "afile").read_text() == "mine\n"


@pytest.mark.parametrize(("command", "mine"), [
    (["relight", "{session}", "--pattern", "checkerboard", "--views", "0", "--out", "{out}"],
     "obj_v0_checkerboard_analytic.png"),
    (["export", "{session}", "--out", "{out}"], "obj/view_000/white.exr"),
])
def test_files_of_the_user_s_named_as_outputs_are_never_replaced(session, tmp_path, command, mine):
    """`sss relight` replaced a file of the user's named as its output (obj_v0_checkerboard_analytic.png), and
    `sss export` the folder obj/view_000 that held the user's white.exr."""
    out = tmp_path / "out"
    (out / mine).parent.mkdir(parents=True)
    (out / mine).write_text("mine\n")
    _one_line(_sss(*[a.format(session=session, out=out) for a in command]),
              f"--out {out} holds files named as the outputs of 'obj' (obj/ or obj_v<view>_...) that no sssphase")
    assert (out / mine).read_text() == "mine\n" and not (out / "sources.json").exists()


@pytest.mark.parametrize(("command", "expected"), [
    (["relight", "{session}", "--pattern", "checkerboard", "--views", " , "], "--views ' , ' names no view"),
    (["geometry", "{session}", "--backend", "analytic", "--views", ","], "--views ',' names no view"),
    (["eval", "relight", "{session}", "--backend", "none", "--views", " , "], "--views ' , ' names no view"),
    (["export", "{session}", "--views", " , "], "--views ' , ' names no view"),
    (["relight", "{session}", "--pattern", "checkerboard", "--views", "0,5"], "has no complete view 5 (complete: 0)"),
    (["eval", "relight", "{session}", "--backend", "none"], "obj view 0 has no reference captures to evaluate against"),
    (["report", "{session}", "--backend", "torch"], "no backend of torch can run: torch needs --decoder"),
    (["report", "{session}", "--backend", "none"], "view 0 of obj has no reference captures to relight against"),
    (["relight", "{session}", "--pattern", "checkerboard", "--resize", "bogus"],  # was ignored for named patterns
     "--resize must be one of fit, fill, stretch, got 'bogus'"),
])
def test_views_and_inputs_are_checked_before_any_work(session, tmp_path, command, expected):
    """`--views 0,5` relit view 0 and then failed on view 5; `--views ,` did nothing and exited 0; `sss report`
    said done without relighting anything."""
    out = tmp_path / "out"
    res = _sss(*[a.format(session=session) for a in command], "--out", str(out))
    _one_line(res, expected)
    assert not any(out.rglob("*.png")) if out.exists() else True


def test_a_black_frame_as_bright_as_the_white_is_refused(tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from test_import import _float_frames

    frames = _float_frames(tmp_path / "f", 1.0)
    np.save(frames / "black.npy", np.load(frames / "white.npy"))  # the wrong file copied
    with pytest.raises(InputError, match=r"the white capture is hardly brighter than the black one"):
        import_folder(frames, tmp_path / "s", "obj", (W, H), patch=16)
    assert not (tmp_path / "s" / "obj").exists()


@pytest.mark.slow
def test_sss_sim_removes_only_what_an_earlier_sim_wrote(tmp_path):
    """A second `sss sim` into one folder leaves none of the first's figures behind; but a scene.json beside
    folders named view0, view1 made it delete those folders whole (a user's files in them too), whoever wrote
    them."""
    (tmp_path / "view1").mkdir()
    (tmp_path / "view1" / "notes.txt").write_text("mine")
    (tmp_path / "scene.json").write_text('{"mine": 1}')
    _one_line(_sss("sim", "--object", "pear", "--views", "1", "--out", str(tmp_path), "--no-decode"),
              f"--out {tmp_path} holds a scene.json that sss sim did not write: give another folder")
    assert (tmp_path / "scene.json").read_text() == '{"mine": 1}' and not (tmp_path / "view0").exists()
    (tmp_path / "scene.json").unlink()
    assert _sss("sim", "--object", "apple", "--views", "2", "--out", str(tmp_path), "--no-decode").returncode == 0
    assert (tmp_path / "view1" / "white.png").is_file()
    assert _sss("sim", "--object", "pear", "--views", "1", "--out", str(tmp_path), "--no-decode").returncode == 0
    assert [p.name for p in (tmp_path / "view1").iterdir()] == ["notes.txt"]  # the earlier run's figures went
    assert (tmp_path / "view1" / "notes.txt").read_text() == "mine"
    assert json.loads((tmp_path / "scene.json").read_text())["object"]["name"] == "pear"
    (tmp_path / "view1" / "notes.txt").unlink()  # none of the first run is left beside the second's
    assert _sss("sim", "--object", "pear", "--views", "1", "--out", str(tmp_path), "--no-decode").returncode == 0
    assert not (tmp_path / "view1").exists()


def test_patterns_are_read_at_their_depth_and_checked_whatever_their_format(tmp_path):
    """A 16-bit colour PNG was read at 8 bits by Pillow; a single-channel float TIFF skipped the range and
    NaN checks (7.0 became 1 in silence)."""
    import cv2
    from PIL import Image

    from sssphase_core.store.imageio import read_pattern

    codes = np.random.default_rng(0).integers(0, 65536, (H, W, 3)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "deep.png"), codes[..., ::-1])
    np.testing.assert_allclose(read_pattern(tmp_path / "deep.png", (W, H)), codes / 65535, atol=1e-6)
    for name, value, expected in (("nan", np.nan, "has NaN or inf"), ("big", 7.0, r"got 0 to 7")):
        data = np.zeros((H, W), np.float32)
        data[3, 3] = value
        Image.fromarray(data, "F").save(tmp_path / f"{name}.tif")
        with pytest.raises(InputError, match=rf"pattern .*{name}\.tif must hold finite values in \[0, 1\].*{expected}"):
            read_pattern(tmp_path / f"{name}.tif", (W, H))


def test_view_folders_that_are_empty_or_skip_numbers_are_named(tmp_path):
    """An empty view_001 was reported as "missing: white, black"; view_000 and view_002 became views 0 and 1 in
    silence; `sss decode` on a folder of views said "24 of 24 PSP frames missing"."""
    import shutil

    sys.path.insert(0, str(Path(__file__).parent))
    from test_import import _float_frames

    frames = _float_frames(tmp_path / "f" / "view_000", 1.0)
    (tmp_path / "f" / "view_001").mkdir()
    with pytest.raises(InputError, match=r"view_001 holds no frame files"):
        import_folder(tmp_path / "f", tmp_path / "s", "obj", (W, H), patch=16)
    _one_line(_sss("decode", str(tmp_path / "f"), "--projector", f"{W}x{H}", "--out", str(tmp_path / "d")),
              "holds view folders: decode one view at a time")
    (tmp_path / "f" / "view_001").rmdir()
    shutil.copytree(frames, tmp_path / "f" / "view_002")
    with pytest.warns(UserWarning, match=r"view folders view_000, view_002 are imported as views 0 to 1 in that order"):
        s = import_folder(tmp_path / "f", tmp_path / "s", "obj", (W, H), patch=16)
    assert s.views() == [0, 1]
