"""Capture sessions end to end through a real daemon process with the sim plugin."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from sss_process import run_sss

from sssphase_core.capture import DEFAULT_HDR, CaptureRequest, RigSpec, import_folder, run_capture
from sssphase_core.errors import DataError, InputError
from sssphase_core.processing.psp import Reason
from sssphase_core.store import session as session_mod
from sssphase_core.store.session import Session

VIEWS = 2
OBJECT = "apple"
CAPTURE = ("capture", "--object", OBJECT, "--views", str(VIEWS), "--reference", "checkerboard")
SLOW_RIG = """
[devices]
camera = "sim:camera0"
projector = "sim:projector0"
turntable = "sim:turntable0"
[options]
grab_delay_s = 0.1
"""


def _arrays(s: Session) -> dict[str, np.ndarray]:
    return {f"{v}/{n}": s.load(v, n) for v in s.views() for n in s.arrays(v)}


def _wait_for(predicate, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _view_status(root: Path, view: int) -> str:
    try:
        return json.loads((root / OBJECT / "manifest.json").read_text())["views"].get(str(view), {}).get("status", "")
    except (OSError, ValueError):
        return ""


@pytest.fixture(scope="module")
def reference(runtime_dir, tmp_path_factory):
    """An uninterrupted capture through the CLI, with no daemon running (so it starts one)."""
    out = tmp_path_factory.mktemp("ref")
    runtime = Path(tempfile.mkdtemp(prefix="sssr", dir="/tmp"))  # no daemon has ever run here
    done = run_sss([*CAPTURE, "--out", str(out)], timeout=240, env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    shutil.rmtree(runtime, ignore_errors=True)
    assert done.returncode == 0, done.stderr + done.stdout
    return out, done.stdout, Session.open(out / OBJECT)


def test_capture_without_daemon_starts_one_and_writes_a_valid_session(reference, sss):
    out, stdout, s = reference
    assert "no daemon running: started a local one (pid" in stdout
    assert s.views() == list(range(VIEWS)) and s.objects == [OBJECT]
    ok = sss("validate", str(out / OBJECT))
    assert ok.returncode == 0 and "checksums match" in ok.stdout
    m = s.manifest
    assert m["devices"]["camera"]["id"] == "sim:camera0" and m["plugins"]["sim"]
    assert len(m["plan"]["frames"]) == 2 * 3 * 4 + 3  # x/y, 3 periods, 4 shifts; white, black, checkerboard
    psp = s.read(0, "psp")
    assert psp.shape == (8, 192, 256, 3) and psp.dtype == np.float32 and not isinstance(psp, np.ndarray)
    assert np.asarray(psp[3, 100:102]).shape == (2, 256, 3)
    for name in ("white", "black", "ref/checkerboard", "corr/reason", "gt/labels", "gt/render/checkerboard"):
        assert m["views"]["1"]["arrays"][name]["checksum"].startswith("sha256:")
    # the decoded correspondence matches the simulator's exact one where it is valid
    xp, mask, gt = s.load(1, "corr/xp"), s.load(1, "corr/mask"), s.load(1, "gt/proj_xy")
    assert mask.sum() > 2000
    assert np.nanmedian(np.abs(xp[mask] - gt[..., 0][mask])) < 0.5
    white, render = s.load(0, "white"), s.load(0, "gt/render/white")
    assert abs(float(white[mask].mean()) - float(render[mask].mean())) < 0.05 * float(render[mask].mean())


@pytest.mark.parametrize("bad", ["../evil", "/etc/passwd", "a/b", "..", "x" * 80])
def test_object_names_that_escape_the_root_are_refused(bad, sss, tmp_path):
    done = sss("capture", "--object", bad, "--views", "1", "--out", str(tmp_path / "s"))
    assert done.returncode == 2 and "is not allowed" in done.stderr
    assert not (tmp_path / "s").exists() and not (tmp_path / "evil").exists()


def test_unknown_sim_object_lists_the_catalogue(daemon, sss, tmp_path):
    done = sss("capture", "--object", "banana", "--views", "1", "--out", str(tmp_path))
    assert done.returncode == 2 and "banana" in done.stderr and "apple" in done.stderr and "lego" in done.stderr


@pytest.mark.slow
def test_daemon_sigkill_mid_capture_then_resume_is_byte_identical(reference, daemon_factory, tmp_path):
    proc, _, runtime = daemon_factory()
    args = [sys.executable, "-c", "from sssphase_cli.main import main; main()", *CAPTURE, "--out", str(tmp_path),
            "--timeout", "2"]
    cli = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    _wait_for(lambda: _view_status(tmp_path, 0) == "complete" and _view_status(tmp_path, 1) == "capturing")
    time.sleep(0.3)  # into view 1's frame stream
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    _, err = cli.communicate(timeout=60)
    assert cli.returncode == 2 and re.search(r"stopped answering|did not answer|has exited \(killed, or crashed", err), err
    assert "complete views are kept; continue with --resume" in err, err
    assert Session.open(tmp_path / OBJECT).views() == [0]
    _, _, runtime = daemon_factory()
    done = subprocess.run([*args, "--resume"], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    assert done.returncode == 0, done.stderr
    resumed, expected = _arrays(Session.open(tmp_path / OBJECT)), _arrays(reference[2])
    assert resumed.keys() == expected.keys()
    for name, arr in expected.items():
        assert arr.dtype == resumed[name].dtype and arr.tobytes() == resumed[name].tobytes(), name
    other = subprocess.run([*args, "--resume", "--seed", "7"], capture_output=True, text=True, timeout=120,
                           env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)})
    assert other.returncode == 2 and "was captured with other rig settings" in other.stderr, other.stderr
    assert "" not in other.stdout.splitlines()  # no empty progress display before the one-line refusal


def test_ctrl_c_leaves_a_resumable_session(daemon_factory, tmp_path, sss):
    _, _, runtime = daemon_factory()
    (tmp_path / "rig.toml").write_text(SLOW_RIG)
    args = ["capture", "--object", OBJECT, "--views", "1", "--out", str(tmp_path), "--rig", str(tmp_path / "rig.toml")]
    cli = subprocess.Popen([sys.executable, "-c", "from sssphase_cli.main import main; main()", *args],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)},
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    _wait_for(lambda: _view_status(tmp_path, 0) == "capturing")
    time.sleep(0.5)
    cli.send_signal(signal.SIGINT)
    _, err = cli.communicate(timeout=30)
    assert cli.returncode == 130 and "interrupted" in err
    s = Session.open(tmp_path / OBJECT)
    assert s.views() == [] and s.status(0) == "interrupted" and not list((tmp_path / OBJECT).glob(".view_*"))
    done = sss("validate", str(tmp_path / OBJECT))
    assert done.returncode == 2 and "rerun with --resume" in done.stdout  # resuming is tested with SIGKILL below


def test_disk_full_is_reported_and_the_session_resumes(reference, daemon_factory, tmp_path, monkeypatch):
    _, client, _ = daemon_factory()
    shutil.copytree(reference[0] / OBJECT, tmp_path / OBJECT)
    s = Session.open(tmp_path / OBJECT)
    s.manifest["views"].pop("1")
    s.save()
    shutil.rmtree(tmp_path / OBJECT / "view_001")

    def full(name: str) -> None:
        if name == "corr/xp":
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(session_mod, "FAULT_HOOK", full)
    req = CaptureRequest(OBJECT, views=VIEWS, references=("checkerboard",), resume=True, out=tmp_path)
    with pytest.raises(DataError, match="disk full.*--resume"):
        run_capture(client, req)
    s = Session.open(tmp_path / OBJECT)
    assert s.views() == [0] and s.status(1) == "interrupted" and not (tmp_path / OBJECT / ".view_001.partial").exists()
    assert s.validate() == ["view 1: interrupted (not captured completely; rerun with --resume)"]


def test_validate_reports_corrupt_and_missing_arrays(reference, tmp_path, sss):
    shutil.copytree(reference[0] / OBJECT, tmp_path / OBJECT)
    view = tmp_path / OBJECT / "view_000"
    chunk = max((p for p in (view / "psp").rglob("*") if p.is_file() and p.name != "zarr.json"), key=lambda p: p.stat().st_size)
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    shutil.rmtree(view / "white")
    problems = Session.open(tmp_path / OBJECT).validate()
    assert "view 0: array psp is corrupt (a chunk's CRC32C checksum does not match its data)" in problems, problems  # in
    # words: zarr's message ended in both checksums as raw bytes
    assert any("white" in p and "missing" in p for p in problems)
    done = sss("validate", str(tmp_path / OBJECT))
    assert done.returncode == 2 and "problem(s)" in done.stderr and "corrupt" in done.stdout
    # a deleted chunk and a shape that disagrees with the manifest were both called "a chunk fails its checksum"
    other = tmp_path / "other" / OBJECT
    shutil.copytree(reference[0] / OBJECT, other)
    next(p for p in (other / "view_000" / "corr" / "xp").rglob("*") if p.is_file() and p.name != "zarr.json").unlink()
    meta = json.loads((other / "manifest.json").read_text())
    meta["views"]["0"]["arrays"]["white"]["shape"] = [10, 10, 3]
    (other / "manifest.json").write_text(json.dumps(meta))
    problems = Session.open(other).validate()
    assert any("corr/xp is damaged (1 of" in p and "chunks missing" in p for p in problems), problems
    assert any("white is damaged (shape" in p and "(10, 10, 3)" in p for p in problems), problems
    # a manifest without its plan's projector passed validate and was refused by relight
    planless = tmp_path / "planless" / OBJECT
    shutil.copytree(reference[0] / OBJECT, planless)
    meta = json.loads((planless / "manifest.json").read_text())
    meta["plan"] = {}
    (planless / "manifest.json").write_text(json.dumps(meta))
    assert Session.open(planless).validate() == [
        "the manifest has no capture plan (plan.projector): the patterns its frames were captured under are unknown, "
        "so it cannot be relit"]
    # a manifest without its rig record passed validate, and relight assumed an unclipped camera and 32-pixel crops
    rigless = tmp_path / "rigless" / OBJECT
    shutil.copytree(reference[0] / OBJECT, rigless)
    meta = json.loads((rigless / "manifest.json").read_text())
    del meta["rig"]
    (rigless / "manifest.json").write_text(json.dumps(meta))
    assert Session.open(rigless).validate() == [
        "the manifest has no rig record (rig): the camera, its saturation level and the footprint crop size it was "
        "captured with are unknown (relighting would assume an unclipped camera and 32-pixel crops)"]
    done = sss("relight", str(rigless), "--pattern", "checkerboard", "--out", str(tmp_path / "relit"), "--backend", "none")
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("its manifest has no rig record") == 1, done.stderr


def test_a_view_folder_renamed_away_is_named_once_not_as_every_array_missing(reference, tmp_path, sss):
    """`sss validate` listed eleven "array X is missing or unreadable (no zarr.json)" lines and relight one of them,
    never that the view's folder was gone."""
    shutil.copytree(reference[0] / OBJECT, tmp_path / OBJECT)
    (tmp_path / OBJECT / "view_000").rename(tmp_path / OBJECT / "view_007")
    problems = Session.open(tmp_path / OBJECT).validate()
    assert [p for p in problems if p.startswith("view 0:")] == [
        f"view 0: its folder view_000 is missing (renamed or deleted?): the manifest lists "
        f"{len(Session.open(tmp_path / OBJECT).arrays(0))} arrays there"], problems
    # and the folder it became, which no command reads, was not named at all
    assert "view_007: a view folder the manifest does not list (copied in from another session, or renamed?): no " \
        "command reads it" in problems, problems
    done = sss("relight", str(tmp_path / OBJECT), "--pattern", "checkerboard", "--views", "0", "--backend", "none",
               "--out", str(tmp_path / "relit"))
    assert done.returncode != 0 and "is missing its folder view_000 (renamed or deleted?)" in " ".join(done.stderr.split())


def test_an_array_rewritten_with_valid_chunks_is_refused_by_every_reader_not_only_validate(reference, tmp_path, sss):
    """Data changed through zarr (its chunks' CRCs valid, the manifest's checksum not) was caught by `sss validate`
    only: relight and evaluation scored it, and `sss export` wrote it out, where an import laundered it into a
    session that validated. Every whole read is held to the manifest's checksum."""
    import zarr

    shutil.copytree(reference[0] / OBJECT, tmp_path / OBJECT)
    white = zarr.open_array(str(tmp_path / OBJECT / "view_000" / "white"), mode="r+")
    data = white[:]
    data[:, : data.shape[1] // 2] *= 0.5
    white[:] = data
    said = "array white of view 0 of {} is corrupt (its data do not match the manifest's checksum: changed since they were written)"
    assert "view 0: array white is corrupt (its data do not match the manifest's checksum" in "\n".join(
        Session.open(tmp_path / OBJECT).validate())
    for args in (("relight", str(tmp_path / OBJECT), "--pattern", "checkerboard", "--backend", "analytic",
                  "--out", str(tmp_path / "relit")),
                 ("export", str(tmp_path / OBJECT), "--out", str(tmp_path / "exported"))):
        done = sss(*args)
        assert done.returncode != 0 and "Traceback" not in done.stderr, done.stderr
        assert said.format(tmp_path / OBJECT) in " ".join(done.stderr.split()), done.stderr
    assert not list((tmp_path / "exported").rglob("white*"))  # nothing of it written out
    array = Session.open(tmp_path / OBJECT).read(0, "white")  # parts of it are read as they are (their chunks' CRCs)
    assert array[0].shape == data.shape[1:] and array[(slice(0, 3), ...)].shape[0] == 3
    assert array.oindex[np.array([0, 2])].shape == (2, *data.shape[1:])
    from sssphase_core.store.session import _whole

    assert not _whole(np.array([0, 2])) and not _whole((np.ones(3, bool), slice(None)))  # (was "ambiguous truth value")
    for whole in (..., slice(None), (slice(None), ...), ()):
        with pytest.raises(DataError, match="do not match the manifest's checksum"):
            array[whole]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:--dot-spacing")  # sparse dots for speed: their crops cut short
def test_footprints_stream_into_crops_and_raw_dots_on_request(daemon, tmp_path):
    _, client = daemon
    req = CaptureRequest("pear", views=1, footprints=True, dot_spacing=8, keep_dots=True, out=tmp_path)
    s = run_capture(client, req)
    assert s.validate() == []
    pixels, crops = s.load(0, "footprints/pixels"), s.load(0, "footprints/crops")
    mask = s.load(0, "corr/mask")
    assert crops.shape == (len(pixels), 32, 32, 3) and len(pixels) == mask.sum()
    assert s.read(0, "dots").shape == (64, 192, 256, 3)
    assert s.manifest["views"]["0"]["footprints"] == {"count": len(pixels), "missing": 0, "spacing": 8,
                                                           "dot_stride": 1}
    centre, between_dots = crops[:, 16, 16].mean(), crops[:, 20, 20].mean()
    assert centre > 1.5 * between_dots, (centre, between_dots)  # each crop is centred on its lit pixel


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:--dot-spacing")  # sparse dots for speed: their crops cut short
def test_raw_dots_are_kept_once_per_dot_grid_with_exposure_brackets(daemon, tmp_path):
    _, client = daemon  # each dot grid is captured at 2 exposures and merged: one kept frame per grid
    s = run_capture(client, CaptureRequest("pear", views=1, footprints=True, dot_spacing=4, keep_dots=True,
                                           hdr=(0.5, 2.0), out=tmp_path))
    assert s.validate() == [] and s.read(0, "dots").shape == (16, 192, 256, 3)


def test_import_from_a_folder_of_images(tmp_path):
    import cv2

    from sssphase_core.processing.patterns import capture_plan
    from sssphase_core.sim import SimScene

    scene = SimScene("orange")
    plan = capture_plan(256, 192, references=("white", "black"))
    frames = scene.capture(np.stack([f.pattern() for f in plan]), np.random.default_rng(1))
    folder = tmp_path / "rig_images" / "view_000"
    folder.mkdir(parents=True)
    for f, img in zip(plan, frames, strict=True):
        if f.key == "white":
            cv2.imwrite(str(folder / "white.png"), cv2.cvtColor(np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), cv2.COLOR_RGB2BGR))
        else:
            np.save(folder / f"{f.key.replace('/', '__')}.npy", img)
    s = import_folder(tmp_path / "rig_images", tmp_path / "sessions", "orange_rig2", (256, 192))
    assert s.validate() == [] and s.views() == [0]
    xp, mask = s.load(0, "corr/xp"), s.load(0, "corr/mask")
    assert mask.sum() > 1000 and np.nanmedian(np.abs(xp[mask] - scene.proj_xy[..., 0][mask])) < 0.5
    assert s.load(0, "white").max() <= 1.0
    with pytest.raises(Exception, match="white"):
        import_folder(tmp_path / "sessions", tmp_path / "x", "empty", (256, 192))


@pytest.mark.slow
def test_hdr_brackets_on_a_rig_without_turntable(daemon, tmp_path):
    _, client = daemon
    (tmp_path / "rig.toml").write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n')
    rig = RigSpec.from_toml(tmp_path / "rig.toml")
    asked: list[tuple[int, float]] = []
    brackets = (*DEFAULT_HDR, 16.0)  # any brackets (`--hdr-exposures 0.25,1,4,16`)
    req = CaptureRequest("soap", views=1, hdr=brackets, out=tmp_path)
    s = run_capture(client, req, rig, ask_move=lambda v, a: asked.append((v, a)))
    assert asked == [(0, 0.0)] and s.validate() == []
    assert len(s.manifest["plan"]["frames"]) == 4 * (24 + 2)
    white, render, mask = s.load(0, "white"), s.load(0, "gt/render/white"), s.load(0, "corr/mask")
    assert mask.sum() > 1000
    assert np.abs(white - render)[mask].mean() < 0.05 * render[mask].mean()
    assert s.manifest["views"]["0"]["hot_pixels"] == s.manifest["views"]["0"]["outliers_repaired"] == 0
    (tmp_path / "bad.toml").write_text('[devices]\ncamera = "sim:camera0"\n')
    with pytest.raises(InputError, match="projector"):
        RigSpec.from_toml(tmp_path / "bad.toml")


def test_each_view_records_the_camera_pipeline_its_frames_went_through(daemon, tmp_path):
    """Colour frames from the sim camera: its own demosaicing (no median at the CPU preset); raw Bayer
    frames developed by this ISP: Malvar and the rig's median. Relighting reads it back to compare relit
    images with captures as the camera records them."""
    from sssphase_core.relight import load_view
    from sssphase_core.sim import rig_preset

    _, client = daemon
    colour = run_capture(client, CaptureRequest("star", views=1, out=tmp_path / "colour"))
    assert colour.manifest["views"]["0"]["camera_isp"] == {"demosaic": "malvar", "median": False, "bayer": "RGGB"}
    assert colour.manifest["views"]["0"]["hot_pixels"] == colour.manifest["views"]["0"]["outliers_repaired"] == 0
    # knowing the Bayer pipeline, the decoder drops background pixels beside the silhouette whose fringes
    # only demosaicing gave them (they decoded as surface, and relighting lit them with the object's light)
    reason, render = colour.load(0, "corr/reason"), colour.load(0, "gt/render/white").max(axis=-1)
    bleed = reason == Reason.DEMOSAIC_BLEED
    assert colour.manifest["views"]["0"]["coverage"]["DEMOSAIC_BLEED"] == bleed.sum() > 50
    assert (render[bleed] < 0.02).mean() > 0.9 and (render[reason == Reason.VALID] < 0.02).sum() < 10
    sensor = rig_preset("cpu").sensor
    (tmp_path / "rig.toml").write_text(
        '[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\nturntable = "sim:turntable0"\n'
        f'[options]\nraw = true\n[processing]\nblack_level = {sensor.black_level}\n'
        f'white_scale = {sensor.dn_per_unit(1.0)}\nmedian = true\n')
    raw = run_capture(client, CaptureRequest("star", views=1, out=tmp_path / "raw"), RigSpec.from_toml(tmp_path / "rig.toml"))
    assert raw.manifest["views"]["0"]["camera_isp"] == {"demosaic": "malvar", "median": True, "bayer": "RGGB"}
    assert load_view(raw, 0).camera_isp == {"demosaic": "malvar", "median": True, "bayer": "RGGB"}
    assert raw.manifest["views"]["0"]["hot_pixels"] == raw.manifest["views"]["0"]["outliers_repaired"] == 0
    (tmp_path / "bad.toml").write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n'
                                       '[processing]\nbayer = "RGBG"\n')
    with pytest.raises(InputError, match=r"\[processing\] bayer must be one of RGGB, GRBG, GBRG, BGGR, got 'RGBG'"):
        RigSpec.from_toml(tmp_path / "bad.toml")


@pytest.fixture(scope="module")
def soap_with_footprints(daemon, tmp_path_factory):
    """One soap view with dot-grid footprints at the default spacing, through a real daemon."""
    _, client = daemon
    req = CaptureRequest("soap", views=1, footprints=True, references=("checkerboard",), out=tmp_path_factory.mktemp("fp"))
    return run_capture(client, req)


@pytest.mark.slow
def test_captured_footprints_carry_one_camera_pixels_energy(soap_with_footprints):
    """Dot crops are normalised per camera pixel (|det J|) and cut to their own dot: their energy matches
    the simulator's exact footprints of the same pixels (it was 1.33x before the normalisation)."""
    from sssphase_core.sim import SimScene

    s = soap_with_footprints
    pixels, crops = s.load(0, "footprints/pixels").astype(np.int64), s.load(0, "footprints/crops")
    pick = np.random.default_rng(0).choice(len(pixels), 400, replace=False)
    exact = SimScene("soap", view=0, n_views=1).footprints(pixels[pick])
    e_exact = exact.sum(axis=(1, 2)).mean(axis=1)
    ok = e_exact > 0.05
    ratio = crops[pick].sum(axis=(1, 2)).mean(axis=1)[ok] / e_exact[ok]
    assert 0.9 < np.median(ratio) < 1.1, np.median(ratio)


@pytest.mark.slow
def test_measured_backend_splats_the_captured_crops_and_exact_the_simulators(soap_with_footprints):
    from sssphase_core.relight import DotTransport, load_view, make_source, relight

    s = soap_with_footprints
    rv = load_view(s, 0)
    measured, k = make_source("measured", rv)
    assert isinstance(measured, DotTransport) and k == 32  # the captured per-dot transport, not a model
    raw = np.asarray(s.load(0, "transport/crops"), np.float32)[:50]
    got = measured.crops_at(np.arange(50))
    kept = got != 0
    np.testing.assert_array_equal(got[kept], raw[kept])  # read as captured, only the noise floor dropped
    assert kept.mean() > 0.03 and (raw[~kept] ** 2).mean() < (raw[kept] ** 2).mean() / 100
    exact, k2 = make_source("exact", rv)
    assert k2 == 32 and not np.allclose(exact(measured.pixels[:50]), raw, atol=1e-4)  # ground truth differs
    white = relight(measured, rv.proj, [np.ones((192, 256), np.float32)], k, white=rv.white)[0]
    lit = rv.proj.mask & (rv.white.mean(-1) > 0.05)
    ratio = white.mean(-1)[lit] / rv.white.mean(-1)[lit]
    assert 0.9 < np.median(ratio) < 1.05  # each dot's light counted once: the white image comes back


@pytest.mark.slow
def test_a_colour_reference_file_is_captured_and_evaluated_with_the_named_ones(daemon, tmp_path):
    from PIL import Image

    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import evaluate_view

    yy, xx = np.mgrid[:192, :256]
    logo = np.stack([(xx % 64 < 32) * 255, (yy % 48 < 24) * 255, np.full_like(xx, 128)], -1).astype(np.uint8)
    Image.fromarray(logo).save(tmp_path / "logo.png")
    _, client = daemon
    req = CaptureRequest("leaf", views=1, references=(str(tmp_path / "logo.png"), "checkerboard"), out=tmp_path / "s")
    s = run_capture(client, req)
    assert {"ref/logo", "ref/checkerboard", "pattern/logo"} <= set(s.arrays(0))
    rv = load_view(s, 0)
    assert set(rv.references) == {"logo", "checkerboard"} and rv.references["logo"].shape == (192, 256, 3)
    rows = evaluate_view(rv, "none", tmp_path / "ev", write=False)
    assert {r["pattern"] for r in rows} == {"logo", "checkerboard"} and all(r["psnr"] > 15 for r in rows)


@pytest.mark.parametrize("extra, message", [
    ("[projector]\ngamma = true\n", r"\[projector\] gamma must be a number"),  # true was read as gamma 1.0
    ("[projector]\nblack = false\n", r"\[projector\] black must be a number"),
    ("[options]\nwidth = 0\nheight = 0\n", r"unknown sim rig \[options\] height, width \(known: anisotropy, backdrop, demosaic"),
    ("[options]\nread_nosie = 4\n", r"unknown sim rig \[options\] read_nosie"),  # a typo ran with the default
])
def test_rig_file_values_the_capture_would_have_ignored_or_misread_are_refused(tmp_path, extra, message):
    (tmp_path / "rig.toml").write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n' + extra)
    with pytest.raises(InputError, match=message):
        RigSpec.from_toml(tmp_path / "rig.toml")


def test_every_documented_sim_rig_option_is_known_and_options_of_other_plugins_pass(tmp_path):
    from sssphase_core.sim.rig import SENSOR_OPTIONS, SIM_RIG_OPTIONS
    from sssphase_plugins import sim_plugin

    assert set(SENSOR_OPTIONS) <= SIM_RIG_OPTIONS
    assert all(f"``{k}``" in sim_plugin.__doc__ for k in SIM_RIG_OPTIONS - {"view"}), sim_plugin.__doc__
    (tmp_path / "rig.toml").write_text('[devices]\ncamera = "uvc:cam0"\nprojector = "sim:projector0"\n'
                                       '[options]\nserial = "/dev/ttyACM0"\nread_noise = 3\n')
    assert RigSpec.from_toml(tmp_path / "rig.toml").options["serial"] == "/dev/ttyACM0"  # not a sim-only rig


@pytest.mark.slow
def test_a_view_where_nothing_decodes_is_kept_with_a_warning(runtime_dir, sss, tmp_path):
    """A rig whose camera sees no fringes (here the sim's benchmark camera, which never looks at the projector)
    gave a session that said "1/1 views complete" and validated, without a word."""
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "sim:bench-camera"\nprojector = "sim:projector0"\nturntable = "sim:turntable0"\n'
                   '[options]\nshape = [192, 256, 3]\n')  # the sim camera's frame size, not the bench camera's 1080p
    res = sss("capture", "--object", "apple", "--views", "1", "--rig", str(rig), "--out", str(tmp_path / "s"))
    assert res.returncode == 0, res.stderr
    assert "view 0: no camera pixel decoded (low modulation" in res.stderr and "Traceback" not in res.stderr


def test_the_rig_is_kept_open_while_the_user_turns_the_object_by_hand(monkeypatch):
    """On a rig without a turntable the daemon closed the rig 5 minutes into the "turn the object" prompt (no
    request came), and the next view failed with "no open rig"."""
    import time

    from sssphase_core.capture import engine

    calls: list[str] = []

    class Client:
        def call(self, op, timeout_s=None, **args):
            calls.append(op)
            return {}

    monkeypatch.setattr(engine, "KEEPALIVE_S", 0.02)
    with engine._keeping_rig_open(Client()):
        time.sleep(0.3)  # the user at the prompt
    n = len(calls)
    time.sleep(0.1)
    assert n >= 5 and set(calls) == {"ping"} and len(calls) == n  # pinged while waiting, and only then


NEGATIVE_CAMERA = '''
import time
import numpy as np
from sssphase_plugins.api import DeviceInfo, Frame, hookimpl


class Camera:
    info = DeviceInfo("negcam:0", "camera", "negcam", "a camera whose driver reads signed data as light", "0")

    def configure(self, *, exposure=None, gain=None, pixel_format=None):
        pass

    def grab(self, timeout_s=5.0):
        return Frame(np.full((48, 64, 3), -1.0, np.float32), 0, time.monotonic_ns(), 1.0, {})

    def stream(self, count):
        return (self.grab() for _ in range(count))

    def close(self):
        pass


class Provider:
    kind = "camera"

    def discover(self):
        return [Camera.info]

    def open(self, device_id, options, shared):
        return Camera()


@hookimpl
def sssphase_cameras():
    return [Provider()]
'''


def test_a_camera_whose_frames_are_no_light_fails_the_capture_naming_it_and_writes_no_view(tmp_path):
    """A driver's frames of -1 everywhere (signed data read as light) captured "1/1 views complete", exit 0; `sss
    validate` then found the session's images far below zero. The capture now refuses them, naming the camera."""
    (tmp_path / "negcam.py").write_text(NEGATIVE_CAMERA)
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "negcam:0"\nprojector = "sim:projector0"\n')
    runtime = Path(tempfile.mkdtemp(prefix="sssn", dir="/tmp"))
    env = {**os.environ, "SSS_PLUGINS": "negcam", "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
           "SSS_RUNTIME_DIR": str(runtime)}
    try:
        res = run_sss(["capture", "--object", "apple", "--views", "1", "--rig", str(rig), "--out", str(tmp_path / "s")],
                      env=env, timeout=300)  # (no turntable, one view: nothing to turn, nothing asked)
    finally:
        run_sss(["daemon", "stop", "--force"], env=env)
        shutil.rmtree(runtime, ignore_errors=True)
    said = res.stdout + res.stderr
    assert res.returncode != 0 and "Traceback" not in said, said
    assert "the camera negcam:0: frame " in said and "below -0.25 x the white level" in said, said
    assert Session.open(tmp_path / "s" / "apple").views() == []


@pytest.mark.slow
def test_a_capture_past_the_file_size_limit_says_so_and_resumes(tmp_path):
    """Under `ulimit -f` a capture ended in "internal error: OSError: [Errno 27] File too large", naming nothing."""
    import resource

    runtime = Path(tempfile.mkdtemp(prefix="sssf", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "300"}
    args = [sys.executable, "-m", "sssphase_cli.main", "capture", "--object", "soap", "--views", "1", "--out",
            str(tmp_path / "s")]
    try:
        limited = subprocess.run(args, capture_output=True, text=True, env=env, timeout=300,
                                 preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000)))
        assert limited.returncode == 2 and "Traceback" not in limited.stderr, limited.stderr
        assert re.search(r"error: a file of \w+ of view 0 in .*/s/soap outgrew the largest file this process may write "
                         r"\(ulimit -f\): raise the limit and rerun with --resume", limited.stderr), limited.stderr
        resumed = run_sss(["capture", "--object", "soap", "--views", "1", "--resume", "--out", str(tmp_path / "s")],
                          env=env, timeout=300)
        assert resumed.returncode == 0 and Session.open(tmp_path / "s" / "soap").validate(expected_views=1) == []
    finally:
        run_sss(["daemon", "stop"], env=env)
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_rig_without_a_turntable_asks_for_each_view_and_says_what_to_do_when_it_cannot_ask(tmp_path):
    """Without a terminal to answer "turn the object to view 0", the capture printed "aborted" and nothing else."""
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n')
    runtime = Path(tempfile.mkdtemp(prefix="sssq", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "300"}
    try:
        res = run_sss(["capture", "--object", "apple", "--views", "2", "--rig", str(rig), "--out", str(tmp_path / "s")],
                      env=env, timeout=300)
    finally:
        run_sss(["daemon", "stop", "--force"], env=env)
        shutil.rmtree(runtime, ignore_errors=True)
    said = res.stdout + res.stderr
    assert res.returncode != 0 and "Traceback" not in said and "aborted" not in said, said
    assert ("the rig has no turntable, so each view waits for you to turn the object, and the input is not a "
            "terminal: run it in a terminal") in said, said


def test_an_hdr_capture_whose_rig_file_says_too_high_a_saturation_is_refused_naming_the_level(tmp_path):
    """`[processing] saturation = 4095` (a sensor's top code) where the frames clip at 1.667: the merge trusted clipped
    samples and the relit PSNR fell from 38 to 25 dB, without a word."""
    rig = tmp_path / "rig.toml"
    rig.write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n[processing]\nsaturation = 4095\n')
    runtime = Path(tempfile.mkdtemp(prefix="ssss", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "300"}
    try:
        res = run_sss(["capture", "--object", "soap", "--views", "1", "--hdr", "--rig", str(rig), "--out",
                       str(tmp_path / "s")], env=env, timeout=300)
    finally:
        run_sss(["daemon", "stop", "--force"], env=env)
        shutil.rmtree(runtime, ignore_errors=True)
    said = res.stdout + res.stderr
    assert res.returncode != 0 and "Traceback" not in said, said
    assert re.search(r"the camera's frames clip at 1\.667 \(linear, at exposure 1\) but the rig file's \[processing\] "
                     r"saturation is 4095: .* set saturation = 1\.63", said), said
