"""`sss import`: frames written by hand (not by our simulator) become a session that relights,
evaluates and trains like a captured one; hostile folders are refused before anything is written."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from sss_process import run_sss

from sssphase_core.capture import import_folder
from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.patterns import capture_plan
from sssphase_core.processing.projector import emitted_light
from sssphase_core.relight.views import load_view
from sssphase_core.store.session import Session

W, H, SPACING, K = 64, 48, 8, 16


def _camera(patterns: np.ndarray) -> np.ndarray:
    """A hand-made rig: camera pixel = projector pixel, albedo 0.8, light spread by a Gaussian (sigma 1.2 px)."""
    light = emitted_light(patterns, 2.2)  # (P, H, W, 3)
    return (gaussian_filter(light, (0, 1.2, 1.2, 0), mode="constant") * 0.8).astype(np.float32)


def _write(folder: Path, key: str, image: np.ndarray, nested: bool, fmt: str = "png") -> None:
    path = folder / (key if nested else key.replace("/", "__"))
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "exr":  # linear float frames, as a lab's HDR pipeline would save them
        from sssphase_core.store.exr import write_exr

        write_exr(path.with_suffix(".exr"), image)
        return
    if fmt == "tiff":  # float32 RGB TIFF, as renderers write (Pillow cannot decode these)
        cv2.imwrite(str(path.with_suffix(".tiff")), np.ascontiguousarray(image[..., ::-1], np.float32))
        return
    u16 = np.round(np.clip(image, 0, 1) * 65535).astype(np.uint16)
    cv2.imwrite(str(path.with_suffix(".png")), cv2.cvtColor(u16, cv2.COLOR_RGB2BGR))


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    plan = capture_plan(W, H, footprints=True, dot_spacing=SPACING, references=("white", "black", "checkerboard"))
    images = _camera(np.stack([f.pattern() for f in plan]))
    folder = tmp_path_factory.mktemp("rig") / "frames"
    for i, (f, img) in enumerate(zip(plan, images, strict=True)):
        _write(folder, f.key, img, nested=f.key.startswith("psp/") and i % 2 == 0,  # both layouts in one folder
               fmt="exr" if i % 3 == 1 else "tiff" if i % 3 == 2 and i % 2 else "png")
    return folder


@pytest.fixture(scope="module")
def handmade(frames, tmp_path_factory) -> Session:
    """The fixture's frames imported once (tests that change a session work on a copy: :func:`_copy`)."""
    return import_folder(frames, tmp_path_factory.mktemp("imported") / "sessions", "handmade", (W, H), patch=K)


def _copy(session: Session, root: Path) -> Session:
    """A copy of ``session`` under ``root``: what an import of the same frames writes there."""
    import shutil

    shutil.copytree(session.path, root / session.name)
    return Session.open(root / session.name)


@pytest.fixture(scope="module")
def clean_psnr(handmade, tmp_path_factory) -> dict[str, float]:
    """``sss eval relight --backend none,measured`` of the clean import: what perturbed frames are held to."""
    return _relit_psnr([handmade], tmp_path_factory.mktemp("clean_eval"))["handmade"]


def test_imported_frames_relight_and_evaluate_like_a_capture(frames, tmp_path):
    s = import_folder(frames, tmp_path / "sessions", "handmade", (W, H), patch=K)
    assert s.validate() == [] and "footprints/crops" in s.arrays(0)
    xp, mask = s.load(0, "corr/xp"), s.load(0, "corr/mask")
    yy, xx = np.mgrid[:H, :W]
    assert mask[8:-8, 8:-8].all() and np.abs(xp - xx)[8:-8, 8:-8].max() < 0.2
    from sssphase_core.relight import load_view

    plan = {f.key: f for f in capture_plan(W, H)}  # the 8 inputs' patterns: what the view calibration relights
    rv = load_view(s, 0)
    np.testing.assert_array_equal(rv.psp_patterns, np.stack([plan[k].pattern() for k in rv.session.manifest["views"]["0"]["psp_keys"]]))
    out = tmp_path / "ev"
    res = run_sss(["eval", "relight", str(s.path), "--backend", "none,measured", "--out", str(out)], timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    psnr = {a["backend"]: a["psnr"] for a in json.loads((out / "relight_eval.json").read_text())["aggregate"]}
    assert psnr["measured"] > psnr["none"] + 3, psnr  # the captured transport explains the blur
    relit = run_sss(["relight", str(s.path), "--pattern", "checkerboard", "--backend", "measured", "--format", "png,exr",
                     "--out", str(tmp_path / "r")], timeout=300)
    assert relit.returncode == 0 and "PSNR" in relit.stdout, relit.stdout + relit.stderr
    from sssphase_core.store.exr import read_exr

    hdr = read_exr(tmp_path / "r" / "handmade_v0_checkerboard_measured.exr")
    png = cv2.imread(str(tmp_path / "r" / "handmade_v0_checkerboard_measured.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert hdr.dtype == np.float32 and hdr.shape == (H, W, 3)
    np.testing.assert_allclose(np.clip(hdr, 0, 1), png / 65535, atol=1 / 65535)


def test_a_failed_import_leaves_nothing_behind(frames, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in (f for f in frames.rglob("*") if f.is_file()):
        target = bad / f.relative_to(frames)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(f.read_bytes())
    (bad / "dots__0_0.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="dots__0_0"):
        import_folder(bad, tmp_path / "sessions", "again", (W, H), patch=K)
    assert not (tmp_path / "sessions" / "again").exists()


def test_an_import_killed_midway_is_replaced_by_the_next_import_of_its_folder_and_says_how(handmade, frames, tmp_path):
    """A killed `sss import` (no cleanup ran) left its session unfinished, and every way on named a fix that does not
    apply (`--resume`, which import has not; `sss capture ... --resume`) or refused the name ("already exists"). The
    unfinished import is now named as one, and importing the same folder again replaces it (it had no complete view
    to keep); another folder's import is still refused the name."""
    from sssphase_core.relight.runner import choose_views

    s = _copy(handmade, tmp_path / "sessions")
    manifest = json.loads((s.path / "manifest.json").read_text())
    manifest["views"]["0"]["status"] = "capturing"  # as a SIGKILL mid-view leaves it
    (s.path / "manifest.json").write_text(json.dumps(manifest))
    s = Session.open(s.path)
    assert s.validate()[0] == "view 0: importing (not imported completely; run the import again)"
    with pytest.raises(InputError, match=r"`sss import` of its folder again completes it"):
        choose_views(s, "")
    other = tmp_path / "other"
    shutil.copytree(frames, other)
    with pytest.raises(InputError, match="already exists"):
        import_folder(other, tmp_path / "sessions", "handmade", (W, H), patch=K)
    with pytest.warns(UserWarning, match="an unfinished import of .* is replaced: none of its views was complete"):
        again = import_folder(frames, tmp_path / "sessions", "handmade", (W, H), patch=K)
    assert again.views() == [0] and not again.validate()


def test_an_interrupted_import_keeps_its_complete_views_and_the_same_import_continues_from_them(frames, tmp_path,
                                                                                                monkeypatch):
    """Ctrl-C (or SIGTERM) in the second view of two removed the whole import, the first view's work with it (hours at
    1080p with dot grids). The complete view now stays; the same import again continues from it without reading it
    again, and an import of the folder with other settings starts afresh and says so."""
    import shutil

    import sssphase_core.capture.importer as importer

    multi = tmp_path / "multi"
    for v in (0, 1):
        shutil.copytree(frames, multi / f"view_00{v}")
    read = importer.FrameLoader.read

    def interrupted_in_view_1(self, path):
        if "view_001" in str(path):
            raise KeyboardInterrupt
        return read(self, path)

    for name in ("same", "other", "edited"):
        monkeypatch.setattr(importer.FrameLoader, "read", interrupted_in_view_1)
        with pytest.raises(KeyboardInterrupt):
            import_folder(multi, tmp_path / "s", name, (W, H), patch=K)
        s = Session.open(tmp_path / "s" / name)
        assert s.views() == [0] and s.status(1) == "interrupted" and not list(s.path.glob(".view_*"))
        monkeypatch.setattr(importer.FrameLoader, "read", read)
    def completed(session_name):  # when view 0 was written
        return Session.open(tmp_path / "s" / session_name).manifest["views"]["0"]["completed"]

    before = {name: completed(name) for name in ("same", "other", "edited")}
    with pytest.warns(UserWarning, match=r"continuing the unfinished import of .*: view 0 already imported is kept"):
        again = import_folder(multi, tmp_path / "s", "same", (W, H), patch=K)
    assert again.views() == [0, 1] and not again.validate() and completed("same") == before["same"]
    with pytest.warns(UserWarning, match=r"an unfinished import of .* is replaced: it was made with other settings"):
        other = import_folder(multi, tmp_path / "s", "other", (W, H), patch=K, gamma=2.0)
    assert other.views() == [0, 1] and other.manifest["plan"]["gamma"] == 2.0 and completed("other") > before["other"]
    white = next(multi.glob("view_000/white.*"))  # view 0's frames replaced after it was imported: it was kept,
    white.write_bytes(white.read_bytes())  # decoded from the old ones
    os.utime(white, ns=(time.time_ns(), time.time_ns() + 10**9))
    with pytest.warns(UserWarning, match=r"an unfinished import of .* is replaced: it was made with other settings"):
        edited = import_folder(multi, tmp_path / "s", "edited", (W, H), patch=K)
    assert edited.views() == [0, 1] and completed("edited") > before["edited"]


def test_a_full_disk_during_an_import_leaves_nothing_and_names_the_imports_own_fix(frames, tmp_path, monkeypatch):
    """The disk filling midway said "free some space and rerun with --resume", an option `sss import` has not."""
    import errno

    import sssphase_core.store.session as store

    def full(name):
        if name == "psp":
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store, "FAULT_HOOK", full)
    with pytest.raises(DataError, match=r"disk full while writing psp of view 0 in .*: free some space and run the "
                                        r"import again$"):
        import_folder(frames, tmp_path / "sessions", "full", (W, H), patch=K)
    assert not (tmp_path / "sessions" / "full").exists()


def _float_frames(folder: Path, scale: float, keys: tuple[str, ...] = ("psp/", "white", "black")) -> Path:
    """The hand-made rig's PSP, white and black frames as float .npy, in units ``scale`` times the camera's
    (a path tracer's radiance is in its own units)."""
    plan = [f for f in capture_plan(W, H, references=("white", "black")) if f.key.startswith(keys)]
    folder.mkdir(parents=True)
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        np.save(folder / (f.key.replace("/", "__") + ".npy"), img * np.float32(scale))
    return folder


@pytest.mark.slow
def test_a_noisy_capture_that_fills_the_frame_is_denoised_by_its_own_noise_floor(tmp_path):
    """Every crop's ring lies in another dot's cell when the surface fills the view (here every pixel):
    the transport's noise floor is read inside the crops' own cells (it read 0, and nothing was denoised:
    measured relit the checkerboard at 23.2 dB, 26.8 with the floor)."""
    plan = capture_plan(W, H, footprints=True, dot_spacing=SPACING, references=("white", "black", "checkerboard"))
    rng, sigma = np.random.default_rng(1), 0.01
    folder = tmp_path / "noisy"
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):  # independent noise per frame
        _write(folder, f.key, img + rng.normal(0, sigma, img.shape).astype(np.float32), nested=False, fmt="exr")
    s = import_folder(folder, tmp_path / "sessions", "noisy", (W, H), patch=K)
    assert s.manifest["views"]["0"]["transport"]["noise"] == pytest.approx(sigma, rel=0.2)
    out = tmp_path / "ev"
    res = run_sss(["eval", "relight", str(s.path), "--backend", "none,measured", "--out", str(out)], timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    data = json.loads((out / "relight_eval.json").read_text())
    psnr = {a["backend"]: a["psnr"] for a in data["aggregate"]}
    assert psnr["measured"] > 25 > psnr["none"] + 10, psnr
    (row,) = [r for r in data["rows"] if r["backend"] == "measured"]  # the noise mask the view's own fringes chose
    fit = row["denoise_fit_psnr"]
    assert set(fit) == {"1.0", "2.0"} and fit[str(row["denoise_smoothing"])] == max(fit.values()), row
    relit = run_sss(["relight", str(s.path), "--pattern", "checkerboard", "--backend", "measured",
                     "--out", str(tmp_path / "r")], timeout=300)
    assert f"captured transport denoised with the {row['denoise_smoothing']:g} px noise mask" in relit.stdout, relit.stdout


def test_float_frames_in_any_units_decode_like_camera_units(tmp_path):
    ref = import_folder(_float_frames(tmp_path / "unit", 1.0), tmp_path / "s", "unit", (W, H), patch=K)
    for scale in (1e-4, 1e3):
        s = import_folder(_float_frames(tmp_path / f"x{scale}", scale), tmp_path / "s", f"x{scale:g}", (W, H), patch=K)
        assert s.manifest["rig"]["frame_scale"] == pytest.approx(1 / (0.8 * scale), rel=1e-3)  # white's top at 1
        np.testing.assert_array_equal(s.load(0, "corr/mask"), ref.load(0, "corr/mask"))
        np.testing.assert_allclose(s.load(0, "corr/xp"), ref.load(0, "corr/xp"), atol=1e-3, equal_nan=True)
    assert ref.manifest["rig"]["frame_scale"] == 1.0  # camera units already: left as they are


def test_frames_where_nothing_decodes_or_too_small_are_refused_naming_why(tmp_path):
    flat = _float_frames(tmp_path / "flat", 1.0)
    for f in flat.glob("psp__*"):
        np.save(f, np.full((H, W, 3), 0.4, np.float32))  # no fringes: every pixel has zero modulation
    with pytest.raises(InputError, match=r"no camera pixel decoded \(100% low modulation\): .*; lit pixels without "
                                         r"fringes: the finest period \(\d+ projector px\) may be too fine"):
        import_folder(flat, tmp_path / "s", "flat", (W, H), patch=K)
    # 8-bit frames of a camera exposed far too long: every fringe clipped at the top code, which the
    # decoder sees as no modulation; the line says clipped, not "low modulation ... above the noise"
    plan = capture_plan(W, H, references=("white", "black"))
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        path = tmp_path / "clipped" / (f.key.replace("/", "__") + ".png")
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), np.round(np.clip(img * (40 if f.key != "black" else 1), 0, 1) * 255).astype(np.uint8))
    with pytest.raises(InputError, match=r"no camera pixel decoded: \d+% of the fringe frames' values sit at the files' top "
                                         r"code \(the camera clipped them"):
        import_folder(tmp_path / "clipped", tmp_path / "s", "clipped", (W, H), patch=K)
    no_black = tmp_path / "no_black"
    no_black.mkdir()
    for f in flat.glob("*.npy"):
        if f.name != "black.npy":
            (no_black / f.name).write_bytes(f.read_bytes())
    with pytest.raises(InputError, match=r"\(missing: black\); a render without the projector's black light has an all-zero"):
        import_folder(no_black, tmp_path / "s", "no_black", (W, H), patch=K)
    for name, make, why in (("dangling", lambda f: f.symlink_to(f.with_name("gone.npy")), "is a broken symbolic link"),
                            ("fifo", os.mkfifo, r"is not a regular file \(a FIFO or a device\)")):
        folder = tmp_path / name
        folder.mkdir()
        for f in flat.glob("*.npy"):
            if f.name != "white.npy":
                (folder / f.name).write_bytes(f.read_bytes())
        make(folder / "white.npy")  # said "missing: white"
        with pytest.raises(InputError, match=why):
            import_folder(folder, tmp_path / "s", name, (W, H), patch=K)
    from sssphase_core.capture.psp_folder import read_psp_folder

    fifo = sorted((tmp_path / "fifo").glob("psp__x__*.npy"))[1]
    fifo.unlink()
    os.mkfifo(fifo)  # `sss decode` skipped it and said "PSP frames x, period P have shifts [0, 2, 3]"
    with pytest.raises(InputError, match=rf"{fifo.name} is not a regular file \(a FIFO or a device\)"):
        read_psp_folder(tmp_path / "fifo", f"{W}x{H}")
    for gain, why in ((100.0, r"psp__x__p\S+\.npy: \d+(\.\d)?x brighter than the white capture"),
                      (0.01, r"the fringe set's mean is 0.0\d*x the white capture's level")):
        mixed = tmp_path / f"mixed{gain:g}"  # fringes in other units than the white: imported with VALID pixels
        mixed.mkdir()
        for f in _float_frames(tmp_path / f"good{gain:g}", 1.0).glob("*.npy"):
            np.save(mixed / f.name, np.load(f) * np.float32(gain if f.name.startswith("psp") else 1.0))
        with pytest.raises(InputError, match=why):
            import_folder(mixed, tmp_path / "s", f"mixed{gain:g}", (W, H), patch=K)
    named = tmp_path / "named"  # view_abc was imported as the next view, renumbered in silence
    for view in ("view_000", "view_abc"):
        (named / view).mkdir(parents=True)
        for f in _float_frames(tmp_path / f"v{view}", 1.0).glob("*.npy"):
            (named / view / f.name).write_bytes(f.read_bytes())
    with pytest.raises(InputError, match=r"view_abc is no view folder: name view folders view_NNN"):
        import_folder(named, tmp_path / "s", "named", (W, H), patch=K)
    (named / "view_abc").rename(named / "view_001")
    for other, why in (("View_002", "is no view folder"), ("view-002", "is no view folder"),
                       ("view 002", "is no view folder"), ("extra_view", "holds frames but is no view folder")):
        (named / "view_001").rename(named / other)  # (each was left out in silence)
        with pytest.raises(InputError, match=rf"{other} {why}: name (view folders view_NNN|it view_NNN)"):
            import_folder(named, tmp_path / "s", "named", (W, H), patch=K)
        (named / other).rename(named / "view_001")
    odd = tmp_path / "odd"  # one fringe frame of another size: summing its set was a broadcasting error
    odd.mkdir()
    for f in flat.glob("*.npy"):
        (odd / f.name).write_bytes(f.read_bytes())
    last = sorted(odd.glob("psp__y__*.npy"))[-1]
    np.save(last, np.load(last)[: H // 2, : W // 2])
    with pytest.raises(InputError, match=rf"{last.name} is {W // 2}x{H // 2}, the other frames {W}x{H}"):
        import_folder(odd, tmp_path / "s", "odd", (W, H), patch=K)
    huge = tmp_path / "huge"
    huge.mkdir()
    for f in flat.glob("*.npy"):
        np.save(huge / f.name, np.load(f).astype(np.float64) * 1e40)  # finite, beyond float32: "NaN or infinite"
    with pytest.raises(InputError, match=r"holds values up to [0-9.]+e\+\d+, beyond what float32 frames hold"):
        import_folder(huge, tmp_path / "s", "huge", (W, H), patch=K)
    (tmp_path / "folder" / "white.png").mkdir(parents=True)  # made by mistake: it said "missing: white, black"
    with pytest.raises(InputError, match="white.png is a folder, not a frame file"):
        import_folder(tmp_path / "folder", tmp_path / "s", "folder", (W, H), patch=K)
    tiny = tmp_path / "tiny"
    tiny.mkdir()
    for f in flat.glob("*.npy"):
        np.save(tiny / f.name, np.full((4, 4, 3), 0.5, np.float32))
    logo = tmp_path / "logo"
    logo.mkdir()
    for f in _float_frames(tmp_path / "good", 1.0).glob("*.npy"):
        (logo / f.name).write_bytes(f.read_bytes())
    np.save(logo / "ref__logo.npy", np.zeros((H, W, 3), np.float32))  # a reference without its projected image
    with pytest.raises(InputError, match="the image projected for it is needed as pattern__logo.png"):
        import_folder(logo, tmp_path / "s", "logo", (W, H), patch=K)
    with pytest.raises(InputError, match="4x4: smaller than a camera frame"):
        import_folder(tiny, tmp_path / "s", "tiny", (W, H), patch=K)
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())


def _png8(folder: Path, scale: float) -> Path:
    """The hand-made rig's PSP, white and black frames as 8-bit PNGs of linear codes times ``scale``."""
    plan = [f for f in capture_plan(W, H, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    folder.mkdir(parents=True)
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        path = folder / (f.key.replace("/", "__") + ".png")
        cv2.imwrite(str(path), np.round(np.clip(img * scale, 0, 1) * 255).astype(np.uint8)[..., ::-1])
    return folder


def test_refusals_of_an_import_name_the_view_and_the_exposure(tmp_path):
    """Two refusals that sent a lab the wrong way (a probe's findings): missing PSP frames named no view folder;
    frames far too dark were told only "the frames must be linear images ... above the noise" (12-bit codes in
    16-bit files read the same way)."""
    views = tmp_path / "views"
    shutil.copytree(_png8(tmp_path / "v", 1.0), views / "view_000")
    shutil.copytree(tmp_path / "v", views / "view_001")
    coarsest = sorted({int(f.name.split("__")[2][1:]) for f in (views / "view_001").glob("psp__y__*")})[-1]
    for f in (views / "view_001").glob(f"psp__y__p{coarsest}__*"):
        f.unlink()
    with pytest.raises(InputError, match=rf"^{re.escape(str(views / 'view_001'))}: 4 PSP frames missing"):
        import_folder(views, tmp_path / "s", "missing", (W, H), patch=K)
    for f in (views / "view_001").glob(f"psp__x__p{coarsest}__*"):  # a whole period gone: it imported, unwrapping less
        f.unlink()
    with pytest.raises(InputError, match=rf"^{re.escape(str(views / 'view_001'))}: its PSP frames have periods .* but "
                                         rf".*view_000 has periods .*{coarsest} with 4 shifts: the views of an import share"):
        import_folder(views, tmp_path / "s", "missing", (W, H), patch=K)
    dark = tmp_path / "dark"  # 16-bit integer frames at 2% of their range (float ones are scaled to their white)
    plan = [f for f in capture_plan(W, H, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        _write(dark, f.key, img * 0.02, nested=False)
    with pytest.raises(InputError, match=r"no camera pixel decoded \(.*\): the white's level is 0\.0\d+ in camera units "
                                         r"where white is about 1, .*: expose the camera longer; if the files hold a 10-, "
                                         r"12- or 14-bit camera's codes in 16 bits, import with --bit-depth 10, 12 or 14"):
        import_folder(dark, tmp_path / "s", "dark", (W, H), patch=K)


def test_a_cameras_12_bit_codes_in_16_bit_files_import_with_bit_depth(tmp_path):
    """A 12-bit camera's codes in the low bits of 16-bit PNGs read as light at most 1/16 of white: a view that
    decoded was relit and scored against a white of 1 it never reached (57 dB where the same frames at full range
    give 42.8), and there was no way to say the camera's word but shifting the files. ``--bit-depth 12`` puts the
    top code at 1; without it the import says so; codes above the word are refused, as is the option on float
    frames."""
    plan = [f for f in capture_plan(W, H, references=("white", "black", "checkerboard"))]
    images = _camera(np.stack([f.pattern() for f in plan]))
    full, low = tmp_path / "full", tmp_path / "low"
    for folder, top in ((full, 65535), (low, 4095)):
        folder.mkdir()
        for f, img in zip(plan, images, strict=True):
            codes = np.round(np.clip(img, 0, 1) * top).astype(np.uint16)
            cv2.imwrite(str(folder / (f.key.replace("/", "__") + ".png")), cv2.cvtColor(codes, cv2.COLOR_RGB2BGR))
    ref = import_folder(full, tmp_path / "s", "full", (W, H), patch=K)
    with pytest.warns(UserWarning, match=r"white.png: the white's level is 0\.0\d+ of the 16-bit files' range \([\d,]+ of "
                                         r"65,535\): if the camera gives 12-bit codes .* import with --bit-depth 12"), \
            pytest.raises(InputError, match=r"no camera pixel decoded .* import with --bit-depth 10, 12 or 14"):
        import_folder(low, tmp_path / "s", "unsaid", (W, H), patch=K, encoding="linear")  # (this rig: all too faint)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to warn of: the camera's word is said
        said = import_folder(low, tmp_path / "s", "said", (W, H), patch=K, encoding="linear", bit_depth=12)
    assert said.manifest["rig"]["frame_bit_depth"] == 12
    assert said.manifest["rig"]["frame_scale"] == pytest.approx(65535 / 4095)
    white, white_ref = said.load(0, "white"), ref.load(0, "white")
    assert np.abs(white - white_ref).max() < 1.5 / 4095  # the same light, to the 12-bit step
    assert said.load(0, "corr/mask").sum() >= 0.99 * ref.load(0, "corr/mask").sum()
    with pytest.raises(InputError, match=r"holds codes up to [\d,]+, above a 10-bit camera's top code 1,023: the codes are "
                                         r"wider or already shifted"):
        import_folder(low, tmp_path / "s", "ten", (W, H), patch=K, encoding="linear", bit_depth=10)
    with pytest.raises(InputError, match=r"--bit-depth must be one of 8, 10, 12, 14, 16 .* got 11"):
        import_folder(low, tmp_path / "s", "eleven", (W, H), patch=K, encoding="linear", bit_depth=11)
    with pytest.raises(InputError, match=r"--bit-depth is for integer frame files .* these frames are float"):
        import_folder(_float_frames(tmp_path / "float", 1.0), tmp_path / "s", "float", (W, H), patch=K, bit_depth=12)
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["full", "said"]  # refused: nothing written


@pytest.mark.parametrize(("name", "expected"), [
    ("psp__x__p.__s0.png", "no frame name"),
    ("dots__a_b.png", "no frame name"),
    ("psp__x__p16__s99999999.png", "no frame name"),
    ("psp__x__p16__s7.png", "shifts"),
    ("psp_x_p16_s0.png", "no frame name"),  # a misspelt frame is refused, not skipped with the thumbnails
    ("White_old.png", "no frame name"),
])
def test_hostile_frame_names_are_refused_before_any_work(frames, tmp_path, name, expected):
    folder = tmp_path / "f"
    folder.mkdir()
    for key in ("white", "black", *(f"psp__{o}__p16__s{n}" for o in "xy" for n in range(4))):
        np.save(folder / f"{key}.npy", np.zeros((H, W, 3), np.float32))
    np.save(folder / name.replace(".png", ".npy"), np.zeros((H, W, 3), np.float32))
    with pytest.raises(InputError, match=expected):
        import_folder(folder, tmp_path / "sessions", "hostile", (W, H))
    assert not (tmp_path / "sessions" / "hostile").exists()


def test_images_beside_the_frames_are_skipped_with_one_warning_naming_them(tmp_path):
    """A lab's folder holds more than frames: a thumbnail, a mask, a phone photo of the rig. They refused the
    whole import ("'thumbnail' is no frame name"); now they are skipped, named in one warning, and the session is
    the one the frames alone give."""
    alone = import_folder(_float_frames(tmp_path / "alone", 1.0), tmp_path / "s", "alone", (W, H), patch=K)
    folder = _float_frames(tmp_path / "f", 1.0)
    cv2.imwrite(str(folder / "thumbnail.png"), np.zeros((8, 8, 3), np.uint8))
    (folder / "IMG_0001.jpg").write_bytes(b"\xff\xd8 not even a JPEG")
    np.save(folder / "mask.npy", np.ones((H, W), bool))
    with pytest.warns(UserWarning, match=r"skipped 3 images whose name is no frame's \(IMG_0001.jpg, mask.npy, "
                                         r"thumbnail.png\)"):
        with_others = import_folder(folder, tmp_path / "s", "others", (W, H), patch=K)
    a, b = load_view(alone, 0), load_view(with_others, 0)
    assert np.array_equal(a.proj.mask, b.proj.mask) and np.array_equal(a.white, b.white)


def test_a_pickled_npy_is_refused(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    for key in ("black", *(f"psp__{o}__p{p}__s{n}" for o in "xy" for p in (16, 64) for n in range(4))):
        np.save(folder / f"{key}.npy", np.zeros((H, W, 3), np.float32))
    np.save(folder / "white.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="white.npy") as err:
        import_folder(folder, tmp_path / "sessions", "pickled", (W, H))
    assert "never loaded" in str(err.value) and "allow_pickle" not in str(err.value)  # numpy's text invited it


def _sss_import(folder: Path, out: Path, *options: str) -> subprocess.CompletedProcess[str]:
    return run_sss(["import", str(folder), "--object", "o", "--projector", f"{W}x{H}", "--out", str(out), *options], timeout=120)


def _one_line_error(res: subprocess.CompletedProcess[str], expected: str) -> None:
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out and "internal error" not in out and "aborted" not in out, out
    assert len(out.strip().splitlines()) == 1 and expected in out, out


@pytest.mark.parametrize(("option", "value", "expected"), [
    ("--patch", "-1", "--patch (the footprint crop size K) must be 9 to 256 px, got -1"),
    ("--patch", "100000", "must be 9 to 256 px, got 100000"), ("--patch", "1", "must be 9 to 256 px, got 1"),
    ("--gamma", "nan", "--gamma (the projector's gamma) must be a number in [0.3, 5] (as a rig file's), got nan"),
    ("--gamma", "0", "must be a number in [0.3, 5] (as a rig file's), got 0.0"),
    ("--gamma", "inf", "must be a number in [0.3, 5] (as a rig file's), got inf"),
])
def test_import_options_out_of_range_are_one_line_before_any_work(tmp_path, option, value, expected):
    folder = _float_frames(tmp_path / "f", 1.0)
    _one_line_error(_sss_import(folder, tmp_path / "s", option, value), expected)
    assert not (tmp_path / "s").exists()


def test_an_empty_npy_frame_is_one_line_naming_it(tmp_path):
    folder = _float_frames(tmp_path / "f", 1.0)
    (folder / "black.npy").write_bytes(b"")  # numpy: EOFError, which click turned into a bare "Aborted"
    _one_line_error(_sss_import(folder, tmp_path / "s"), f"{folder / 'black.npy'}: empty or truncated .npy file")


@pytest.mark.parametrize(("white", "expected"), [
    ("gif", "white.gif: .gif is not a frame format the importer reads"),  # said "missing: white"
    ("pages", "white.tif holds 2 images (a multi-page or animated file)"),  # only the first page was imported
    ("bool", "white.npy holds bool values, not an image"),
    ("int8", "white.npy holds signed int8 codes"),  # -128 / 127 would be negative light
    ("cut", "white.npy: empty or truncated .npy file (the header promises more data than it holds)"),
])
def test_white_captures_the_importer_would_misread_are_refused_naming_them(tmp_path, white, expected):
    """Found by hand: each of these imported without a word (or with a misleading one)."""
    from PIL import Image

    folder = _float_frames(tmp_path / "f", 1.0)
    light = np.load(folder / "white.npy")
    (folder / "white.npy").unlink()
    codes = (np.clip(light, 0, 1) * 255).astype(np.uint8)
    if white == "gif":
        Image.fromarray(codes).save(folder / "white.gif")
    elif white == "pages":
        Image.fromarray(codes).save(folder / "white.tif", save_all=True, append_images=[Image.fromarray(codes)])
    elif white == "bool":
        np.save(folder / "white.npy", light > 0.1)
    elif white == "int8":
        np.save(folder / "white.npy", codes.astype(np.int8) // 2)
    else:
        np.save(folder / "white.npy", light)
        data = (folder / "white.npy").read_bytes()
        (folder / "white.npy").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=re.escape(expected)):
        import_folder(folder, tmp_path / "s", "o", (W, H), patch=K)
    assert not (tmp_path / "s" / "o").exists()


def test_an_out_folder_that_is_a_broken_link_is_one_line(tmp_path):
    """It said "cannot create the session folder ...: File exists"."""
    folder = _float_frames(tmp_path / "f", 1.0)
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    _one_line_error(_sss_import(folder, tmp_path / "gone"), f"--out {tmp_path / 'gone'} is a broken symbolic link")
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    _one_line_error(_sss_import(folder, tmp_path / "loop"), f"--out {tmp_path / 'loop'} is a symbolic link loop")


def test_an_empty_npy_pattern_or_reference_is_one_line_naming_it(tmp_path):
    s = import_folder(_float_frames(tmp_path / "f", 1.0), tmp_path / "sessions", "plain", (W, H))
    zero = tmp_path / "zero.npy"
    zero.write_bytes(b"")
    for args in (["relight", str(s.path), "--pattern", str(zero), "--backend", "none", "--out", str(tmp_path / "r")],
                 ["capture", "--object", "apple", "--reference", str(zero), "--out", str(tmp_path / "c")]):
        res = run_sss([*args], timeout=120)
        _one_line_error(res, f"{zero}: empty or truncated .npy file")  # not click's bare "Aborted"
    assert not (tmp_path / "c").exists()  # refused before a daemon was started for it


@pytest.mark.parametrize("array", [np.float32(1.0), np.ones(W, np.float32), np.ones((0, W), np.float32)],
                         ids=["0-d", "1-d", "empty"])
def test_an_npy_frame_without_an_image_shape_is_one_line_wherever_it_is_read(tmp_path, array):
    """A 0-d .npy frame (np.save of a scalar) was an internal error (IndexError) in sss import and sss decode."""
    folder = _float_frames(tmp_path / "f", 1.0)
    np.save(folder / "white.npy", array)
    said = f"{folder / 'white.npy'} has shape {array.shape}: expected (H, W) or (H, W, 3)"
    _one_line_error(_sss_import(folder, tmp_path / "s"), said)
    np.save(folder / "white.npy", np.load(tmp_path / "f" / "black.npy"))
    odd = sorted(folder.glob("psp__*.npy"))[0]
    np.save(odd, array)
    said = f"{odd} has shape {array.shape}: expected (H, W) or (H, W, 3)"
    res = run_sss(["decode", str(folder), "--projector", f"{W}x{H}", "--out", str(tmp_path / "d")])
    out = res.stdout + res.stderr  # (after its progress bar: the frames before it were read)
    assert res.returncode == 2 and "Traceback" not in out and out.strip().splitlines()[-1] == f"error: {said}", out
    _one_line_error(run_sss(["relight", str(import_folder(_float_frames(tmp_path / "g", 1.0), tmp_path / "t", "o",
                                                           (W, H)).path), "--pattern", str(odd), "--out",
                             str(tmp_path / "r")]), said)
    assert not (tmp_path / "s").exists() and not (tmp_path / "r").exists()


def test_report_refuses_unknown_backends_and_foreign_decoders_in_one_line(tmp_path):
    s = import_folder(_float_frames(tmp_path / "f", 1.0), tmp_path / "sessions", "plain", (W, H))
    evil = tmp_path / "evil.pt"
    evil.write_bytes(b"not a checkpoint")
    for options, expected in ((["--backend", "bogus"], "unknown backend 'bogus'; available: analytic"),
                              (["--backend", "torch", "--decoder", str(evil)], f"{evil} is not a checkpoint file"),
                              (["--pretrain", str(evil)], f"{evil} is not a checkpoint file")):
        res = run_sss(["report", str(s.path), *options, "--out", str(tmp_path / "rep")], timeout=300)
        _one_line_error(res, expected)  # was exit 0, "done", with the problem only inside the page
        assert not (tmp_path / "rep").exists()


def test_a_session_exports_to_exr_bit_exactly(handmade, tmp_path):
    from sssphase_core.store.exr import read_exr

    s = _copy(handmade, tmp_path / "sessions")
    res = run_sss(["export", str(s.path), "--out", str(tmp_path / "x")], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    view = tmp_path / "x" / "handmade" / "view_000"
    psp = s.load(0, "psp")
    for i in range(len(psp)):
        assert read_exr(view / "psp" / f"{i:02d}.exr").tobytes() == psp[i].astype(np.float32).tobytes()
    # which fringe each file holds (the numbers alone did not say): x shifts, then y shifts of the finest period
    import OpenEXR

    keys = [line.split(",")[1] for line in (view / "psp" / "keys.csv").read_text().splitlines()[1:]]
    assert [k.rsplit("/", 1)[1] for k in keys] == [f"s{n}" for n in range(4)] * 2 and keys[0].startswith("psp/x/")
    with OpenEXR.File(str(view / "psp" / "05.exr")) as f:
        assert f.header()["sssphase_key"] == keys[5] and keys[5].startswith("psp/y/")
    assert read_exr(view / "white.exr").tobytes() == s.load(0, "white").astype(np.float32).tobytes()
    crops, pixels = s.load(0, "footprints/crops"), s.load(0, "footprints/pixels")
    mosaic = read_exr(view / "footprints_crops.exr")
    cols = mosaic.shape[1] // K
    rows = np.loadtxt(view / "footprints_pixels.csv", delimiter=",", ndmin=2)
    assert len(rows) == len(crops) and (rows == pixels).all()
    for i in (0, len(crops) // 2, len(crops) - 1):
        r, c = divmod(i, cols)
        assert np.array_equal(mosaic[r * K:(r + 1) * K, c * K:(c + 1) * K], crops[i].astype(np.float32))
    dots = s.load(0, "transport/crops")  # the captured transport `measured` relights with was left out in silence
    mosaic = read_exr(view / "transport_crops.exr")
    cols = mosaic.shape[1] // K
    r, c = divmod(len(dots) - 1, cols)
    assert np.array_equal(mosaic[r * K:(r + 1) * K, c * K:(c + 1) * K], dots[-1].astype(np.float32))
    assert len(np.loadtxt(view / "transport_dots.csv", delimiter=",", ndmin=2)) == len(dots)


def test_viz_footprints_shows_the_captured_crops_next_to_a_model(handmade, tmp_path):
    s = _copy(handmade, tmp_path / "sessions")
    out = tmp_path / "fp.png"
    res = run_sss(["viz", "footprints", str(s.path), "--backend", "captured,analytic,none", "--pixels", "3",
                   "--out", str(out)], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert out.is_file() and (tmp_path / "fp_profiles.png").is_file() and "captured, analytic, none at 3 pixels" in res.stdout

    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import footprints_at

    px = np.asarray(s.load(0, "footprints/pixels"))[:2]
    fps = footprints_at(load_view(s, 0), px, ["captured", "none"])
    assert fps["captured"].shape == fps["none"].shape == (2, K, K, 3)
    assert np.array_equal(fps["captured"][1], np.asarray(s.load(0, "footprints/crops"))[1])
    assert np.count_nonzero(fps["none"].sum(-1)) == 2  # one delta per pixel, padded to K


def test_sss_report_on_a_users_own_session(handmade, tmp_path):
    s = _copy(handmade, tmp_path / "sessions")
    res = run_sss(["report", str(tmp_path / "sessions"), "--backend", "none,measured,torch", "--out", str(tmp_path / "rep")],
                  timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "backend torch left out: no --decoder" in res.stdout  # (it was left out of the tables without a word)
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "torch: no --decoder" in page
    assert "<h1>sssphase report</h1>" in page and "Captured sessions" in page
    assert "measured PSNR" in page and "handmade" in page
    assert "no footprint model among the backends" in page and "kNN table: not available" in page  # said, not left out
    config = page[page.index("<h2>Configuration</h2>"):page.index("<h2>Timings</h2>")]
    assert "not given" in config and "checkerboard" in config and "stripes_x" not in config  # what was given,
    assert "pretrain_epochs" not in config and "none given" in config  # not the demo's built-in settings
    assert [p.name for p in (tmp_path / "rep" / "img").glob("*compare.png")]
    assert "[relight] done" in res.stdout
    assert "the simulator's exact footprints" not in page and "blend</code> weighs" not in page  # (not run here)
    assert "<code>measured</code> splats the session's captured light transport" in page
    timings = page[page.index("<h2>Timings</h2>"):]  # the sessions given were not made here (they showed "done 0 s")
    assert "test_sessions</td><td class='l'>given (not run here)" in timings, timings
    bad = run_sss(["report", str(s.path), "--view", "3", "--out", str(tmp_path / "r2")], timeout=120)
    assert bad.returncode == 2 and "view 3 is not complete" in bad.stderr and "Traceback" not in bad.stderr


def test_geometry_of_an_imported_session_triangulates_only_with_the_rigs_calibration(handmade, tmp_path):
    """Without --calibration, `sss geometry` says how to get points and writes none; with a calibration file of
    another rig (the simulated one's, for this hand-made camera = projector mapping) it writes them and says that
    the rays miss each other, with the question to ask."""
    from sssphase_core.sim import rig_preset, stereo_calibration

    res = run_sss(["geometry", str(handmade.path), "--out", str(tmp_path / "g"), "--mesh", "--refine-axis"], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "note: no points triangulated: give --calibration FILE" in res.stdout
    assert "note: no mesh written: meshing joins the 3D points, which need --calibration" in res.stdout
    assert "note: the axis was not refined: that needs the 3D points of two or more turntable views" in res.stdout
    folder = tmp_path / "g" / "handmade" / "view_000"
    assert "points" not in np.load(folder / "correspondence_for_geometry.npz").files and not (folder / "points.ply").exists()
    assert cv2.imread(str(folder / "shift.png")) is not None  # the shift along the baseline, without depth
    c = stereo_calibration(rig_preset("cpu"))
    calibration = tmp_path / "calibration.yml"
    fs = cv2.FileStorage(str(calibration), cv2.FILE_STORAGE_WRITE)
    for name, value in (("cam_K", c.camera_matrix), ("proj_K", c.projector_matrix), ("R", c.rotation), ("T", c.translation)):
        fs.write(name, value)
    fs.release()
    res = run_sss(["geometry", str(handmade.path), "--calibration", str(calibration), "--out", str(tmp_path / "h")], timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "rays miss each other by" in res.stdout and "is the calibration this rig's" in res.stdout, res.stdout
    assert (tmp_path / "h" / "handmade" / "view_000" / "points.ply").exists() and "the calibration's unit" in res.stdout
    again = run_sss(["geometry", str(handmade.path), "--out", str(tmp_path / "h")], timeout=120)  # without a calibration
    assert again.returncode == 0 and not (tmp_path / "h" / "handmade" / "view_000" / "points.ply").exists()  # (stale)
    bad = run_sss(["geometry", str(handmade.path), "--calibration", str(tmp_path), "--out", str(tmp_path / "i")], timeout=120)
    assert bad.returncode == 2 and "a folder, not a calibration file" in bad.stderr and "Traceback" not in bad.stderr
    assert not (tmp_path / "i").exists()  # refused before any work


def test_sss_views_depth_of_an_imported_session_and_its_live_decode_need_the_rigs_calibration(handmade):
    """`sss view`'s depth and surface maps: an imported session has no calibration of its own, so without
    --calibration the map is refused in one line saying how to get one, and the live decode of a rig that is not
    simulated carries that line instead of a depth map; with a calibration they are the points it triangulates.
    The hand-made frames map each camera pixel to the same projector pixel, which a projector whose principal
    point lies 40 px right of the camera's, 60 mm to the camera's right, sees as a wall at fx * 60 / 40 mm (the
    edge pixels' projector points, 0.54 px off, within 1.4%)."""
    pytest.importorskip("starlette")
    import base64

    from sssphase_core.capture.live import LiveDecode
    from sssphase_core.capture.plan import RigSpec
    from sssphase_core.processing.triangulation import StereoCalibration
    from sssphase_view.app import ViewState, _decode_message, session_map_png, session_points
    from sssphase_view.live import LiveRig

    state = ViewState(token="t", out=handmade.path.parent / "view_out", sessions=handmade.path.parent,
                      live=LiveRig(RigSpec("usb:cam", "hdmi:proj", None)))
    with pytest.raises(InputError, match=r"^no camera-projector calibration for depth: start sss view with --calibration FILE"):
        session_map_png(state, "handmade", 0, "depth")
    with pytest.raises(InputError, match="unknown map 'points'; choose .*depth, surface"):
        session_map_png(state, "handmade", 0, "points")
    with pytest.raises(InputError, match="^no camera-projector calibration for depth"):
        session_points(state, "handmade", 0)
    fx = 80.0
    camera = np.array([[fx, 0, (W - 1) / 2], [0, fx, (H - 1) / 2], [0, 0, 1]])
    projector = camera + np.array([[0, 0, 40.0], [0, 0, 0], [0, 0, 0]])
    state.calibration = StereoCalibration(camera, np.zeros(0), projector, np.zeros(0), np.eye(3), np.array([-60.0, 0, 0]))
    state.calibration_path = Path("rig.yml")
    png, lo, hi, unit = session_map_png(state, "handmade", 0, "depth")
    assert lo == pytest.approx(fx * 60 / 40, rel=0.015) and hi == pytest.approx(fx * 60 / 40, rel=0.015), (lo, hi)
    assert unit.startswith("calibration units from the camera (calibration rig.yml, reprojection 0.0")
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (H, W, 3)
    png, _, _, unit = session_map_png(state, "handmade", 0, "surface")
    grey = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    inner = grey[8:-8, 8:-8]
    assert unit.startswith("surface lit from above left") and inner.min() == inner.max() > 150  # a flat wall, lit evenly
    cloud = session_points(state, "handmade", 0, max_points=500)
    xyz = np.frombuffer(base64.b64decode(cloud["xyz"]), np.float32).reshape(-1, 3)
    assert cloud["count"] == len(xyz) == 500 and cloud["views"] == [0] and "view 0; calibration rig.yml" in cloud["which"]
    assert np.median(xyz[:, 2]) == pytest.approx(fx * 60 / 40, rel=0.01)  # the wall, at the depth above

    mask = handmade.load(0, "corr/mask").astype(bool)
    xp, yp = (np.where(mask, handmade.load(0, f"corr/{k}"), np.nan).astype(np.float32) for k in ("xp", "yp"))
    decoded = LiveDecode(mask, np.ones((H, W), np.float32), np.zeros((H, W), np.uint8), 0.01, {}, xp, yp)
    white = np.full((H, W, 3), 0.5, np.float32)
    message = _decode_message(decoded, white, 0.1, state)
    assert message["depth_range"][0] == pytest.approx(fx * 60 / 40, rel=0.015) and message["surface_png"]
    state.calibration = None
    message = _decode_message(decoded, white, 0.1, state)
    assert "depth_png" not in message and message["depth_note"].startswith("no camera-projector calibration")
    state.live = LiveRig()  # the simulated rig: its exact calibration
    assert "depth_png" in _decode_message(decoded, white, 0.1, state)


def test_sss_report_writes_only_where_it_may_and_stops_at_damaged_data(handmade, tmp_path):
    """It replaced a user's own index.html and a demo folder's step records (a resumed demo then kept the
    report's rows), merged two sessions of one object, and reported a damaged session as "done"."""
    import shutil

    s = _copy(handmade, tmp_path / "sessions")

    def report(*args: str) -> subprocess.CompletedProcess[str]:
        return run_sss(["report", *args, "--backend", "none"], timeout=300)

    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<h1>my lab</h1>")
    res = report(str(s.path), "--out", str(site))
    assert res.returncode == 2 and "holds index.html, not a folder `sss report` wrote" in res.stderr
    assert (site / "index.html").read_text() == "<h1>my lab</h1>" and sorted(p.name for p in site.iterdir()) == ["index.html"]
    demo = tmp_path / "demo"
    for sub in ("steps", "sessions"):
        (demo / sub).mkdir(parents=True)
    res = report(str(s.path), "--out", str(demo))
    assert res.returncode == 2 and "is a demo folder" in res.stderr
    shutil.copytree(s.path, tmp_path / "copy" / "handmade")
    res = report(str(s.path), str(tmp_path / "copy"), "--out", str(tmp_path / "rep"))
    assert res.returncode == 2 and "two sessions hold the object 'handmade'" in res.stderr
    chunk = next(p for p in sorted((tmp_path / "copy" / "handmade" / "view_000" / "white" / "c").rglob("*")) if p.is_file())
    chunk.write_bytes(chunk.read_bytes()[:20])
    res = report(str(tmp_path / "copy"), "--out", str(tmp_path / "rep"))
    assert res.returncode == 2 and "damaged" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
def test_the_captures_choose_the_noise_mask_that_keeps_faint_wide_tails(tmp_path):
    """A frame-filling wide scatterer with shot noise and a clean black frame (as a renderer writes): a
    1 px noise mask drops the faint tails that add up over many dots, a 2 px mask keeps them. The view's
    own fringe captures choose the 2 px mask, and it relights a noise-free reference better."""
    from sssphase_core.processing.footprints import DENOISE_SMOOTHING
    from sssphase_core.relight import load_view, relight
    from sssphase_core.relight.transport import denoised_transport

    wp, hp, spacing, k = 112, 84, 16, 32
    plan = capture_plan(wp, hp, footprints=True, dot_spacing=spacing, references=("white", "black", "checkerboard"))
    r = np.hypot(*np.mgrid[-10:11, -10:11]).astype(np.float32)
    kernels = [np.exp(-r / lam) / np.exp(-r / lam).sum() for lam in (2.5, 1.2, 0.7)]

    def render(pattern: np.ndarray) -> np.ndarray:
        light = emitted_light(pattern[None], 2.2)[0] * np.float32(0.35)
        return np.stack([cv2.filter2D(light[..., c], -1, kernels[c], borderType=cv2.BORDER_CONSTANT) for c in range(3)], -1)

    rng, folder = np.random.default_rng(0), tmp_path / "render"
    clean = {}
    for f in plan:
        img = render(f.pattern())
        clean[f.key] = img
        noisy = rng.poisson(np.maximum(img, 0) * 4000) / 4000 + rng.normal(0, 0.001, img.shape)  # shot and read noise
        _write(folder, f.key, noisy.astype(np.float32), nested=False, fmt="exr")
    s = import_folder(folder, tmp_path / "sessions", "wide", (wp, hp), patch=k)
    rv = load_view(s, 0)
    info = s.manifest["views"]["0"]["transport"]
    assert info["denoise_smoothing"] == list(DENOISE_SMOOTHING) and info["noise"] > 0
    args = (rv, s.load(0, "transport/pixels"), s.load(0, "transport/dots"), s.read(0, "transport/crops"), info["noise"])
    chosen, tight = denoised_transport(*args, DENOISE_SMOOTHING), denoised_transport(*args, (1.0,))
    assert chosen.smoothing == 2.0 and chosen.fit[2.0] > chosen.fit[1.0] + 1, chosen.fit
    m, ref = rv.proj.mask, clean["ref/checkerboard"] * np.float32(s.manifest["rig"]["frame_scale"])  # in the session's units
    err = {t.smoothing: np.mean((relight(t, rv.proj, [rv.references["checkerboard"]], k)[0][m] - ref[m]) ** 2)
           for t in (chosen, tight)}
    assert err[2.0] < 0.7 * err[1.0], err  # > 1.5 dB better against the noise-free reference


def _perturbed(frames: Path, out: Path, change) -> Path:
    """A copy of the frames folder (as float EXR) with ``change(image)`` applied to every frame."""
    out.mkdir(parents=True)
    for path in sorted(frames.rglob("*.*")):
        key = path.relative_to(frames).with_suffix("").as_posix().replace("/", "__")
        if path.suffix == ".png":
            img = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB).astype(np.float32) / 65535
        elif path.suffix == ".exr":
            from sssphase_core.store.exr import read_exr

            img = read_exr(path)
        else:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32)
        _write(out, key.replace("__", "/"), change(img.copy()).astype(np.float32), nested=False, fmt="exr")
    return out


def _relit_psnr(sessions: list[Session], tmp_path: Path) -> dict[str, dict[str, float]]:
    """``{session name: {backend: PSNR}}`` from ``sss eval relight --backend none,measured`` (the CLI in this
    process: a subprocess per session spent ~4 s importing)."""
    from typer.testing import CliRunner

    from sssphase_cli.main import app

    out = {}
    for session in sessions:
        res = CliRunner().invoke(app, ["eval", "relight", str(session.path), "--backend", "none,measured", "--out",
                                       str(tmp_path / session.name)])
        assert res.exit_code == 0, res.output
        rows = json.loads((tmp_path / session.name / "relight_eval.json").read_text())["aggregate"]
        out[session.name] = {a["backend"]: a["psnr"] for a in rows}
    return out


def test_fireflies_in_the_frames_are_repaired_before_anything_reads_them(frames, handmade, clean_psnr, tmp_path):
    """A path tracer's fireflies (isolated values far above what full white gives) in every frame: they are
    replaced by their neighbours' median as the view is processed, so the session decodes and relights as
    without them (they took the captured transport of a render to -15.8 dB); clean frames are untouched."""
    clean = handmade
    assert clean.manifest["views"]["0"]["outliers_repaired"] == 0
    assert clean.manifest["views"]["0"]["hot_pixels"] == 0
    rng = np.random.default_rng(3)

    def fireflies(img: np.ndarray) -> np.ndarray:
        ys, xs = rng.integers(0, H, 2), rng.integers(0, W, 2)
        img[ys, xs] += rng.uniform(5, 50, (2, 3)).astype(np.float32)
        return img

    noisy = _perturbed(frames, tmp_path / "fireflies", fireflies)
    s = import_folder(noisy, tmp_path / "s", "fireflies", (W, H), patch=K)
    assert s.manifest["views"]["0"]["outliers_repaired"] >= 3 * len(list(frames.rglob("*.*")))
    np.testing.assert_allclose(s.load(0, "corr/xp")[8:-8, 8:-8], clean.load(0, "corr/xp")[8:-8, 8:-8], atol=0.1)
    out = {**_relit_psnr([s], tmp_path), "clean": clean_psnr}
    assert out["fireflies"]["none"] > out["clean"]["none"] - 0.5, out
    assert out["fireflies"]["measured"] > 40, out  # the clean frames' 72 dB is exact; one firefly per frame sinks it


def test_a_path_tracers_stray_nan_and_inf_samples_are_repaired_and_a_broken_file_is_refused(frames, handmade, clean_psnr,
                                                                                           tmp_path):
    """A few NaN / inf pixels in a render's frames refused the whole import ("holds NaN or infinite values");
    they are now replaced by their finite neighbours' median and counted, and the view relights as without
    them. A frame with many of them is a broken file: one line naming it and the count."""
    clean = handmade
    assert clean.manifest["views"]["0"]["nonfinite_repaired"] == 0
    rng = np.random.default_rng(4)

    def stray(img: np.ndarray) -> np.ndarray:
        ys, xs, cs = rng.integers(0, H, 2), rng.integers(0, W, 2), rng.integers(0, 3, 2)
        img[ys, xs, cs] = np.float32([np.nan, np.inf])
        return img

    with pytest.warns(UserWarning, match=r"\d+ NaN or infinite values .* were repaired from their neighbours"):
        s = import_folder(_perturbed(frames, tmp_path / "stray", stray), tmp_path / "s", "stray", (W, H), patch=K)
    assert s.manifest["views"]["0"]["nonfinite_repaired"] == 2 * len(list(frames.rglob("*.*")))
    np.testing.assert_allclose(s.load(0, "corr/xp")[8:-8, 8:-8], clean.load(0, "corr/xp")[8:-8, 8:-8], atol=0.1)
    out = {**_relit_psnr([s], tmp_path), "clean": clean_psnr}
    assert out["stray"]["none"] > out["clean"]["none"] - 0.5, out

    def broken(img: np.ndarray) -> np.ndarray:
        img[:4] = np.nan  # 4 of 48 rows
        return img

    with pytest.raises(InputError, match=r"of its \d+ values are NaN or infinite \(more than the 0.1%"):
        import_folder(_perturbed(frames, tmp_path / "broken", broken), tmp_path / "s", "broken", (W, H), patch=K)
    assert not (tmp_path / "s" / "broken").exists()


def test_hot_pixels_are_found_in_the_black_frame_and_their_offset_leaves_every_frame(frames, handmade, clean_psnr, tmp_path):
    """Hot pixels (the same value added to every frame, black included) survive the smoothed dark frame that
    the dot grids subtract, so each sat in every footprint crop around it; they are found in the black frame
    (its excess over the neighbours, beyond the projector's black light on the texture, seen in the lit
    frames too) and their offset is subtracted from every frame, which keeps their fringe phase; stuck pixels
    (one value in every frame) are left dark. Without it these frames' measured transport relit at 10.5 dB
    (72.5 clean)."""
    rng = np.random.default_rng(5)
    ys, xs, cs = rng.integers(4, H - 4, 25), rng.integers(4, W - 4, 25), rng.integers(0, 3, 25)
    offsets = rng.uniform(0.05, 0.3, 25).astype(np.float32)
    stuck = rng.integers(8, H - 8, 5), rng.integers(8, W - 8, 5), rng.integers(0, 3, 5)

    def hot(img: np.ndarray) -> np.ndarray:
        img[ys, xs, cs] += offsets
        img[stuck] = 0.05  # stuck pixels: one value in every frame, whatever the light (here below the lit ones)
        return img

    s = import_folder(_perturbed(frames, tmp_path / "hot", hot), tmp_path / "s", "hot", (W, H), patch=K)
    clean = handmade
    n_defects = len(set(zip([*ys.tolist(), *stuck[0].tolist()], [*xs.tolist(), *stuck[1].tolist()], strict=True)))
    assert n_defects >= s.manifest["views"]["0"]["hot_pixels"] >= n_defects - 3
    np.testing.assert_allclose(s.load(0, "white")[ys, xs, cs], clean.load(0, "white")[ys, xs, cs], atol=0.01)
    np.testing.assert_allclose(s.load(0, "corr/xp")[8:-8, 8:-8], clean.load(0, "corr/xp")[8:-8, 8:-8], atol=0.1)
    out = {**_relit_psnr([s], tmp_path), "clean": clean_psnr}
    assert out["hot"]["none"] > out["clean"]["none"] - 0.5, out
    assert out["hot"]["measured"] > 40, out


def test_view_folders_import_in_numeric_order(frames, tmp_path):
    """view_2 comes before view_10 (a text sort put view_10 first)."""
    folder = tmp_path / "two"
    _perturbed(frames, folder / "view_2", lambda img: img)
    _perturbed(frames, folder / "view_10", lambda img: img * np.float32(0.5))
    s = import_folder(folder, tmp_path / "s", "two", (W, H), patch=K)
    assert s.views() == [0, 1]
    assert s.load(0, "white").mean() > 1.8 * s.load(1, "white").mean()


def test_an_import_records_the_turntable_angles_it_is_given(frames, tmp_path):
    """Imported sessions had no turntable angle: `sss geometry` could never merge another rig's views."""
    from sssphase_core.capture.importer import parse_angles
    from sssphase_core.relight.merged_points import recorded_angles

    folder = tmp_path / "turned"
    for v in range(2):
        _perturbed(frames, folder / f"view_{v:03d}", lambda img: img)
    with pytest.raises(InputError, match=r"--angles gives 3 angles for 2 views: give one per view, in view order"):
        import_folder(folder, tmp_path / "s", "turned", (W, H), patch=K, angles=[0, 90, 180])
    with pytest.raises(InputError, match=r"--angles must be finite numbers of degrees"):
        import_folder(folder, tmp_path / "s", "turned", (W, H), patch=K, angles=[0, float("nan")])
    assert not (tmp_path / "s" / "turned").exists()
    with pytest.raises(InputError, match=r"--angles must be the views' turntable angles in degrees, comma-separated"):
        parse_angles("0;90")
    s = import_folder(folder, tmp_path / "s", "turned", (W, H), patch=K, angles=parse_angles("0, 90"))
    assert recorded_angles(s, [0, 1]) == {0: 0.0, 1: 90.0}
    plain = import_folder(folder, tmp_path / "s", "plain", (W, H), patch=K)
    assert recorded_angles(plain, [0, 1]) is None and "angles" not in plain.manifest["import_options"]


def test_16_bit_npy_frames_import_like_16_bit_pngs(frames, tmp_path):
    """A lab's raw frames saved as uint16 .npy are the camera's codes, like a 16-bit PNG's: divided by the
    top code (they were taken as linear values in the tens of thousands, saturation unseen)."""
    import shutil

    folders = {kind: tmp_path / kind for kind in ("png", "npy")}
    for kind, folder in folders.items():
        folder.mkdir()
        for path in sorted(frames.rglob("*.*")):
            key = path.relative_to(frames).with_suffix("").as_posix().replace("/", "__")
            if path.suffix == ".png" and kind == "npy":  # the fixture's 16-bit PNGs as uint16 .npy
                codes = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
                np.save(folder / f"{key}.npy", codes.astype(np.uint16))
            else:
                shutil.copy(path, folder / f"{key}{path.suffix}")
    a = import_folder(folders["png"], tmp_path / "s", "png", (W, H), patch=K)
    b = import_folder(folders["npy"], tmp_path / "s", "npy", (W, H), patch=K)
    np.testing.assert_array_equal(a.load(0, "white"), b.load(0, "white"))
    assert 0.2 < float(b.load(0, "white").max()) <= 1.0


@pytest.mark.parametrize(("frame", "change", "expected"), [
    ("white", lambda img: img * 0, "the white capture holds no light (99.9th percentile 0)"),
    ("white", lambda img: -img, "the white capture holds no light (99.9th percentile -"),
    ("white", lambda img: img * np.float32(1e-44), "the white capture holds no light"),  # denormal: 1/level overflows
    # negated over a lit backdrop's noise: its level is that noise's, and the black was blamed for being below it
    ("white", lambda img: np.where(np.arange(img.shape[1])[:, None] < 8, np.float32(0.05), -img),
     "of its values are below -0.25 x the white capture's level"),
    ("psp__x__p18__s1", lambda img: img - np.float32(0.6), "of its values are below -0.25 x the white capture's level"),
    ("black", lambda img: img - np.float32(0.5), "100% of its values are below -0.25 x the white capture's level"),  # not 1e+02%
    ("black", lambda img: img + np.float32(2.0), "the black capture is brighter than the white one (99.9th percentiles 2"),
])
def test_frames_without_light_or_far_below_zero_are_refused_naming_them(tmp_path, frame, change, expected):
    """A black, negative or denormal white capture, a frame with a black level subtracted twice: imported
    without a word, they relit at 3.9-10.4 dB where "none" read 18.4. A black brighter than the white (the two
    swapped) is named as such, in the file's units. Noise around zero still imports."""
    folder = _float_frames(tmp_path / "f", 1.0)
    path = folder / f"{frame}.npy"
    np.save(path, change(np.load(path)))
    with pytest.raises(InputError, match=f"{path}: .*{expected.replace('(', '.').replace(')', '.')}"):
        import_folder(folder, tmp_path / "s", "o", (W, H), patch=K)
    assert not (tmp_path / "s" / "o").exists()
    noisy = _float_frames(tmp_path / "n", 1.0)
    rng = np.random.default_rng(0)
    for p in noisy.glob("*.npy"):  # read noise of 2% of white around zero in every frame: not refused
        np.save(p, np.load(p) + rng.normal(0, 0.02, (H, W, 3)).astype(np.float32))
    assert import_folder(noisy, tmp_path / "s", "noisy", (W, H), patch=K).views() == [0]
    # white and black swapped, float frames with noise around zero: the white's negative values were named first
    swapped = _float_frames(tmp_path / "w", 1.0)
    white, black = np.load(swapped / "white.npy"), np.load(swapped / "black.npy")
    np.save(swapped / "white.npy", black + rng.normal(0, 0.02, black.shape).astype(np.float32))
    np.save(swapped / "black.npy", white)
    with pytest.raises(InputError, match=r"black.npy: the black capture is brighter than the white one .* are white "
                                         r"and black swapped\?"):
        import_folder(swapped, tmp_path / "s", "swapped", (W, H), patch=K)


def test_grey_frames_import_as_colour_and_one_grey_frame_among_colour_ones_is_refused(tmp_path):
    """A mono camera's frames (one channel) import as grey light in every colour; one grey file among a colour
    camera's (an export gone wrong) was repeated into RGB without a word, its view's colours decoded from mixed
    frames."""
    grey = _float_frames(tmp_path / "grey", 1.0)
    for p in grey.glob("*.npy"):
        np.save(p, np.load(p).mean(-1))
    s = import_folder(grey, tmp_path / "s", "grey", (W, H), patch=K)
    white = np.asarray(s.load(0, "white"))
    assert white.shape[-1] == 3 and np.array_equal(white[..., 0], white[..., 2]) and white.max() > 0.2
    mixed = _float_frames(tmp_path / "mixed", 1.0)
    one = mixed / "psp__x__p18__s1.npy"
    np.save(one, np.load(one).mean(-1))
    with pytest.raises(InputError, match=rf"{one} is a grey image, the other frames \(.*\) colour: one camera"):
        import_folder(mixed, tmp_path / "s", "mixed", (W, H), patch=K)
    assert not (tmp_path / "s" / "mixed").exists()


def test_a_colour_cameras_raw_bayer_frames_are_demosaiced_with_their_layout_and_not_read_as_grey(tmp_path):
    """A lab's machine-vision camera saves raw Bayer samples (one grey channel): they imported as a monochrome
    camera's, colour lost and each 2 x 2 cell's colours read as a pattern of light. Now the greens' diagonal is read
    from the white, the layout asked for (red and blue cannot be told apart) and the samples demosaiced."""
    from sssphase_core.processing.isp import bayer_mosaic, develop

    w, h = 2 * W, 2 * H
    plan = [f for f in capture_plan(w, h, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    yy, xx = np.mgrid[:h, :w]
    inside = ((yy - h / 2) / 38) ** 2 + ((xx - w / 2) / 54) ** 2 <= 1
    light = gaussian_filter(emitted_light(np.stack([f.pattern() for f in plan]), 2.2) * inside[..., None],
                            (0, 1.2, 1.2, 0)) * np.float32([0.9, 0.45, 0.15])
    folder = tmp_path / "raw"
    folder.mkdir()
    for f, img in zip(plan, light.astype(np.float32), strict=True):
        np.save(folder / (f.key.replace("/", "__") + ".npy"), bayer_mosaic(img, "GRBG"))
    with pytest.raises(InputError, match=r"white.npy: a grey frame whose 2 x 2 sites hold different colours' light, "
                                         r"greens on the main diagonal .* give its layout \(GRBG or GBRG\) with --bayer"):
        import_folder(folder, tmp_path / "s", "auto", (w, h), patch=16)
    with pytest.raises(InputError, match=r"--bayer RGGB puts green on the anti diagonal .* on the main one .*GRBG or GBRG"):
        import_folder(folder, tmp_path / "s", "wrong", (w, h), patch=16, bayer="RGGB")
    assert not (tmp_path / "s" / "auto").exists() and not (tmp_path / "s" / "wrong").exists()
    s = import_folder(folder, tmp_path / "s", "raw", (w, h), patch=16, bayer="GRBG")
    info = s.manifest["views"]["0"]
    assert info["raw_bayer"] == "GRBG: demosaiced by malvar"
    assert info["camera_isp"] == {"bayer": "GRBG", "demosaic": "malvar", "median": False}
    white = np.asarray(s.load(0, "white"))
    want = develop(bayer_mosaic(light[-2], "GRBG"), 0.0, 1.0, median=False, layout="GRBG")
    np.testing.assert_allclose(white, want, atol=1e-6)  # the samples as the layout's demosaicing gives them
    core = inside & (np.hypot((yy - h / 2) / 38, (xx - w / 2) / 54) < 0.7)
    ratio = white[core].mean(0) / white[core].mean()
    np.testing.assert_allclose(ratio, np.float32([0.9, 0.45, 0.15]) / 0.5, rtol=0.02)  # its colours, not grey
    assert s.load(0, "corr/mask")[core].mean() > 0.95
    # a 12-bit camera's samples, its brightest clipped: Malvar's filters overshoot the top code beside them, which
    # must not read as codes wider than 12 bits (they are checked as they came, before demosaicing)
    codes = tmp_path / "codes"
    codes.mkdir()
    for f, img in zip(plan, light.astype(np.float32), strict=True):
        mosaic = bayer_mosaic(img, "GRBG") / (0.8 * float(light[-2].max()))
        np.save(codes / (f.key.replace("/", "__") + ".npy"), np.round(np.clip(mosaic, 0, 1) * 4095).astype(np.uint16))
    with pytest.warns(UserWarning, match="clipped"):
        twelve = import_folder(codes, tmp_path / "s", "twelve", (w, h), patch=16, bayer="GRBG", bit_depth=12)
    assert twelve.manifest["views"]["0"]["raw_bayer"] == "GRBG: demosaiced by malvar"
    assert float(np.asarray(twelve.load(0, "white")).max()) > 1.0  # (the overshoot, kept as light)
    # ... and kept by relighting's camera model too: the codes' range bounds the samples, not frames made from them
    assert "frame_codes_range" not in twelve.manifest["rig"]  # (clipped to it, relit images scored 3.4 dB low)
    # the samples saved by a tool as three equal channels are the same samples (they imported as grey light)
    trip = tmp_path / "trip"
    trip.mkdir()
    for path in folder.glob("*.npy"):
        np.save(trip / path.name, np.repeat(np.load(path)[..., None], 3, axis=-1))
    with pytest.raises(InputError, match=r"trip/white.npy: a grey frame whose 2 x 2 sites hold different colours"):
        import_folder(trip, tmp_path / "s", "trip", (w, h), patch=16)
    tripled = import_folder(trip, tmp_path / "s", "tripled", (w, h), patch=16, bayer="GRBG")
    np.testing.assert_array_equal(tripled.load(0, "white"), s.load(0, "white"))
    # one camera per import: a colour view beside a raw one was read by the first view's kind
    mixed = tmp_path / "mixed"
    shutil.copytree(folder, mixed / "view_001")
    (mixed / "view_000").mkdir()
    for f, img in zip(plan, light.astype(np.float32), strict=True):  # the same scene, as a colour camera's files
        np.save(mixed / "view_000" / (f.key.replace("/", "__") + ".npy"), img)
    with pytest.raises(InputError, match=r"view_001/white.npy holds raw Bayer samples, .*view_000/white.npy colour "
                                         r"frames: the views of one import come from one camera"):
        import_folder(mixed, tmp_path / "s", "mixed", (w, h), patch=16, bayer="GRBG")


def test_a_demosaicing_cameras_integer_frames_are_scored_through_its_clipped_codes(tmp_path):
    """A relit image goes through the camera's demosaicing to compare with its captures; Malvar's filters overshoot
    below 0 beside edges, which a camera's PNG cannot hold: scored unclipped, an imported crab's 16-bit PNGs relit
    3.6 dB below its EXRs (36.3 against 39.9 dB)."""
    from typer.testing import CliRunner

    from sssphase_cli.main import app
    from sssphase_core.processing.isp import through_camera

    w, h = 2 * W, 2 * H
    plan = [f for f in capture_plan(w, h, references=("white", "black", "checkerboard"))
            if not f.key.startswith("dots/")]
    yy, xx = np.mgrid[:h, :w]
    inside = ((yy - h / 2) / 38) ** 2 + ((xx - w / 2) / 54) ** 2 <= 1
    light = gaussian_filter(emitted_light(np.stack([f.pattern() for f in plan]), 2.2) * inside[..., None],
                            (0, 1.2, 1.2, 0)) * np.float32([0.9, 0.45, 0.15])
    frames = through_camera(light, demosaic="malvar", layout="GRBG")
    assert frames.min() < -0.01  # the overshoot beside the silhouette and the checkerboard's edges
    scores, lowest = {}, {}
    for name in ("floats", "codes"):
        folder = tmp_path / name
        folder.mkdir()
        for f, img in zip(plan, frames, strict=True):
            stem = folder / f.key.replace("/", "__")
            if name == "floats":
                np.save(stem.with_suffix(".npy"), img)
            else:
                u16 = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
                cv2.imwrite(str(stem.with_suffix(".png")), cv2.cvtColor(u16, cv2.COLOR_RGB2BGR))
        s = import_folder(folder, tmp_path / "s", name, (w, h), patch=16, bayer="GRBG", demosaic="malvar")
        assert s.manifest["rig"].get("frame_codes_range") == ([0.0, 1.0] if name == "codes" else None)
        lowest[name] = float(load_view(s, 0).through_camera(light[-1:]).min())
        res = CliRunner().invoke(app, ["eval", "relight", str(s.path), "--backend", "none", "--out", str(tmp_path / name)])
        assert res.exit_code == 0, res.output
        scores[name] = json.loads((tmp_path / name / "relight_eval.json").read_text())["aggregate"][0]["psnr"]
    assert scores["codes"] >= scores["floats"], scores  # the same light, its files clipped: 18.5 dB against 17.5
    assert lowest["codes"] == 0 and lowest["floats"] < 0  # (float files hold the overshoot: kept)


def test_fringes_at_another_exposure_than_the_white_are_refused_naming_the_set(tmp_path):
    """Fringe frames at twice the white's exposure imported with a warning that led with sRGB files, and relit 6 dB
    low; unwrapping sets at twice it (enough of them to set the white's estimate the outlier repair bounds frames
    by) were blamed on the shifts' order."""
    for name, glob, said in (("all", "psp__*.npy", r"all: the fringe frames average 1\.00 of the white"),
                             ("unwrap", "psp__?__p[17]*__s*.npy", r"unwrap/psp__[xy]__p(18|71)__s\* average 1\.00 of the white")):
        folder = _float_frames(tmp_path / name, 1.0)
        for path in folder.glob(glob):
            np.save(path, np.load(path) * np.float32(2))
        with pytest.raises(InputError, match=said + r".* about 2\.0x as exposed as the white"):
            import_folder(folder, tmp_path / "s", name, (W, H), patch=K)
        assert not (tmp_path / "s" / name).exists()


def test_frames_beside_view_folders_are_refused_not_left_out(tmp_path):
    """Loose frames next to view_NNN folders were one view silently dropped (and said first that view_001 was
    imported as view 0, before the refusal)."""
    folder = _float_frames(tmp_path / "mixed", 1.0)
    _float_frames(folder / "view_001", 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the refusal alone
        with pytest.raises(InputError, match="holds frames beside its view_NNN folders"):
            import_folder(folder, tmp_path / "s", "o", (W, H), patch=K)


def test_a_given_projected_image_wins_over_our_pattern_of_the_same_name(tmp_path):
    """``pattern__checkerboard.png`` beside ``ref__checkerboard``: the lab's own checkerboard (another check
    size) is what its capture shows, so relighting and evaluation use it, not ours."""
    from sssphase_core.processing.patterns import reference_pattern
    from sssphase_core.relight import load_view

    folder = _float_frames(tmp_path / "f", 1.0)
    theirs = reference_pattern("stripes_x", W, H)  # not our checkerboard
    np.save(folder / "pattern__checkerboard.npy", theirs)
    np.save(folder / "ref__checkerboard.npy", _camera(theirs[None])[0])
    rv = load_view(import_folder(folder, tmp_path / "s", "o", (W, H), patch=K), 0)
    np.testing.assert_allclose(rv.references["checkerboard"], theirs, atol=1e-6)


def test_renderers_multi_layer_exr_frames_are_read_by_their_colour_layer(tmp_path):
    """Path tracers write multi-layer EXR (Blender's ViewLayer.Combined.R, with depth and normals beside it):
    the colour layer is read; a file with several unnamed colour layers is refused naming them."""
    import OpenEXR

    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.imageio import read_frame

    rng = np.random.default_rng(0)
    rgb = rng.random((H, W, 3)).astype(np.float32)
    layers = {f"ViewLayer.Combined.{c}": np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("RGB")}
    layers |= {f"ViewLayer.Normal.{c}": rng.random((H, W)).astype(np.float32) for c in "RGB"}
    layers |= {"ViewLayer.Combined.A": np.ones((H, W), np.float32), "ViewLayer.Depth.Z": rng.random((H, W)).astype(np.float32)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, layers) as f:
        f.write(str(tmp_path / "white.exr"))
    np.testing.assert_array_equal(read_frame(tmp_path / "white.exr"), rgb)
    two = {f"{lay}.{c}": np.ascontiguousarray(rgb[..., i]) for lay in ("left", "right") for i, c in enumerate("RGB")}
    with OpenEXR.File(header, two) as f:
        f.write(str(tmp_path / "two.exr"))
    with pytest.raises(DataError, match=r"holds several colour layers \(left, right\)"):
        read_frame(tmp_path / "two.exr")
    # depth in one part, the colour in another (multi-part files): the colour is read
    parts = [OpenEXR.Part({**header, "name": "depth"}, {"Z": np.zeros((H, W), np.float32)}),
             OpenEXR.Part({**header, "name": "beauty"}, {"RGB": rgb})]
    OpenEXR.File(parts).write(str(tmp_path / "parts.exr"))
    np.testing.assert_array_equal(read_frame(tmp_path / "parts.exr"), rgb)
    # an AOV part with colour written before the beauty (Arnold, Nuke) was read as the image
    parts = [OpenEXR.Part({**header, "name": "diffuse_direct"}, {"RGB": rgb * np.float32(0.6)}),
             OpenEXR.Part({**header, "name": "beauty"}, {"RGB": rgb})]
    OpenEXR.File(parts).write(str(tmp_path / "aov_first.exr"))
    np.testing.assert_array_equal(read_frame(tmp_path / "aov_first.exr"), rgb)
    parts = [OpenEXR.Part({**header, "name": n}, {"RGB": rgb}) for n in ("left", "right")]
    OpenEXR.File(parts).write(str(tmp_path / "two_parts.exr"))
    with pytest.raises(DataError, match=r"holds an image in several parts \(left, right\): .* name its part beauty"):
        read_frame(tmp_path / "two_parts.exr")
    # lower-case layer channels (Houdini's C.r) and a grey channel beside alpha or depth were refused
    for name, channels in (("lower", {f"C.{c}": np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("rgb")}
                                     | {"C.a": np.ones((H, W), np.float32)}),
                           ("grey_alpha", {"Y": np.ascontiguousarray(rgb[..., 0]), "A": np.ones((H, W), np.float32)})):
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp_path / f"{name}.exr"))
        np.testing.assert_array_equal(read_exr(tmp_path / f"{name}.exr"), rgb if name == "lower" else rgb[..., 0])
    # half floats that overflowed (values above 65504 became +inf) were "repaired" as a renderer's stray samples
    with np.errstate(over="ignore"):
        bright = (rgb * np.float32(7e4)).astype(np.float16)
    with OpenEXR.File(header, {"RGB": bright}) as f:
        f.write(str(tmp_path / "half.exr"))
    with pytest.raises(DataError, match=r"values are \+inf in half floats whose others reach 65\d+: values above 65504 "
                                        r"overflowed; write float32"):
        read_exr(tmp_path / "half.exr")
    # no light channels: depth alone, or luminance/chroma, were read as an image
    for name, channels, why in (("depth", {"Z": rgb[..., 0]}, r"its channels: Z\)"),
                                ("yc", {"Y": rgb[..., 0], "RY": rgb[..., 1], "BY": rgb[..., 2]}, "luminance/chroma")):
        with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as f:
            f.write(str(tmp_path / f"{name}.exr"))
        with pytest.raises(DataError, match=rf"holds no image light as R, G, B or one grey channel .*{why}"):
            read_frame(tmp_path / f"{name}.exr")
    (tmp_path / "cut.exr").write_bytes((tmp_path / "white.exr").read_bytes()[:400])
    with pytest.raises(DataError, match=r"cannot read EXR .*cut.exr \(damaged, truncated or not an EXR file\)$"):
        read_frame(tmp_path / "cut.exr")
    with pytest.raises(DataError, match=r"cannot read EXR .*gone.exr: no such file$"):  # not "damaged": not there
        read_exr(tmp_path / "gone.exr")


def test_an_import_warns_of_a_wrong_projector_size_and_of_clipped_light(tmp_path):
    """Imports that decode but are suspect exited 0 in silence: frames of a 64x48 projector imported as 48x40
    (a quarter of the pixels mapped outside), and a white capture clipped at its top code."""
    good = _float_frames(tmp_path / "good", 1.0)
    with pytest.warns(UserWarning, match=r"% of the decoded pixels map outside the 48x40 projector: is --projector right\?"):
        import_folder(good, tmp_path / "s", "small", (48, 40), patch=K)
    clipped = tmp_path / "clipped"
    clipped.mkdir()
    for f in good.glob("*.npy"):
        img = np.full((H, W, 3), 1.0, np.float32) if f.stem == "white" else np.load(f)
        cv2.imwrite(str(clipped / (f.stem + ".png")), np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
    with pytest.warns(UserWarning, match=r"the white capture is clipped at 100.0% of the decoded pixels"):
        import_folder(clipped, tmp_path / "s", "clipped", (W, H), patch=K)


def test_fringes_of_another_convention_warn_and_x_frames_copied_as_y_are_refused(tmp_path):
    """A rig whose shifts are numbered from another phase origin (its s0 our s1) or the other way (s1 and s3
    swapped) moves every decoded point by a quarter of the coarsest period, or mirrors it: the first imported without
    a word (14% of the points outside the projector here, 15.5% on a crab; the warning needed 20%); a folder whose y
    fringe frames were copies of the x ones decoded every y from x; x and y swapped decoded every point inside the
    projector, in silence. The clean frames warn of nothing."""
    import warnings

    w, h = 256, 192  # the cpu rig's projector and periods (the hand-made rig's unwrap fails instead: refused)
    good = tmp_path / "good"
    good.mkdir()
    plan = [f for f in capture_plan(w, h, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    lit = np.zeros((h, w, 1), np.float32)  # an object in the middle of the view, the background unlit: shifted by
    lit[int(0.3 * h):int(0.7 * h), int(0.3 * w):int(0.7 * w)] = 1  # the origin, 14% of it maps outside (20% warned)
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        np.save(good / (f.key.replace("/", "__") + ".npy"), img * lit + (0.0 if f.key == "black" else 1e-3))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        import_folder(good, tmp_path / "s", "good", (w, h), patch=K)
    assert not [w for w in said if "outside" in str(w.message) or "swapped" in str(w.message)], [str(w.message) for w in said]

    def renamed(name: str, shifts: dict[int, int]) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        for f in good.iterdir():
            stem = f.stem
            if stem.startswith("psp__"):
                head, shift = stem.rsplit("__s", 1)
                stem = f"{head}__s{shifts[int(shift)]}"
            (folder / f"{stem}.npy").write_bytes(f.read_bytes())
        return folder

    for name, shifts in (("origin", {0: 1, 1: 2, 2: 3, 3: 0}), ("reversed", {0: 0, 1: 3, 2: 2, 3: 1})):
        with pytest.warns(UserWarning, match=r"% of the decoded pixels map outside the 256x192 projector: is --projector "
                                             r"right\? \(else the fringes' conventions: shifts numbered the other way"):
            import_folder(renamed(name, shifts), tmp_path / "s", name, (w, h), patch=K)
    swapped = tmp_path / "swapped"  # every point still inside the projector, a checkerboard would still match
    swapped.mkdir()
    for f in good.iterdir():
        other = {"psp__x__": "psp__y__", "psp__y__": "psp__x__"}.get(f.name[:8], f.name[:8])
        (swapped / (other + f.name[8:])).write_bytes(f.read_bytes())
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        import_folder(swapped, tmp_path / "s", "swapped", (w, h), patch=K)
    said = [str(w.message) for w in said]
    assert any("the x fringes' projector columns change down the camera's rows" in m and "are the psp__x and psp__y "
               "frames swapped?" in m for m in said), said
    assert not any("outside" in m for m in said), said
    copied = tmp_path / "copied"
    copied.mkdir()
    for f in good.iterdir():
        if not f.stem.startswith("psp__y__"):
            (copied / f.name).write_bytes(f.read_bytes())
            if f.stem.startswith("psp__x__"):
                (copied / f.name.replace("psp__x__", "psp__y__")).write_bytes(f.read_bytes())
    with pytest.raises(InputError, match=r"the y fringe frames \(psp__y__\*\) hold the same images as the x ones"):
        import_folder(copied, tmp_path / "s", "copied", (w, h), patch=K)
    assert not (tmp_path / "s" / "copied").exists()


def test_a_few_decoded_pixels_without_white_light_do_not_upset_the_reference_checks():
    """A float white among 16-bit frames left 6 of 5,803 decoded pixels with white <= 0; each reference's light was
    divided by the white floored at 1e-6 there, and the import warned that a faithful reference held "27x another
    amount of light" and did not follow its pattern (correlation 0.02, "is --projector right?")."""
    from types import SimpleNamespace

    from sssphase_core.capture.importer import reference_match

    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pattern = np.kron((np.indices((h // 10, w // 10)).sum(0) % 2), np.ones((10, 10))).astype(np.float32)
    white = np.full((h, w, 3), 0.6, np.float32)
    black = np.full((h, w, 3), 0.01, np.float32)
    sent = emitted_light(pattern[None], 2.2)[0]
    ref = black + (white - black) * sent
    white[[3, 17, 29], [5, 40, 11]] = black[0, 0] - 1e-4  # decoded, but no white light above black
    proc = SimpleNamespace(corr=SimpleNamespace(mask=np.ones((h, w), bool), xp=xx, yp=yy),
                           images={"white": white, "black": black, "ref/checkers": ref},
                           patterns={"ref/checkers": pattern}, unrepaired={})
    bright: dict[str, float] = {}
    match = reference_match(proc, [{"name": "ref/checkers", "kind": "image"}], 2.2, bright)
    assert match["checkers"] > 0.99 and bright["checkers"] == pytest.approx(1.0, abs=0.01), (match, bright)


def test_frames_with_a_transparent_alpha_channel_import_and_say_it_is_ignored(tmp_path):
    """RGBA frames whose alpha is 0 everywhere imported without a word (a pattern's alpha is warned of)."""
    import warnings

    linear = _float_frames(tmp_path / "linear", 1.0)
    for alpha, name in ((0, "clear"), (65535, "opaque")):
        folder = tmp_path / name
        folder.mkdir()
        for f in linear.glob("*.npy"):
            codes = np.round(np.clip(np.load(f), 0, 1) * 65535).astype(np.uint16)
            bgra = np.concatenate([codes[..., ::-1], np.full((H, W, 1), alpha, np.uint16)], -1)
            cv2.imwrite(str(folder / f"{f.stem}.png"), bgra)
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            session = import_folder(folder, tmp_path / "s", name, (W, H), patch=K)
        told = [str(w.message) for w in said if "alpha channel" in str(w.message)]
        assert bool(told) == (alpha == 0) and session.views() == [0], told
        if told:
            assert "below full opacity at 100% of the pixels (transparent at 100%)" in told[0]


def test_an_icc_profile_of_linear_light_is_read_as_linear(tmp_path):
    """Any ICC profile was taken for sRGB: a 16-bit render tagged with a linear profile lost 74% of its pixels."""
    import io

    from PIL import Image, ImageCms

    from sssphase_core.store.imageio import declared_encoding

    codes = np.full((8, 8, 3), 30000, np.uint16)
    for name, profile, expected in (("linear", ImageCms.createProfile("XYZ"), "linear"),
                                    ("srgb", ImageCms.createProfile("sRGB"), "srgb")):
        buffer = io.BytesIO(ImageCms.ImageCmsProfile(profile).tobytes())
        path = tmp_path / f"{name}.png"
        Image.fromarray(codes[..., 0]).save(path, icc_profile=buffer.getvalue())
        encoding, why = declared_encoding(path)
        assert encoding == expected and "ICC colour profile" in why, (name, encoding, why)


def _srgb_codes(light: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] -> 8-bit sRGB codes (IEC 61966-2-1), as a renderer's PNG output holds them."""
    v = np.clip(light, 0, 1)
    return np.round(255 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)).astype(np.uint8)


def test_srgb_encoded_frames_are_decoded_to_light_by_their_tag_or_told_by_their_fringes(tmp_path):
    """A renderer's or a webcam's 8-bit PNGs hold sRGB codes, which were read as light: the fringe offset
    (the footprints' energy) came out ~1.4x too bright against the white. Tagged files are decoded; untagged
    ones are named by their fringes' mean (0.5 of the white's light in linear frames, whatever the transport)."""
    from PIL import Image, PngImagePlugin

    linear = _float_frames(tmp_path / "linear", 1.0)
    tagged, untagged = tmp_path / "tagged", tmp_path / "untagged"
    for folder in (tagged, untagged):
        folder.mkdir()
    srgb_chunk = PngImagePlugin.PngInfo()
    srgb_chunk.add(b"sRGB", b"\x00")  # perceptual rendering intent
    for f in linear.glob("*.npy"):
        codes = _srgb_codes(np.load(f))
        Image.fromarray(codes).save(tagged / f"{f.stem}.png", pnginfo=srgb_chunk)
        Image.fromarray(codes).save(untagged / f"{f.stem}.png")
    ref = import_folder(linear, tmp_path / "s", "linear", (W, H), patch=K)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a decoded sRGB import is clean
        dec = import_folder(tagged, tmp_path / "s", "tagged", (W, H), patch=K)
    assert dec.manifest["rig"]["frame_encoding"] == "srgb" and "sRGB chunk" in dec.manifest["rig"]["frame_encoding_from"]
    mask = ref.load(0, "corr/mask") & dec.load(0, "corr/mask")
    for name in ("corr/offset", "white"):  # light, within 8-bit quantisation
        a, b = ref.load(0, name)[mask], dec.load(0, name)[mask]
        assert np.median(b / np.maximum(a, 1e-3)) == pytest.approx(1.0, abs=0.02), name
    assert abs(ref.manifest["views"]["0"]["fringe_mean_share"] - 0.5) < 0.01
    floats = import_folder(linear, tmp_path / "s", "floats", (W, H), patch=K, encoding="srgb")  # .npy floats: light
    assert floats.manifest["rig"]["frame_encoding"] == "linear"
    np.testing.assert_array_equal(floats.load(0, "white"), ref.load(0, "white"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # untagged sRGB codes are told by their fringes' mean: decoded, no warning
        guessed = import_folder(untagged, tmp_path / "s", "untagged", (W, H), patch=K)
    assert guessed.manifest["rig"]["frame_encoding"] == "srgb", guessed.manifest["rig"]
    assert re.search(r"no colour tag; its fringes average 0\.[45]\d of the white's light read as sRGB codes, 0\.[67]\d "
                     r"read as linear ones", guessed.manifest["rig"]["frame_encoding_from"]), guessed.manifest["rig"]
    np.testing.assert_array_equal(guessed.load(0, "white"), dec.load(0, "white"))
    with pytest.warns(UserWarning, match=r"the fringe frames average 0\.[67]\d of the white capture's light .* "
                                         r"import with --encoding srgb"):
        raw = import_folder(untagged, tmp_path / "s", "raw", (W, H), patch=K, encoding="linear")
    assert raw.manifest["rig"]["frame_encoding"] == "linear"
    plain = tmp_path / "plain"  # untagged codes of linear light stay linear
    plain.mkdir()
    for f in linear.glob("*.npy"):
        Image.fromarray(np.round(255 * np.clip(np.load(f), 0, 1)).astype(np.uint8)).save(plain / f"{f.stem}.png")
    kept = import_folder(plain, tmp_path / "s", "plain", (W, H), patch=K)
    assert kept.manifest["rig"]["frame_encoding"] == "linear" and kept.manifest["rig"]["frame_encoding_from"] == "no colour tag"
    (untagged / "white.png").unlink()  # one tagged file among untagged ones
    Image.fromarray(_srgb_codes(np.load(linear / "white.npy"))).save(untagged / "white.png", pnginfo=srgb_chunk)
    with pytest.raises(InputError, match=r"is (srgb|linear) \(.*\) but .* is (linear|srgb) .*give --encoding"):
        import_folder(untagged, tmp_path / "s", "mixed", (W, H), patch=K)
    (untagged / "white.png").rename(untagged / "white.jpg")
    with pytest.raises(InputError, match=r"white\.jpg: \.jpg frames are lossy"):
        import_folder(untagged, tmp_path / "s", "jpeg", (W, H), patch=K)
    (untagged / "white.jpg").unlink()
    Image.fromarray(_srgb_codes(np.load(linear / "white.npy"))).save(untagged / "white.png", format="JPEG")
    with pytest.raises(InputError, match=r"white\.png holds JPEG data, which is lossy"):  # whatever its name says
        import_folder(untagged, tmp_path / "s", "jpeg", (W, H), patch=K, encoding="linear")
    assert not (tmp_path / "s" / "mixed").exists() and not (tmp_path / "s" / "jpeg").exists()


def test_frames_of_two_bit_depths_are_refused_before_anything_is_written(tmp_path):
    """8-bit sRGB codes beside 16-bit linear ones (two pipelines' files in one folder) were decoded by one
    encoding into a session that relit 9 dB worse, with only a hint to re-import with the other encoding."""
    from PIL import Image

    linear = _float_frames(tmp_path / "linear", 1.0)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for f in linear.glob("*.npy"):
        light = np.clip(np.load(f), 0, 1)
        if f.stem.startswith("psp__y"):  # one orientation's frames from another pipeline: 16-bit linear codes
            cv2.imwrite(str(mixed / f"{f.stem}.png"), np.round(light * 65535).astype(np.uint16)[..., ::-1])
        else:
            Image.fromarray(_srgb_codes(light)).save(mixed / f"{f.stem}.png")
    for encoding in ("auto", "srgb", "linear"):
        with pytest.raises(InputError, match=r"holds (8|16)-bit codes but .*psp__.* holds (16|8)-bit ones: an import's "
                                             r"frames come from one camera pipeline"):
            import_folder(mixed, tmp_path / "s", "mixed", (W, H), patch=K, encoding=encoding)
    assert not (tmp_path / "s" / "mixed").exists()


def test_footprints_cached_for_one_session_are_never_read_for_another(tmp_path):
    """The footprint cache in OUT/cache was named by object, view, backend and model only: the same object
    imported again (here: brighter frames) and relit into the same --out got the first session's footprints."""
    from sssphase_core.store.exr import read_exr

    for name, scale in (("a", 1.0), ("b", 3.0)):
        import_folder(_float_frames(tmp_path / f"f{name}", scale), tmp_path / name, "obj", (W, H), patch=K)

    from typer.testing import CliRunner

    from sssphase_cli.main import app

    def relit(session: str, out: str) -> np.ndarray:
        res = CliRunner().invoke(app, ["relight", str(tmp_path / session / "obj"), "--pattern", "checkerboard",
                                       "--backend", "analytic", "--format", "exr", "--out", str(tmp_path / out)])
        assert res.exit_code == 0, res.output
        return read_exr(tmp_path / out / "obj_v0_checkerboard_analytic.exr")

    relit("a", "shared")
    for image in (tmp_path / "shared").glob("obj_v0_*"):  # (another session's images there are refused; its cache stays)
        image.unlink()
    fresh, shared = relit("b", "fresh"), relit("b", "shared")
    np.testing.assert_array_equal(shared, fresh)
    cached = sorted(p.name for p in (tmp_path / "shared" / "cache").glob("obj_v0_*_analytic_*.npz"))
    eigen = [n for n in cached if n.endswith("_lowrank.npz")]  # the eigen-footprints are per session's view too
    assert len(cached) == 4 and len(eigen) == 2 and len({n.split("_")[2] for n in eigen}) == 2


def test_frames_a_camera_demosaiced_itself_drop_the_silhouettes_bleed_when_the_layout_is_given(tmp_path):
    """A camera that demosaics on board (most colour USB cameras) lights background pixels beside the
    silhouette with the object's fringes in their filled colours; `sss import --bayer RGGB` drops them as
    `sss decode --bayer` does and records the pipeline, which the view calibration then reproduces."""
    from sssphase_core.processing.isp import through_camera
    from sssphase_core.processing.psp import Reason

    plan = [f for f in capture_plan(W, H, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    yy, xx = np.mgrid[:H, :W]
    inside = ((yy - H / 2) / 16) ** 2 + ((xx - W / 2) / 22) ** 2 <= 1  # an ellipse on a black background
    light = emitted_light(np.stack([f.pattern() for f in plan]), 2.2) * np.float32([0.8, 0.5, 0.3]) * inside[..., None]
    frames = np.clip(through_camera(light.astype(np.float32), demosaic="malvar", median=False, layout="RGGB"), 0, None)
    folder = tmp_path / "f"
    folder.mkdir()
    for f, img in zip(plan, frames, strict=True):
        np.save(folder / (f.key.replace("/", "__") + ".npy"), img)
    plain = import_folder(folder, tmp_path / "s", "plain", (W, H), patch=16, bayer="none")
    told = import_folder(folder, tmp_path / "s", "told", (W, H), patch=16, bayer="rggb", demosaic="malvar")
    outside = lambda s: int((s.load(0, "corr/mask").astype(bool) & ~inside).sum())  # noqa: E731
    assert outside(plain) > 10 and outside(told) < outside(plain) // 2, (outside(plain), outside(told))
    assert told.manifest["views"]["0"]["coverage"].get(Reason.DEMOSAIC_BLEED.name, 0) > 0
    assert told.manifest["views"]["0"]["camera_isp"] == {"bayer": "RGGB", "demosaic": "malvar", "median": False}
    assert plain.manifest["views"]["0"]["camera_isp"] is None
    with pytest.raises(InputError, match=r"--demosaic must be one of malvar, opencv, other"):
        import_folder(folder, tmp_path / "s", "bad", (W, H), bayer="RGGB", demosaic="ahd")
    with pytest.raises(InputError, match=r"unknown Bayer layout 'RGBG'"):
        import_folder(folder, tmp_path / "s", "bad", (W, H), bayer="RGBG")
    with pytest.raises(InputError, match=r"--demosaic malvar says how .* --bayer none says there were none"):
        import_folder(folder, tmp_path / "s", "bad", (W, H), bayer="none", demosaic="malvar")  # was ignored
    assert not (tmp_path / "s" / "bad").exists()


def test_the_demosaicing_a_camera_used_is_the_one_that_gives_its_frames_back():
    """A demosaiced frame is a fixed point of its method (its samples kept, the rest filled from them, but where the
    camera clipped): Malvar's and OpenCV's frames are told apart, as floats and as 8-bit codes; OpenCV's bilinear
    frames and a three-chip camera's are neither. Not said, an exported sim crab relit 10 dB below its session."""
    import cv2

    from sssphase_core.processing.isp import bayer_mosaic, detect_demosaic, through_camera

    psp = [f for f in capture_plan(W, H) if f.key.startswith("psp/x/")]
    finest = min(int(f.key.split("/")[2][1:]) for f in psp)
    plan = [f for f in psp if f.key.startswith(f"psp/x/p{finest}/")]
    light = (emitted_light(np.stack([f.pattern() for f in plan]), 2.2) * np.float32([0.9, 0.45, 0.15])).astype(np.float32)
    noisy = light + np.random.default_rng(0).normal(size=light.shape).astype(np.float32) * np.sqrt(light / 3000)
    mask = np.ones((H, W), bool)
    for method in ("malvar", "opencv"):
        frames = np.clip(through_camera(noisy, demosaic=method, layout="GBRG"), 0, 1)
        for codes in (frames, np.round(frames * 255) / 255):
            found, why = detect_demosaic(codes, "GBRG", mask)
            assert found == method, why
    bilinear = np.stack([cv2.cvtColor(np.round(bayer_mosaic(f) * 65535).astype(np.uint16), cv2.COLOR_BayerBG2RGB)
                         for f in np.clip(noisy, 0, 1)]).astype(np.float32) / 65535
    for frames in (bilinear, noisy):
        found, why = detect_demosaic(frames, "RGGB", mask)
        assert found is None and why.startswith("neither method gives its fringe frames back"), why


def test_the_bayer_layout_a_camera_demosaiced_from_is_read_from_the_frames_noise(tmp_path):
    """Each photosite's shot noise follows its own colour, and the PSP residual I0 + I2 - I1 - I3 is noise
    only, so its variance per 2 x 2 site gives the layout away (`--bayer auto`, the default); frames with no
    colour filter array (renders, three-chip cameras) have none to give."""
    from sssphase_core.processing.isp import detect_bayer_layout, through_camera
    from sssphase_core.processing.psp import Reason

    w, h = 2 * W, 2 * H  # enough pixels per 2 x 2 site (isp.BAYER_MIN_PIXELS)
    plan = [f for f in capture_plan(w, h, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    yy, xx = np.mgrid[:h, :w]
    inside = ((yy - h / 2) / 38) ** 2 + ((xx - w / 2) / 54) ** 2 <= 1
    light = (emitted_light(np.stack([f.pattern() for f in plan]), 2.2) * np.float32([0.9, 0.45, 0.15])
             * inside[..., None]).astype(np.float32)
    rng = np.random.default_rng(0)
    noisy = light + rng.normal(size=light.shape).astype(np.float32) * np.sqrt(light / 3000)  # shot noise
    for name, frames in (("bayer", through_camera(noisy, demosaic="malvar", median=False, layout="GRBG")),
                         ("bayer_opencv", through_camera(noisy, demosaic="opencv", median=False, layout="GRBG")),
                         ("three_chip", noisy)):
        folder = tmp_path / name
        folder.mkdir()
        for f, img in zip(plan, np.clip(frames, 0, None), strict=True):
            np.save(folder / (f.key.replace("/", "__") + ".npy"), img)
        s = import_folder(folder, tmp_path / "s", name, (w, h), patch=16)
        info = s.manifest["views"]["0"]
        if name == "bayer_opencv":  # its edge-aware filling mixes the sites' noise: suspected, said, not applied
            assert "the 2 x 2 sites' noise varies" in info["bayer_detected"] and info["camera_isp"] is None
        elif name == "bayer":
            assert info["bayer_detected"].startswith("GRBG: the noise of its 2 x 2 sites follows GRBG"), info["bayer_detected"]
            assert info["camera_isp"]["bayer"] == "GRBG" and info["coverage"].get(Reason.DEMOSAIC_BLEED.name, 0) > 0
            # and the method, which relighting needs to compare relit fringes through it (not said: 10 dB lower)
            assert info["camera_isp"]["demosaic"] == "malvar", info["demosaic_detected"]
            assert info["demosaic_detected"].startswith("malvar: its fringe frames come back from malvar demosaicing")
        else:
            assert info["bayer_detected"].startswith("none: the noise is alike at every 2 x 2 site"), info["bayer_detected"]
            assert info["camera_isp"] is None
    # a named layout the noise contradicts is said (a GRBG camera's frames named RGGB relit 9 dB low in silence)
    with pytest.warns(UserWarning, match=r"--bayer RGGB, but the noise of its 2 x 2 sites follows GRBG's colours .* is the "
                                         r"camera's layout GRBG\?"):
        import_folder(tmp_path / "bayer", tmp_path / "s", "named_wrong", (w, h), patch=16, bayer="RGGB")
    told = import_folder(tmp_path / "bayer_opencv", tmp_path / "s", "told", (w, h), patch=16, bayer="GRBG")
    assert told.manifest["views"]["0"]["camera_isp"] == {"bayer": "GRBG", "demosaic": "opencv", "median": False}
    # a path tracer's firefly (one sample 10^4 times the light) in one frame: still no layout, still GRBG
    for frames, want in ((noisy, None), (through_camera(noisy, demosaic="malvar", median=False, layout="GRBG"), "GRBG")):
        fired = frames[:8].copy()
        fired[1, h // 2 + 1, w // 2] = 1e4
        layout, why = detect_bayer_layout([fired[:4], fired[4:]], frames[-2], inside)
        assert layout == want, why
        if want is None:
            assert why.startswith("the noise is alike at every 2 x 2 site"), why
    psp = np.stack([light[i] for i in range(8)])
    assert detect_bayer_layout([psp[:4], psp[4:]], light[-2], inside)[0] is None  # noise-free: nothing to read
    # a noise-free render whose camera pixel spans 1.5 projector pixels: each set's residual alternates along its
    # own fringes (columns for x, rows for y), which summed over the sets looked like a layout (correlation 1.00)
    aliased = psp.copy()
    aliased[0] += (1 + 0.8 * (-1) ** xx)[..., None] * np.float32([0.02, 0.01, 0.004]) * inside[..., None]
    aliased[4] += (1 + 0.8 * (-1) ** yy)[..., None] * np.float32([0.004, 0.01, 0.02]) * inside[..., None]
    layout, why = detect_bayer_layout([aliased[:4], aliased[4:]], light[-2], inside)
    assert layout is None and why.startswith("the 2 x 2 sites' residual differs between the fringe sets"), why


def test_an_import_without_dot_grids_evaluates_without_measured_and_a_black_above_the_fringes_is_refused(tmp_path):
    """`sss eval relight` with its default backends relit none and analytic, wrote their images, then failed on
    `measured` (no dot grids, the usual import); a constant black at 0.75 (white 0.8) imported with a warning
    that fringes averaged -7 of the white's light."""
    plan = [f for f in capture_plan(W, H, references=("white", "black", "checkerboard")) if not f.key.startswith("dots/")]
    folder = tmp_path / "f"
    folder.mkdir()
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        np.save(folder / (f.key.replace("/", "__") + ".npy"), img)
    s = import_folder(folder, tmp_path / "s", "obj", (W, H), patch=K)
    out = tmp_path / "ev"
    res = run_sss(["eval", "relight", str(s.path), "--out", str(out)], timeout=300)
    assert res.returncode == 0 and "measured left out: obj view 0 holds no dot-grid footprints" in res.stdout, res.stdout + res.stderr
    assert {r["backend"] for r in json.loads((out / "relight_eval.json").read_text())["rows"]} == {"none", "analytic"}
    res = run_sss(["eval", "relight", str(s.path), "--backend", "none,measured", "--out", str(tmp_path / "ev2")], timeout=300)
    _one_line_error(res, "--backend measured: obj view 0 has no captured footprints (capture with --footprints)")
    assert not (tmp_path / "ev2").exists() or not any((tmp_path / "ev2").iterdir())
    np.save(folder / "black.npy", np.full((H, W, 3), 0.75, np.float32))
    with pytest.raises(InputError, match=r"black\.npy: the fringe frames average -\d+\.\d\d of the white's light above this "
                                         r"black frame"):
        import_folder(folder, tmp_path / "s", "bright_black", (W, H), patch=K)


def test_frames_of_any_shift_count_give_the_four_step_images_they_imply(tmp_path):
    """Learning and relighting read the paper's 4 shifts per orientation. A renderer's 6-step frames (which
    decoded, then failed every relight) are resampled by their first harmonic: a linear camera sees the
    fringes as A + C cos d + S sin d, so the 4-step images come out as a 4-step capture would have given,
    and the view calibration relights them under the matching 4-step patterns."""
    from sssphase_core.processing.patterns import PSPConfig, psp_config_for
    from sssphase_core.processing.psp import four_step
    from sssphase_core.relight import load_view

    ramp = np.linspace(0, 1, 7, dtype=np.float32)[:, None] * np.ones((7, 5), np.float32)
    sines = np.stack([0.4 + 0.3 * np.cos(2 * ramp + 2 * np.pi * n / 6) for n in range(6)])
    np.testing.assert_allclose(four_step(sines), np.stack([0.4 + 0.3 * np.cos(2 * ramp + np.pi * k / 2) for k in range(4)]),
                               atol=1e-6)
    sessions = {}
    for n in (4, 6):
        base = psp_config_for(W, H)
        config = PSPConfig(period=base.period, n_shifts=n, unwrap_periods=base.unwrap_periods)
        plan = list(capture_plan(W, H, psp=config, references=("white", "black", "checkerboard")))
        folder = tmp_path / f"f{n}"
        folder.mkdir()
        for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
            np.save(folder / (f.key.replace("/", "__") + ".npy"), img)
        sessions[n] = load_view(import_folder(folder, tmp_path / f"s{n}", "ramp", (W, H), patch=K), 0)
    four, six = sessions[4], sessions[6]
    assert six.session.manifest["views"]["0"]["psp_from_shifts"] == 6
    m = four.proj.mask & six.proj.mask
    np.testing.assert_allclose(six.psp[:, m], four.psp[:, m], atol=2e-4)
    np.testing.assert_allclose(six.psp_patterns, four.psp_patterns, atol=1e-6)


def test_an_import_warns_when_a_reference_capture_does_not_follow_its_pattern(tmp_path):
    """Frames rendered for another projector size decode (their names give the fringes) but every named
    pattern, made at the --projector size, is another image: relighting then scored 9.6 dB in silence. Each
    reference capture is compared with its pattern at the decoded points (recorded as reference_match), and its
    light with what its pattern sends, before the outlier repair (a reference at twice the exposure, clipped by it,
    read 1.3x on a sim capture and was not warned of); a reference with many values repaired is said."""
    from sssphase_core.capture.importer import REFERENCE_BRIGHTNESS

    plan = [f for f in capture_plan(W, H, references=("white", "black", "checkerboard"))]
    images = dict(zip((f.key for f in plan), _camera(np.stack([f.pattern() for f in plan])), strict=True))
    for name, swap in (("right", False), ("other", True)):
        folder = tmp_path / name
        folder.mkdir()
        for key, img in images.items():
            if swap and key == "ref/checkerboard":  # the camera saw another checkerboard: its squares swapped
                img = _camera(1.0 - next(f for f in plan if f.key == key).pattern()[None])[0]
            np.save(folder / (key.replace("/", "__") + ".npy"), img)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning for the right pattern
        right = import_folder(tmp_path / "right", tmp_path / "s", "right", (W, H), patch=K)
    assert right.manifest["views"]["0"]["reference_match"]["checkerboard"] > 0.8
    with pytest.warns(UserWarning, match=r"checkerboard \(correlation -0\.\d\d\) does not follow the pattern .* is "
                                         r"--projector right \(64x48\)"):
        other = import_folder(tmp_path / "other", tmp_path / "s", "other", (W, H), patch=K)
    assert other.manifest["views"]["0"]["reference_match"]["checkerboard"] < -0.5
    assert right.manifest["views"]["0"]["reference_brightness"]["checkerboard"] == pytest.approx(1.0, abs=0.05)
    np.save(tmp_path / "right" / "ref__checkerboard.npy", np.float32(0.5) * images["ref/checkerboard"])  # half the exposure
    with pytest.warns(UserWarning, match=r"reference capture checkerboard \(0\.[456]\dx\) holds another amount of light"):
        half = import_folder(tmp_path / "right", tmp_path / "s", "half", (W, H), patch=K)  # scored 12.6 dB in silence
    assert half.manifest["views"]["0"]["reference_brightness"]["checkerboard"] == pytest.approx(0.5, abs=0.08)
    np.save(tmp_path / "right" / "ref__checkerboard.npy", 2 * images["ref/checkerboard"])  # twice the exposure
    with pytest.warns(UserWarning, match=r"reference capture checkerboard \((1\.9[5-9]|2\.0[0-5])x, 1,\d{3} values clipped\) "
                                         r"holds another amount of light"):
        twice = import_folder(tmp_path / "right", tmp_path / "s", "twice", (W, H), patch=K)
    # measured as it came: the outlier repair clips its lit squares towards the white (it read 1.87x after it)
    assert twice.manifest["views"]["0"]["reference_brightness"]["checkerboard"] == pytest.approx(2.0, abs=0.05)
    assert twice.manifest["views"]["0"]["reference_repaired"]["checkerboard"] > 1000
    from sssphase_core.relight.evaluation import evaluate_view

    with pytest.warns(UserWarning, match=r"twice view 0: the reference capture checkerboard \(2\.0\dx\) holds another "
                                         r"amount of light .* measures that, not the relighting"):  # said when scored too
        evaluate_view(load_view(twice, 0), "none", tmp_path / "ev", write=False)
    lamp = images["ref/checkerboard"].copy()
    lamp[:12, :16] += np.float32(1.5) * images["white"][:12, :16]  # a room light on one corner of the scene
    np.save(tmp_path / "right" / "ref__checkerboard.npy", lamp)
    with pytest.warns(UserWarning, match=r"reference capture checkerboard \(\d+ values, \d\.\d% of the lit ones\) held "
                                         r"light brighter than full white could make it"):
        lit = import_folder(tmp_path / "right", tmp_path / "s", "lamp", (W, H), patch=K)
    assert REFERENCE_BRIGHTNESS[0] < lit.manifest["views"]["0"]["reference_brightness"]["checkerboard"] < REFERENCE_BRIGHTNESS[1]


def test_fireflies_setting_the_white_captures_level_are_named_and_left_out_of_it(tmp_path):
    """A render's white with 0.2% of its pixels at 1000 was refused as "the fringe set's mean is 0.0004x the white
    capture's level": the fringes were named, not the white's fireflies. They were then said first, and a render
    with 0.1% fireflies in every frame still scaled its frames by them (1/50) and decoded nothing. The level is
    now its 3 x 3 median's, and the view imports as without them."""
    clean = import_folder(_float_frames(tmp_path / "c", 1.0), tmp_path / "s", "clean", (W, H), patch=K)
    folder = _float_frames(tmp_path / "f", 1.0)
    rng = np.random.default_rng(0)
    for path in folder.glob("*.npy"):  # every frame, as a path tracer's
        image = np.load(path)
        image.reshape(-1, 3)[rng.choice(H * W, max(3, H * W // 500), replace=False)] = 1000.0 if path.stem == "white" \
            else 100.0 * image.max()
        np.save(path, image)
    with pytest.warns(UserWarning, match=r"white.npy: its level .* is set by isolated bright pixels, \d+x its 3 x 3 "
                                         r"median's .*scaled by the median's level instead"):
        s = import_folder(folder, tmp_path / "s", "fireflies", (W, H), patch=K)
    assert s.manifest["rig"]["frame_scale"] == clean.manifest["rig"]["frame_scale"]
    both = s.load(0, "corr/mask") & clean.load(0, "corr/mask")
    assert both.sum() >= 0.95 * clean.load(0, "corr/mask").sum()


def test_frames_too_faint_for_the_decoder_are_scaled_if_float_and_warned_of_if_integer(tmp_path):
    """A render at 0.12 x camera units lost 80% of its object to the decoder's thresholds, in silence (float frames
    with a white level in [0.1, 10] were left as they were); so does a camera exposed far too short."""
    ref = import_folder(_float_frames(tmp_path / "unit", 1.0), tmp_path / "s", "unit", (W, H), patch=K)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # scaled, decoded like camera units, no warning
        dim = import_folder(_float_frames(tmp_path / "dim", 0.12), tmp_path / "s", "dim", (W, H), patch=K)
    assert dim.manifest["rig"]["frame_scale"] == pytest.approx(1 / (0.8 * 0.12), rel=1e-3)
    np.testing.assert_array_equal(dim.load(0, "corr/mask"), ref.load(0, "corr/mask"))
    plan = [f for f in capture_plan(W, H, references=("white", "black")) if f.key.startswith(("psp/", "white", "black"))]
    short = tmp_path / "short"
    short.mkdir()
    ramp = np.linspace(0.005, 0.1, W, dtype=np.float32)[None, :, None]  # exposure x albedo, across the view
    ramp = ramp * np.array([1.0, 0.8, 0.6], np.float32)  # (a coloured object)
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        _write(short, f.key, img * ramp, nested=False)  # 16-bit codes, white far below the top code on the left
    with pytest.warns(UserWarning, match=r"\d+% of the pixels holding light were dropped as too faint for the decoder") as got:
        import_folder(short, tmp_path / "s", "short", (W, H), patch=K)
    # the white's level, said twice (the 16-bit hint and the dim view), is one figure (they quoted 0.0545 and 0.044)
    levels = {re.search(r"white's level is ([0-9.e-]+)", str(w.message))[1] for w in got
              if "white's level is" in str(w.message)}
    assert len(levels) == 1, levels


def test_a_dropped_or_copied_fringe_frame_is_refused_and_shifts_out_of_order_are_named(tmp_path):
    """An all-black or white-copy fringe frame imported without a word (0.7-0.8 px decoding error), and
    frames s1 and s3 exchanged dropped half the object as "unwrap inconsistent" without one."""
    for name, change in (("dropped", lambda img, white: img * 0), ("copied", lambda img, white: white)):
        folder = _float_frames(tmp_path / name, 1.0)
        frame = folder / "psp__x__p18__s1.npy"
        np.save(frame, change(np.load(frame), np.load(folder / "white.npy")))
        with pytest.raises(InputError, match=r"psp__x__p18\*: opposite shifts .* s0 \+ s2 hold 1\.00, s1 \+ s3 hold"):
            import_folder(folder, tmp_path / "s", name, (W, H), patch=K)
        assert not (tmp_path / "s" / name).exists()
    folder = _float_frames(tmp_path / "swapped", 1.0)
    s1, s3 = folder / "psp__x__p18__s1.npy", folder / "psp__x__p18__s3.npy"
    a, b = np.load(s1), np.load(s3)
    np.save(s1, b)
    np.save(s3, a)
    with pytest.warns(UserWarning, match="did not unwrap consistently .* in the order they were projected"):
        import_folder(folder, tmp_path / "s", "swapped", (W, H), patch=K)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the frames as captured: no warning
        import_folder(_float_frames(tmp_path / "clean", 1.0), tmp_path / "s", "clean", (W, H), patch=K)


def _dot_frames(folder: Path) -> Path:
    """The hand-made rig's frames with a full dot grid, as float .npy."""
    plan = capture_plan(W, H, footprints=True, dot_spacing=SPACING, references=("white", "black"))
    folder.mkdir(parents=True)
    for f, img in zip(plan, _camera(np.stack([f.pattern() for f in plan])), strict=True):
        np.save(folder / (f.key.replace("/", "__") + ".npy"), img)
    return folder


def test_dot_frames_must_be_a_whole_grid_holding_the_whites_light(tmp_path):
    """Dot frames replaced by the white (or black) capture made footprints 37x too bright that relit at -23 dB,
    and a grid with 34 of its 36 frames missing imported as footprints with nothing in them, without a word."""
    folder = _dot_frames(tmp_path / "f")
    s = import_folder(folder, tmp_path / "s", "whole", (W, H), patch=K)
    assert abs(s.manifest["views"]["0"]["dots_light_share"] - 1) < 0.05
    missing = folder / "dots__3_5.npy"
    kept = np.load(missing)
    missing.unlink()
    with pytest.raises(InputError, match=r"1 of the 64 frames of a 8 x 8 dot grid are missing \(dots__3_5\)"):
        import_folder(folder, tmp_path / "s", "missing", (W, H), patch=K)
    np.save(missing, kept)
    white = np.load(folder / "white.npy")
    for path in folder.glob("dots__*.npy"):
        np.save(path, white)
    with pytest.raises(InputError, match=r"the 64 dot-grid frames together hold 64\.\d\d of the white capture's light"):
        import_folder(folder, tmp_path / "s", "white", (W, H), patch=K)
    assert not (tmp_path / "s" / "white").exists()
    folder = _dot_frames(tmp_path / "g")
    black = np.load(folder / "black.npy")
    for path in folder.glob("dots__*.npy"):  # captured at 1.5x the white's exposure
        np.save(path, black + 1.5 * (np.load(path) - black))
    with pytest.warns(UserWarning, match=r"hold 1\.5\d of the white .* 1\.5\dx too bright"):
        import_folder(folder, tmp_path / "s", "brighter", (W, H), patch=K)


def test_each_dot_frame_must_light_its_own_dots_and_crops_keep_capture_order(tmp_path):
    """Dot frames named dots__<sy>_<sx> (8,105 of 9,282 crops of the wrong pixels), one frame a copy of another or
    black: the grid's light summed over its frames is unchanged, and each imported without a word. Each frame's
    light must now fall on its own dots at the decoded points; the crops are stored as a capture takes them."""
    folder = _dot_frames(tmp_path / "f")
    s = import_folder(folder, tmp_path / "s", "whole", (W, H), patch=K)
    dots = np.asarray(s.load(0, "transport/dots"))  # each crop's dot (sx, sy): rows of shifts, as captured
    order = [(int(sy), int(sx)) for sx, sy in dots % SPACING]
    assert order == sorted(order) and len(set(order)) == SPACING ** 2
    swapped = tmp_path / "swapped"
    swapped.mkdir()
    for path in folder.iterdir():
        m = re.fullmatch(r"dots__(\d+)_(\d+)\.npy", path.name)
        shutil.copy(path, swapped / (f"dots__{m[2]}_{m[1]}.npy" if m else path.name))
    with pytest.raises(InputError, match=r"dots__1_0.npy: its light falls on projector column 0 and row 1 of each 8 x 8 "
                                         r"cell .* where dots__1_0 lights column 1 and row 0: x and y swapped"):
        import_folder(swapped, tmp_path / "s", "swapped", (W, H), patch=K)
    copied = folder / "dots__2_3.npy"
    kept = np.load(copied)
    shutil.copy(folder / "dots__2_2.npy", copied)
    with pytest.raises(InputError, match=r"dots__2_3.npy: its light falls on projector column 2 and row 2 .* a mislabelled "
                                         r"or copied dot frame"):
        import_folder(folder, tmp_path / "s", "copied", (W, H), patch=K)
    np.save(copied, np.load(folder / "black.npy"))
    with pytest.raises(InputError, match=r"dots__2_3.npy: holds 0.00 of the light a dot frame of this 8 x 8 grid gives"):
        import_folder(folder, tmp_path / "s", "black", (W, H), patch=K)
    np.save(copied, kept)
    assert not any((tmp_path / "s" / n).exists() for n in ("swapped", "copied", "black"))


def test_a_sparse_dot_grid_imports_as_its_capture_keeps_it(tmp_path):
    """`sss capture --dot-stride 4` takes every 4th dot shift: its frames were refused as a 17 x 17 grid with 264
    frames missing, and no option could say otherwise. The stride is the offsets' common divisor, the spacing the
    plan.json's or the last offset plus the stride; the crops are the full grid's at the pixels it covers."""
    full = _dot_frames(tmp_path / "full")
    whole = import_folder(full, tmp_path / "s", "whole", (W, H), patch=K)
    sparse = tmp_path / "sparse"
    shutil.copytree(full, sparse)
    for path in sparse.glob("dots__*.npy"):
        if any(int(v) % 2 for v in re.findall(r"\d+", path.stem)):
            path.unlink()
    s = import_folder(sparse, tmp_path / "s", "sparse", (W, H), patch=K)
    info = s.manifest["views"]["0"]
    assert info["dot_stride"] == 2 and abs(info["dots_light_share"] - whole.manifest["views"]["0"]["dots_light_share"]) < 0.1
    assert "transport/crops" not in s.arrays(0)  # (no light transport from a sparse lattice, as captured)
    rows = {tuple(p): i for i, p in enumerate(np.asarray(whole.load(0, "footprints/pixels")))}
    pixels = np.asarray(s.load(0, "footprints/pixels"))
    assert 0 < len(pixels) < len(rows)
    np.testing.assert_array_equal(np.asarray(s.load(0, "footprints/crops")),
                                  np.asarray(whole.load(0, "footprints/crops"))[[rows[tuple(p)] for p in pixels]])
    (sparse / "dots__2_4.npy").unlink()  # a missing frame is named on the sparse lattice
    with pytest.raises(InputError, match=r"1 of the 16 frames of a 8 x 8 dot grid at dot stride 2 are missing "
                                         r"\(dots__2_4\)"):
        import_folder(sparse, tmp_path / "s", "missing", (W, H), patch=K)


def test_views_in_other_units_are_refused_naming_both_whites(tmp_path):
    """One view in units 1000x the other's: the shared scale crushed view 0, refused as "100% shadow"."""
    _float_frames(tmp_path / "f" / "view_000", 1.0)
    _float_frames(tmp_path / "f" / "view_001", 1000.0)
    with pytest.raises(InputError, match=r"view_001/white.npy is 1e\+03x as bright as .*view_000/white.npy"):
        import_folder(tmp_path / "f", tmp_path / "s", "o", (W, H), patch=K)


def test_exr_frames_are_placed_by_their_display_window(tmp_path):
    """A renderer's overscan (data window beyond the display window) or region render was read as its data
    window's pixels: shifted 6 px against the other frames, decoded 0.6 px off without a word."""
    import OpenEXR

    from sssphase_core.store.exr import exr_size, read_exr

    image = np.random.default_rng(0).random((20, 36)).astype(np.float32)
    for name, data_window, want in (("overscan", ((-3, 0), (32, 19)), image[:, 3:33]),
                                    ("region", ((4, 2), (39, 21)), np.pad(image[:18, :26], ((2, 0), (4, 0))))):
        path = tmp_path / f"{name}.exr"
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "dataWindow": data_window, "displayWindow": ((0, 0), (29, 19))}
        with OpenEXR.File(header, {c: image for c in "RGB"}) as f:
            f.write(str(path))
        got = read_exr(path)
        assert got.shape == (20, 30, 3) and exr_size(path) == (20, 30)
        assert np.array_equal(got[..., 1], want)


def test_an_exr_whose_data_window_is_over_the_frame_limit_is_refused_before_decoding(tmp_path, monkeypatch):
    """The size check read the display window, the library decoded the whole data window: a 5 MB file with a
    20000 x 20000 data window behind a 256 x 192 display took 5 GB, then relit and exited 0. (The limit is
    lowered here so that the file stays small.)"""
    import OpenEXR

    from sssphase_core.errors import DataError
    from sssphase_core.store import imageio
    from sssphase_core.store.exr import exr_size, read_exr

    monkeypatch.setattr(imageio, "MAX_FRAME_PIXELS", 1000)
    path = tmp_path / "overscan.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "dataWindow": ((0, 0), (39, 29)), "displayWindow": ((0, 0), (29, 19))}  # 1200 px behind 600
    with OpenEXR.File(header, {c: np.zeros((30, 40), np.float32) for c in "RGB"}) as f:
        f.write(str(path))
    for read in (read_exr, exr_size):
        with pytest.raises(DataError, match=r"declares a 40x30 pixel window, over 0 MP: .*refused before decoding it"):
            read(path)


def test_frames_too_large_for_the_memory_are_refused_from_their_headers(tmp_path, monkeypatch):
    """Frames that compress to almost nothing (constant 2400x1800 PNGs, 33 kB each) but decode to 52 MB each:
    the view's frames are held as float32 until it is processed, so more than the free memory ended in the
    kernel's out-of-memory kill (a 64-MP bomb per frame passed the per-frame limit). Refused from the first
    frame's header, before a pixel is decoded."""
    import time

    from sssphase_core import compute

    folder = tmp_path / "big"
    folder.mkdir()
    for f in capture_plan(W, H, references=("white", "black")):
        level = 1.0 if f.key == "white" else 0.01 if f.key == "black" else 0.5
        cv2.imwrite(str(folder / (f.key.replace("/", "__") + ".png")), np.full((1800, 2400, 3), int(level * 65535), np.uint16))
    monkeypatch.setattr(compute, "available_memory", lambda: 2 << 30)  # a machine with 2 GiB free
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"its 26 frames of 2400x1800 need about 4\.\d GiB to import, more than the 2\.0 GiB free"):
        import_folder(folder, tmp_path / "s", "big", (W, H))
    assert time.monotonic() - t0 < 2 and not (tmp_path / "s" / "big").exists()


def test_frame_names_with_more_unwrapping_periods_than_any_plan_are_refused_naming_the_folder(tmp_path):
    for o in "xy":
        for period in (11, *range(20, 200, 10)):  # 18 unwrapping periods: a plan has at most 16
            for shift in range(4):
                np.save(tmp_path / f"psp__{o}__p{period}__s{shift}.npy", np.zeros((4, 4, 3), np.float32))
    for name in ("white", "black"):
        np.save(tmp_path / f"{name}.npy", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(InputError, match=f"{tmp_path}: its PSP frame names: at most 16 unwrapping periods, got 18"):
        import_folder(tmp_path, tmp_path / "s", "o", (W, H), patch=K)


def test_a_view_whose_lit_pixels_mostly_did_not_decode_is_said_to_be_scored_on_the_rest(frames, handmade, tmp_path):
    """A render whose object scattered too widely for the fringes decoded the wall only: relit black where the
    object was, and scored 65 dB "on the object mask" without a word, after an import that advised a longer
    exposure. The import now names the fringes' period, and the share of the lit pixels that decoded is recorded
    with each score and warned of below 90%."""
    from typer.testing import CliRunner

    from sssphase_cli.main import app
    from sssphase_core.relight.views import DECODED_SHARE_WARN

    def washed(img: np.ndarray) -> np.ndarray:  # the left half's fringes blurred away; its light (the white) stays
        img[:, : W // 2] = gaussian_filter(img, (12, 12, 0), mode="nearest")[:, : W // 2]
        return img

    with pytest.warns(UserWarning, match=r"\d+% of the pixels holding light were dropped: well exposed .* their fringes "
                                         r"show too little modulation: the finest period \(\d+ projector px\) may be too fine"):
        lost = import_folder(_perturbed(frames, tmp_path / "washed", washed), tmp_path / "s", "washed", (W, H), patch=K)
    assert load_view(handmade, 0).decoded_share >= DECODED_SHARE_WARN > load_view(lost, 0).decoded_share
    for session, warned in ((handmade, False), (lost, True)):
        out = tmp_path / f"ev_{session.name}"
        with warnings.catch_warnings(record=True) as caught:  # (the CLI prints them as "warning: ...")
            warnings.simplefilter("always")
            res = CliRunner().invoke(app, ["eval", "relight", str(session.path), "--backend", "none", "--out", str(out)])
        assert res.exit_code == 0, res.output
        said = [w for w in caught if re.search(r"only \d+% of the pixels the projector lights decoded; the others stay "
                                               r"black", str(w.message))]
        assert bool(said) == warned, [str(w.message) for w in caught]
        rows = json.loads((out / "relight_eval.json").read_text())["rows"]
        assert all((r["decoded_share"] < DECODED_SHARE_WARN) == warned for r in rows), rows


def test_psp_frame_names_are_checked_period_first_then_orientations_then_shifts(tmp_path):
    from sssphase_core.capture.importer import psp_config_from_names

    def keys(orientations, period, shifts=range(4)):
        return [f"psp/{o}/p{period}/s{n}" for o in orientations for n in shifts]

    cases = ((keys("x", 0), "a PSP period must be positive, got 0 in the frame names"),  # said "the y orientation ..."
             (keys("x", 20), "the y orientation has no PSP frames at period 20"),
             (keys("x", 20) + keys("y", 20, (0, 2, 3)), "PSP frames y, period 20 have shifts [0, 2, 3]"),
             (keys("xy", 20) + keys("x", 200, range(5)) + keys("y", 200),  # a stray s4: "period 20 have shifts
              "PSP frames x, period 20 have 4 shifts but x, period 200 has 5 (up to s4): every set shares one shift "
              "count"))  # [0, 1, 2, 3]; every set needs shifts 0..N-1", which they have
    for names, expected in cases:
        with pytest.raises(InputError, match=re.escape(f"{tmp_path}: {expected}")):
            psp_config_from_names(tmp_path, names)
    config = psp_config_from_names(tmp_path, keys("xy", 20) + keys("xy", 200))
    assert (config.period, config.n_shifts, config.unwrap_periods) == (20, 4, (200,))


def test_a_reference_name_outside_its_characters_says_which_are_allowed(tmp_path):
    from sssphase_core.capture.importer import frame_files

    for name in ("ref__sp ace.npy", "ref__ünï.npy"):
        np.save(tmp_path / name, np.zeros((2, 2), np.float32))
        with pytest.raises(InputError, match=r"is no frame name .*pattern__<name> \(a name of ASCII letters, digits, '_', "
                                             r"'\.' and '-', at most 64\)"):
            frame_files(tmp_path)
        (tmp_path / name).unlink()


def test_a_white_of_another_exposure_than_the_fringes_is_refused_not_repaired_as_fireflies(tmp_path):
    """A white rendered at twice the fringes' scale: every lit value lay above the brightest any pattern gives,
    and 17,304 of them were "repaired" from their neighbours (towards 0) with exit 0."""
    from sssphase_core.errors import DataError

    folder = _float_frames(tmp_path / "frames", 1.0)
    np.save(folder / "white.npy", np.load(folder / "white.npy") * np.float32(2))
    # (named by its file, and said as what it is: the white is brighter than the fringes say white is)
    with pytest.raises(DataError, match=r"frames/white.npy: [\d,]+ of its values \(\d+% of the lit ones\) are brighter "
                                        r"than the fringe sets say full white is .* another exposure or units"):
        import_folder(folder, tmp_path / "s", "twice", (W, H), patch=K)
    firefly = _float_frames(tmp_path / "firefly", 1.0)  # a few stray samples are still repaired, not refused
    frame = np.load(firefly / "white.npy")
    frame[5, 7] *= 50
    np.save(firefly / "white.npy", frame)
    session = import_folder(firefly, tmp_path / "s", "firefly", (W, H), patch=K)
    assert session.manifest["views"]["0"]["outliers_repaired"] >= 1


def test_a_plan_json_beside_the_frames_must_agree_with_the_import(tmp_path):
    """The plan `sss patterns` wrote for a 320x240 projector, beside frames imported as another size, was ignored."""
    import json

    folder = _float_frames(tmp_path / "frames", 1.0)
    plan = json.loads(capture_plan(W, H, references=("white", "black")).to_json())
    (folder / "plan.json").write_text(json.dumps(plan))
    assert import_folder(folder, tmp_path / "s", "same", (W, H), patch=K).views() == [0]
    for edit, expected in (({"projector": [W * 2, H * 2], "frames": []}, rf"is the plan of a {W * 2}x{H * 2} projector, but --projector "
                                                          rf"says {W}x{H}"),
                           ({"gamma": 1.0}, r"made its patterns for a projector gamma of 1, but --gamma says 2.2: pass "
                                            r"--gamma 1"),
                           ({"psp": {**plan["psp"], "period": plan["psp"]["period"] + 1}}, r"plans PSP period .* but the "
                                                                                           r"frame names say period")):
        (folder / "plan.json").write_text(json.dumps({**plan, **edit}))
        with pytest.raises(InputError, match=expected):
            import_folder(folder, tmp_path / "s", "other", (W, H), patch=K)


def test_a_renderers_frame_number_after_a_frame_name_is_pointed_out(tmp_path):
    """Blender writes white0001.exr: it was refused as no frame name, without saying why."""
    from sssphase_core.capture.importer import frame_files

    for name, frame in (("white0001.npy", "white"), ("black_0001.npy", "black"), ("psp__x__p20__s0.0042.npy", "psp/x/p20/s0")):
        np.save(tmp_path / name, np.zeros((2, 2), np.float32))
        with pytest.raises(InputError, match=rf"is no frame name .*: without the renderer's frame number \d+ it would be "
                                             rf"frame '{re.escape(frame)}'"):
            frame_files(tmp_path)
        (tmp_path / name).unlink()


@pytest.mark.parametrize(("record", "expected"), [
    ({"denoise_smoothing": ["abc", "abc"]}, r"transport record is damaged \(denoise_smoothing"),  # internal ValueError
    ({"denoise_smoothing": [float("nan"), -5.0]}, r"transport record is damaged \(denoise_smoothing"),  # a -5 px mask
    ({"denoise_smoothing": [1.0 + i / 100 for i in range(300)]}, "1 to 16 mask widths"),  # minutes of denoising
    ([1], r"transport record is damaged \(not a table\)"),  # internal AttributeError
    ({"noise_dropped": True, "denoise_smoothing": [1.0, 2.0], "noise": "x"}, r"damaged \(noise x\)"),
])
def test_a_damaged_transport_record_is_one_line(handmade, tmp_path, record, expected):
    import json

    from sssphase_core.errors import DataError
    from sssphase_core.relight import load_view
    from sssphase_core.relight.backends import make_source

    s = _copy(handmade, tmp_path)
    manifest = json.loads((s.path / "manifest.json").read_text())
    manifest["views"]["0"]["transport"] = record
    (s.path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataError, match=expected):
        make_source("measured", load_view(Session.open(s.path), 0))


def test_transport_indices_outside_the_image_or_projector_are_refused(handmade):
    """A dot of 10^6 was an internal IndexError; a dot of -1 lit the projector's last column without a word."""
    from sssphase_core.errors import DataError
    from sssphase_core.relight import load_view
    from sssphase_core.relight.backends import _check_transport

    rv = load_view(handmade, 0)
    pixels, dots, crops = handmade.load(0, "transport/pixels"), handmade.load(0, "transport/dots"), handmade.read(0, "transport/crops")
    _check_transport(rv, pixels, dots, crops)  # as captured
    for name, a, b, said in (("dots", pixels, np.full_like(dots, 10**6), "holds positions outside the .* projector"),
                             ("dots", pixels, -dots - 1, "holds positions outside the .* projector"),
                             ("pixels", pixels - 10**4, dots, "holds positions outside the .* camera image"),
                             ("pixels", pixels[:-1], dots, f"not {len(crops)} whole-number pairs")):
        with pytest.raises(DataError, match=f"transport/{name} (is .*)?{said}"):
            _check_transport(rv, a, b, crops)


def _rewritten(session: Session, root: Path, name: str, change) -> Session:
    """A copy of ``session`` whose view-0 array ``name`` is ``change(array)``, written as sssphase writes arrays and
    recorded in the manifest with its checksum: intact, as another program could write it."""
    import json
    import shutil

    from sssphase_core.store.session import _chunk_count, _chunks, _zarr_write, array_checksum

    s = _copy(session, root)
    data = np.ascontiguousarray(change(s.load(0, name)))
    shutil.rmtree(s.path / "view_000" / name)
    _zarr_write(s.path / "view_000" / name, data)
    manifest = json.loads((s.path / "manifest.json").read_text())
    manifest["views"]["0"]["arrays"][name] = {"shape": list(data.shape), "dtype": data.dtype.str,
                                              "checksum": array_checksum(data),
                                              "chunks": _chunk_count(data.shape, _chunks(data.shape, data.dtype.itemsize))}
    (s.path / "manifest.json").write_text(json.dumps(manifest))
    return Session.open(s.path)


def test_crops_of_no_light_are_refused_where_they_are_read(handmade, tmp_path):
    """Crops of -60000 (intact, checksums matching) relit at 16 dB with exit 0 and trained a decoder to a loss of
    1e10; `sss validate` said ok."""
    from sssphase_core.errors import DataError
    from sssphase_core.learning.data import session_views
    from sssphase_core.relight import load_view
    from sssphase_core.relight.backends import make_source

    negative = lambda a: np.full_like(a, -60000)  # noqa: E731
    transport = _rewritten(handmade, tmp_path / "t", "transport/crops", negative)
    with pytest.raises(DataError, match="transport/crops: .*below -0.25 x the white level"):
        make_source("measured", load_view(transport, 0))
    assert any("array transport/crops" in p for p in transport.validate())
    crops = _rewritten(handmade, tmp_path / "f", "footprints/crops", negative)
    with pytest.raises(DataError, match="footprints/crops: .*below -0.25 x the white level"):
        session_views(crops.path, footprints=True)
    assert any("array footprints/crops" in p for p in crops.validate())


def test_a_square_view_with_as_many_unwrapping_frames_as_rows_exports_each_frame(tmp_path):
    """A 16 x 16 view kept 16 unwrapping frames, (16, 16, 16, 3): their first two sizes are the view's, and
    `sss export` took the stack for one image and failed ("cannot write an array of shape (16, 16, 16, 3)")."""
    from sssphase_core.reporting.export import export_session
    from sssphase_core.store.exr import read_exr

    rng = np.random.default_rng(0)
    session = Session.create(tmp_path / "s", "square")
    writer = session.begin_view(0)
    writer.write("white", rng.random((16, 16, 3), dtype=np.float32))
    writer.write("corr/xp", rng.random((16, 16), dtype=np.float32))
    stack = rng.random((16, 16, 16, 3), dtype=np.float32)
    writer.write("unwrap", stack)
    writer.commit()
    export_session(Session.open(session.path), tmp_path / "e")
    frames = sorted((tmp_path / "e" / "square" / "view_000" / "unwrap").glob("*.exr"))
    assert len(frames) == 16
    assert np.array_equal(read_exr(frames[5]), stack[5])
    assert read_exr(tmp_path / "e" / "square" / "view_000" / "corr_xp.exr").shape[:2] == (16, 16)


def test_an_imported_session_exports_and_imports_again_and_an_export_without_unwrapping_frames_says_why_not(tmp_path):
    """The docs promise that an export imports again; an imported session kept no unwrapping frames, so its
    export did not, and the error blamed --projector."""
    from sssphase_core.reporting.export import export_session

    session = import_folder(_float_frames(tmp_path / "frames", 1.0), tmp_path / "s", "o", (W, H), patch=K)
    assert "unwrap" in session.arrays(0)
    export_session(session, tmp_path / "e")
    again = import_folder(tmp_path / "e" / "o", tmp_path / "s2", "o", (W, H), patch=K)
    assert np.array_equal(np.asarray(again.read(0, "corr/mask")), np.asarray(session.read(0, "corr/mask")))
    # the export carries its plan: the projector's size given the wrong way round was imported in silence
    with pytest.raises(InputError, match=rf"plan.json is the plan of a {W}x{H} projector, but --projector says {H}x{W}"):
        import_folder(tmp_path / "e" / "o", tmp_path / "s4", "o", (H, W), patch=K)
    shutil.rmtree(tmp_path / "e" / "o" / "view_000" / "unwrap")  # as a session captured without --keep-unwrap
    with pytest.raises(InputError, match=r"PSP frames of one period \(\d+ px\) and none of a longer period to unwrap"):
        import_folder(tmp_path / "e" / "o", tmp_path / "s3", "o", (W, H), patch=K)
