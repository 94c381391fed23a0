"""The session runner that `sss relight`, `sss geometry` and `sss eval relight` call (and a notebook or web
view can call the same way): results returned, narration through a narrator, outputs written."""

import cv2
import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.relight.cache import cache_path
from sssphase_core.relight.runner import (
    EVAL_BACKENDS,
    Narrator,
    choose_views,
    evaluate_sessions,
    geometry_session,
    parse_formats,
    relight_session,
    resize_note,
    same_pattern,
)
from sssphase_core.store.session import Session


class Recorder(Narrator):
    """Keeps what a run says and the progress it reports."""

    def __init__(self):
        self.lines, self.tasks, self.progress = [], [], []

    def say(self, text, warning=""):
        self.lines.append((text, warning))

    def task(self, label):
        self.tasks.append(label)
        return lambda done, total: self.progress.append((label, done, total))

    def text(self):
        return "\n".join(t for t, _ in self.lines)


@pytest.fixture(scope="module")
def session(tmp_path_factory, sim_daemon):
    """One view of the sand rake (the smallest unseen object) with a checkerboard reference, captured through the daemon."""
    from sssphase_core.capture import CaptureRequest, run_capture

    req = CaptureRequest("sand_rake", views=1, references=("checkerboard",), out=tmp_path_factory.mktemp("s"))
    return run_capture(sim_daemon, req).path


def test_relight_session_returns_what_it_wrote_and_scores_a_reference(session, tmp_path):
    said = Recorder()
    res = relight_session(session, ["checkerboard", "white"], backend="none", out=tmp_path, narrator=said)
    assert res.backend == "none" and res.checkpoint is None and res.patterns == ["checkerboard", "white"]
    assert res.mixes == {0: None}  # model-free: never calibrated
    by_name = {im.pattern: im for im in res.images}
    assert set(by_name) == {"checkerboard", "white"}
    for im in res.images:
        assert im.view == 0 and im.object == "sand_rake"
        assert [p.name for p in im.paths] == [f"sand_rake_v0_{im.pattern}_none.png", f"sand_rake_v0_{im.pattern}_none_display.png"]
        assert all(p.exists() for p in im.paths) and 0.0 <= im.clipped <= 1.0
    board = by_name["checkerboard"]
    assert board.metrics is not None and board.metrics["psnr"] > 15 and board.figure.exists()
    assert by_name["white"].metrics is None  # no reference capture of the white pattern
    assert said.tasks == ["sand_rake view 0: none"] and said.progress[-1][1] == said.progress[-1][2]
    lines = [t for t, _ in said.lines]
    assert lines[0].startswith("wrote ") and f"PSNR {board.metrics['psnr']:.2f} dB" in lines[0]
    assert len(list((tmp_path / "cache").glob("sand_rake_v0_*_none_*.npz"))) == 1  # the footprints, for later patterns


def test_auto_is_the_analytic_model_calibrated_to_the_view_and_cached(session, tmp_path):
    said = Recorder()
    res = relight_session(Session.open(session), ["checkerboard"], out=tmp_path, views=[0], narrator=said,
                          formats="exr,png")
    assert res.backend == "analytic"
    assert said.lines[0] == ("backend: analytic (no --checkpoint: the analytic model; with a trained decoder's --checkpoint, the decoder blends in)", "")
    mix = res.mixes[0]
    assert mix.shape == (3,) and ((0 <= mix) & (mix <= 1)).all()
    assert "analytic footprints calibrated to the view's fringe captures" in said.text()
    assert sorted(p.suffix for p in res.images[0].paths) == [".exr", ".png", ".png"]  # linear EXR and PNG, display PNG
    s = Session.open(session)
    from sssphase_core.relight import load_view

    cached = cache_path(tmp_path, s, load_view(s, 0), "analytic", None)
    assert cached.exists() and cached.parent == tmp_path / "cache"


def test_relight_session_checks_its_input_before_any_work(session, tmp_path):
    with pytest.raises(InputError, match="two patterns would both be written as 'checkerboard'"):
        relight_session(session, ["checkerboard", "checkerboard"], backend="none", out=tmp_path / "a")
    with pytest.raises(InputError, match="--resize must be one of"):
        relight_session(session, ["checkerboard"], backend="none", resize="bogus", out=tmp_path / "b")
    with pytest.raises(InputError, match="the torch backend needs --checkpoint"):
        relight_session(session, ["checkerboard"], backend="torch", out=tmp_path / "c")
    with pytest.raises(InputError, match="has no complete view 3"):
        relight_session(session, ["checkerboard"], backend="none", views="0,3", out=tmp_path / "d")
    odd = tmp_path / "we ird\nname.png"  # a newline in a pattern's file name would be in its outputs' names
    cv2.imwrite(str(odd), np.zeros((8, 8), np.uint8))
    with pytest.raises(InputError, match=r"its file name holds a control character .*: rename the file"):
        relight_session(session, [str(odd)], backend="none", out=tmp_path / "e")
    assert not any((tmp_path / n).exists() and any((tmp_path / n).glob("*.png")) for n in "abcde")


def test_options_a_backend_does_not_use_are_noted_not_silently_dropped(session, tmp_path):
    """--checkpoint and --widen with backends that are data, not a model (never calibrated): one note each, and the
    images are those of the run without them."""
    run = _tiny_decoder(tmp_path / "run")
    said = Recorder()
    res = relight_session(session, ["checkerboard"], backend="none", widen=2.0, checkpoint=run, out=tmp_path / "a",
                          narrator=said)
    notes = [t for t, _ in said.lines if t.startswith("note:")]
    assert notes == ["note: --checkpoint is not used by --backend none",
                     "note: --widen is not used by --backend none (its footprints are data, not a model: the view "
                     "calibration that stretches them does not run)"]
    plain = relight_session(session, ["checkerboard"], backend="none", out=tmp_path / "b")
    assert res.images[0].metrics == plain.images[0].metrics
    said = Recorder()
    evaluate_sessions([session], backend="none", widen=2.0, out=tmp_path / "c", narrator=said)
    assert "note: --widen is not used by --backend none" in said.text()
    said = Recorder()  # one backend of several that uses it: the widening line names it, no note
    evaluate_sessions([session], backend="none,analytic", widen=2.0, out=tmp_path / "d", narrator=said)
    assert "is not used" not in said.text() and "calibration (analytic): the analytic footprints join" in said.text()


def test_geometry_session_writes_and_scores_the_corrected_points(session, tmp_path):
    said = Recorder()
    (geo,) = geometry_session(session, backend="exact", out=tmp_path, narrator=said)
    assert geo.path == tmp_path / "sand_rake" / "view_000" / "correspondence_for_geometry.npz" and geo.path.exists()
    data = np.load(geo.path)
    assert set(data.files) == {"xp", "yp", "xp_decoded", "yp_decoded", "shift_x", "shift_y", "mask", "points",
                               "points_decoded"}
    assert np.isfinite(geo.shift).all() and geo.period > 0
    assert geo.exact is not None and geo.exact[2] <= geo.exact[0] + 1e-3  # the exact footprints never make it worse
    lines = [t for t, _ in said.lines]
    assert lines[0] == "triangulating with the simulated rig's exact calibration"
    assert lines[-2].startswith(f"wrote {geo.path}: median shift") and "against the exact points" in lines[-2]
    # the 3D points: the corrected correspondences triangulated with the rig's own calibration, in mm
    points = data["points"]
    assert points.shape == (*data["mask"].shape, 3) and np.isnan(points[~data["mask"]]).all()
    assert 300 < np.nanmedian(points[..., 2]) < 500  # the turntable is 400 mm from the camera
    assert geo.reprojection < 0.1 and geo.exact_3d is not None and geo.exact_3d[0] < 0.5  # mm, at 400 mm
    assert abs(geo.exact_3d[3]) <= abs(geo.exact_3d[1]) + 5e-3  # the exact footprints take the depth bias out, not in
    assert lines[-1].startswith(f"wrote {geo.cloud}: {geo.n_points} points") and "against the exact surface" in lines[-1]
    import trimesh

    cloud = trimesh.load(geo.cloud)  # a PLY any point-cloud tool reads: the finite points, each with a colour
    finite = np.isfinite(points).all(-1)
    assert len(cloud.vertices) == geo.n_points == finite.sum()
    np.testing.assert_allclose(np.asarray(cloud.vertices), points[finite], atol=1e-4)
    assert np.asarray(cloud.colors)[:, :3].std() > 0  # coloured by the white capture, not one grey
    assert geo.figure == geo.path.parent / "shift.png" and cv2.imread(str(geo.figure)).shape[1] > 800  # three panels
    with pytest.raises(InputError, match="without scattering there is no shift"):
        geometry_session(session, backend="none", out=tmp_path / "g")


def test_evaluate_sessions_tabulates_and_writes_its_record(session, tmp_path):
    said = Recorder()
    res = evaluate_sessions([session], backend="none", out=tmp_path, narrator=said)
    assert res.backends == ["none"] and res.json.exists() and res.md.exists()
    assert [(r["object"], r["view"], r["pattern"], r["backend"]) for r in res.rows] == [("sand_rake", 0, "checkerboard", "none")]
    assert np.isfinite(res.rows[0]["psnr"]) and said.tasks == ["sand_rake view 0: none"]
    assert said.lines[-1] == (f"wrote {res.json} and {res.md}", "")
    assert res.tables[0].markdown() in said.text()
    with pytest.raises(InputError, match="--backend measured: sand_rake view 0 has no captured footprints"):
        evaluate_sessions([session], backend="none,measured", out=tmp_path / "m")


class FakeSession:
    path = "S"
    manifest = {"views": {"0": {}, "1": {}, "2": {}}}

    def views(self):
        return [0, 2]

    def status(self, v):
        return "complete" if v != 1 else "capturing"

    imported, completes_it = Session.imported, Session.completes_it  # a capture's: its manifest names no import


def test_choose_views_takes_text_or_numbers_each_once():
    s = FakeSession()
    assert choose_views(s, "") == [0, 2] and choose_views(s, None) == [0, 2]
    assert choose_views(s, "2, 0,2") == [2, 0] and choose_views(s, [2, 2]) == [2]
    with pytest.raises(InputError, match="names no view"):
        choose_views(s, " , ")
    with pytest.raises(InputError, match="must be comma-separated integers"):
        choose_views(s, "a")
    with pytest.raises(InputError, match=r"has no complete view 1 \(complete: 0, 2\)"):
        choose_views(s, "1")
    s.views = lambda: []
    with pytest.raises(InputError, match="view 1: capturing"):
        choose_views(s)


def test_all_views_says_which_incomplete_ones_it_leaves_out():
    class Lines:
        def __init__(self):
            self.lines = []

        def say(self, text, warning=""):
            self.lines.append(text)

    s, said = FakeSession(), Lines()
    s.name = "apple"
    assert choose_views(s, "", said) == [0, 2]
    assert said.lines == ["apple: left out, not complete (view 1: capturing); `sss capture ... --resume` completes it"]
    said.lines.clear()
    assert choose_views(s, "0,2", said) == [0, 2] and said.lines == []  # views named: nothing left out unasked
    s.status = lambda v: "complete"
    assert choose_views(s, "", said) == [0, 2] and said.lines == []


def test_small_helpers(tmp_path):
    from PIL import Image

    from sssphase_cli import cmd_relight

    assert EVAL_BACKENDS == cmd_relight.EVAL_BACKENDS  # the CLI's default is the runner's
    assert parse_formats("PNG, png") == ("png",) and parse_formats(["exr", "png"]) == ("exr", "png")
    with pytest.raises(InputError, match="choose png, exr"):
        parse_formats("tiff")
    board = np.indices((4, 6)).sum(axis=0) % 2
    assert same_pattern(board, np.repeat(board[..., None], 3, axis=-1))  # mono and RGB of one pattern
    assert not same_pattern(board, 1 - board) and not same_pattern(board, board[:, :4])
    Image.fromarray(np.zeros((10, 20), np.uint8)).save(tmp_path / "p.png")
    assert resize_note(str(tmp_path / "p.png"), (20, 10), "stretch") is None
    line, warning = resize_note(str(tmp_path / "p.png"), (40, 40), "stretch")
    assert line == f"{tmp_path / 'p.png'}: 20x10 -> 40x40 (stretch); aspect ratio changed by 100% (fit or fill keep it)"
    assert warning == "aspect ratio changed by 100%"
    assert resize_note(str(tmp_path / "p.png"), (40, 20), "fit") == (f"{tmp_path / 'p.png'}: 20x10 -> 40x20 (fit)", "")
    quiet = Narrator()  # the default narrator says nothing and frames nothing
    quiet.say("x")
    with quiet.bar(), quiet.status("y"):
        quiet.task("z")(1, 2)


def test_a_decoder_of_another_footprint_size_is_refused_before_any_work(session, tmp_path):
    """A paper-preset decoder (K = 90) on a CPU-preset session (K = 32) relit for minutes, grew to 5.4 GB and
    ended in an allocation error: the decoder's K must be the session's, as training requires."""
    import dataclasses

    import torch

    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint

    small = dataclasses.replace(get_preset("lite"), name="lite48", patch=48, stem=8, stages=(8, 12, 16), bottleneck=32,
                                proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4)
    torch.manual_seed(0)
    ckpt = tmp_path / "dec.pt"
    save_checkpoint(ckpt, {"kind": "decoder", "preset": small.to_dict(), "config": {"head": "reciprocal"},
                           "encoder": Encoder(small).state_dict(), "decoder": Decoder(small, head="reciprocal").state_dict()})
    why = r"dec\.pt is a lite48 decoder \(48x48 footprints\) but sand_rake was captured with 32x32 crops"
    with pytest.raises(InputError, match=why):
        relight_session(session, ["checkerboard"], backend="blend", checkpoint=ckpt, out=tmp_path / "relit")
    with pytest.raises(InputError, match=why):
        evaluate_sessions([session], backend="none,torch", checkpoint=ckpt, out=tmp_path / "eval")
    with pytest.raises(InputError, match=why):
        geometry_session(session, backend="torch", checkpoint=ckpt, out=tmp_path / "geo")
    assert not (tmp_path / "relit").exists() or not any((tmp_path / "relit").glob("*.png"))


@pytest.mark.parametrize("box", [(slice(40, 90), slice(70, 150)), (slice(0, 30), slice(150, 200))])
def test_ssim_of_the_mask_is_the_whole_images_ssim_at_its_pixels(box):
    """relight_metrics computes SSIM only around the mask (a fraction of a 1080p image): the value is the one of
    the whole image's SSIM map averaged over the mask, inside the image and where the mask meets its border."""
    import kornia
    import torch

    from sssphase_core.relight.evaluation import SSIM_WINDOW, relight_metrics

    rng = np.random.default_rng(3)
    mask = np.zeros((120, 200), bool)
    mask[box] = rng.random(mask[box].shape) > 0.3
    a = rng.random((120, 200, 3))
    b = a + 0.1 * rng.standard_normal(a.shape)
    ta, tb = (torch.as_tensor(x, dtype=torch.float32).permute(2, 0, 1)[None] for x in (a, b))
    whole = kornia.metrics.ssim(ta, tb, window_size=SSIM_WINDOW, max_val=1.0)[0].mean(0).numpy()
    assert relight_metrics(a, b, mask)["ssim"] == pytest.approx(float(whole[mask].mean()), abs=1e-6)


def test_later_patterns_are_relit_from_the_views_cached_eigen_footprints(session, tmp_path):
    """A model's relight keeps the view's eigen-footprints and calibration; the next `sss relight` of the same
    view relights any pattern from them alone, close to the full relight, and says so; --no-cache does not."""
    first = relight_session(session, ["checkerboard"], backend="analytic", out=tmp_path, formats="exr")
    assert len(list((tmp_path / "cache").glob("sand_rake_v0_*_analytic_*_lowrank.npz"))) == 1
    said = Recorder()
    fast = relight_session(session, ["checkerboard", "stripes_x"], backend="analytic", out=tmp_path, formats="exr",
                           narrator=said)
    assert "relit from its cached eigen-footprints" in said.text() and said.tasks == []  # no footprint pass
    full = relight_session(session, ["checkerboard", "stripes_x"], backend="analytic", out=tmp_path / "full",
                           formats="exr", cache=False)
    np.testing.assert_allclose(fast.mixes[0], first.mixes[0])  # the calibration that was fitted, not a new one
    from sssphase_core.store.exr import read_exr

    for a, b in zip(fast.images, full.images, strict=True):
        x, y = read_exr(a.paths[0]), read_exr(b.paths[0])
        assert 10 * np.log10(y.max() ** 2 / np.mean((x - y) ** 2)) > 55  # PSNR at the image's peak


@pytest.mark.slow
def test_bench_relight_cache_runs_the_three_relights_as_processes(session, tmp_path):
    """`sss bench relight-cache`: cold, cached and full relights, each an `sss relight` process with its own
    seconds and peak RSS; the cached one used the eigen-footprints and agrees with the full one."""
    import json

    from sssphase_core.bench import relight_cache_bench

    res = relight_cache_bench.run(session, tmp_path / "rc.json", backend="analytic", frames=8)
    steps = {r["step"]: r for r in res["rows"]}
    assert list(steps) == ["cold", "cached", "full", "sequence"]
    assert "wrote 8 frames to" in steps["sequence"]["output"] and np.isfinite(res["seconds_per_frame"])  # (8: too few to time)
    assert all(r["seconds"] > 0 and r["peak_rss_mib"] > 50 and r["returncode"] == 0 for r in steps.values())
    assert "--no-cache" in steps["full"]["command"] and "eigen-footprints" in steps["cached"]["output"]
    assert res["agreement"]["psnr_at_peak"] > 55 and res["speedup"] == steps["full"]["seconds"] / steps["cached"]["seconds"]
    assert json.loads((tmp_path / "rc.json").read_text())["agreement"] == res["agreement"]
    assert "| cached | stripes_y |" in (tmp_path / "rc.md").read_text()


@pytest.mark.slow
def test_an_evaluation_starts_from_the_footprints_the_trainings_check_kept(session, tmp_path):
    """`sss train decoder --check-sessions` relights the check views with the run's checkpoint (``baseline_check``
    into the run's check/); an evaluation of the same view with that checkpoint reads those footprints instead of
    predicting them again, and keeps its own for the next one; ``cache=False`` keeps none."""
    import dataclasses

    import torch

    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint
    from sssphase_core.relight.cache import CHECK_FOLDER
    from sssphase_core.relight.evaluation import baseline_check

    small = dataclasses.replace(get_preset("lite"), name="lite-small", stem=8, stages=(8, 12, 16), bottleneck=32,
                                proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4)
    torch.manual_seed(0)
    run = tmp_path / "run"
    run.mkdir()
    save_checkpoint(run / "best.pt", {"kind": "decoder", "preset": small.to_dict(), "config": {"head": "reciprocal"},
                                      "encoder": Encoder(small).state_dict(), "decoder": Decoder(small, head="reciprocal").state_dict()})
    checked = baseline_check([Session.open(session)], run, run / CHECK_FOLDER)
    (kept,) = (run / CHECK_FOLDER / "cache").glob("sand_rake_v0_*_torch_*.npz")
    said = Recorder()
    res = evaluate_sessions([session], backend="torch", checkpoint=run, out=tmp_path / "ev", narrator=said)
    # the same file (linked): a footprint predicted again would have had the cache rewritten
    assert (tmp_path / "ev" / "cache" / kept.name).stat().st_ino == kept.stat().st_ino
    (row,) = res.rows
    assert row["psnr"] == pytest.approx(next(r["psnr"] for r in checked["rows"] if r["backend"] == "torch"), abs=1e-9)
    assert row["footprints_from_cache"] == 1.0 and "torch read 100% of its footprints" in said.text()
    evaluate_sessions([session], backend="analytic", out=tmp_path / "none", cache=False)  # a model: else kept
    assert not (tmp_path / "none" / "cache").exists()
    # a first evaluation read back the footprints its own calibration had just cached: "read 50% from cache"
    said = Recorder()
    (row,) = evaluate_sessions([session], backend="analytic", out=tmp_path / "fresh", narrator=said).rows
    assert row["footprints_from_cache"] == 0 and "of its footprints from" not in said.text()
    assert list((tmp_path / "fresh" / "cache").glob("*.npz"))  # kept for the next one


def _tiny_decoder(run):
    """A decoder checkpoint of a small untrained model (its footprints are some footprints: enough for the plumbing)."""
    import dataclasses

    import torch

    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint

    small = dataclasses.replace(get_preset("lite"), name="lite-small", stem=8, stages=(8, 12, 16), bottleneck=32,
                                proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4)
    torch.manual_seed(0)
    run.mkdir()
    save_checkpoint(run / "best.pt", {"kind": "decoder", "preset": small.to_dict(), "config": {"head": "reciprocal"},
                                      "encoder": Encoder(small).state_dict(), "decoder": Decoder(small, head="reciprocal").state_dict()})
    return run


@pytest.mark.slow
def test_the_decoders_calibration_widens_by_default_and_the_analytic_models_does_not(session, tmp_path):
    """By default (``widen=None``) a backend that runs the decoder has its footprints stretched in the calibration
    (:data:`~sssphase_core.relight.choices.DECODER_WIDEN`), said once, and keeps its eigen-footprints under that
    stretch; ``widen=1`` turns them off; the analytic model has none unless asked; an evaluation records each
    backend's stretch and relights as `sss relight` does."""
    from sssphase_core.relight.choices import DECODER_WIDEN, widen_for

    assert widen_for("torch", None) == widen_for("blend", None) == DECODER_WIDEN
    assert widen_for("analytic", None) is None and widen_for("torch", 1.0) is None and widen_for("analytic", 1.5) == 1.5
    run = _tiny_decoder(tmp_path / "run")
    out = tmp_path / "w"  # one folder: the decoder's footprints are predicted once and read back from its cache after
    said = Recorder()
    wide = relight_session(session, ["checkerboard"], backend="torch", checkpoint=run, out=out, narrator=said, formats="exr")
    assert said.text().count(f"stretched {DECODER_WIDEN:g} x") == 1
    assert len(list((out / "cache").glob(f"sand_rake_v0_*_torch_*_w{DECODER_WIDEN:g}_lowrank.npz"))) == 1
    from sssphase_core.store.exr import read_exr

    x = read_exr(wide.images[0].paths[0])
    said = Recorder()
    plain = relight_session(session, ["checkerboard"], backend="torch", checkpoint=run, out=out, narrator=said,
                            widen=1.0, formats="exr")
    assert "stretched" not in said.text() and "eigen-footprints" not in said.text()  # not the widened relight's
    assert len([p for p in (out / "cache").glob("sand_rake_v0_*_torch_*_lowrank.npz") if "_w" not in p.name]) == 1
    assert np.abs(x - read_exr(plain.images[0].paths[0])).max() > 1e-4  # the stretched footprints took the place of the plain ones
    said = Recorder()
    res = evaluate_sessions([session], backend="analytic,torch", checkpoint=run, out=out, narrator=said)
    import json

    assert json.loads(res.json.read_text())["widen"] == {"analytic": None, "torch": DECODER_WIDEN}
    assert "calibration (torch): the torch footprints join the view's fit stretched" in said.text()
    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import relight_metrics

    rv = load_view(Session.open(session), 0)  # the evaluation relit as `sss relight` did: the same score
    row = next(r for r in res.rows if r["backend"] == "torch")
    assert row["psnr"] == pytest.approx(relight_metrics(x, rv.captured["checkerboard"], rv.proj.mask)["psnr"], abs=0.05)


def test_an_interrupted_relight_keeps_the_footprints_computed_so_far_and_the_next_computes_the_rest(session, tmp_path,
                                                                                                   monkeypatch):
    """Ctrl-C (or SIGTERM) mid-relight lost every footprint computed so far (tens of minutes for a 1080p view through a
    decoder on a CPU): the view's cache now keeps them, and the same relight again computes only the rest, to the same
    image as an uninterrupted relight."""
    from sssphase_core.relight import cache as cache_module
    from sssphase_core.relight import load_view
    from sssphase_core.store.exr import read_exr

    init, calls = cache_module.FootprintCache.__init__, []

    def interrupted_at_the_second_chunk(self, source, *args, **kwargs):
        def source_until_interrupted(pixels):
            calls.append(len(pixels))
            if len(calls) == 2:
                raise KeyboardInterrupt
            return source(pixels)
        init(self, source_until_interrupted, *args, **kwargs)

    monkeypatch.setattr(cache_module.FootprintCache, "__init__", interrupted_at_the_second_chunk)
    with pytest.raises(KeyboardInterrupt):
        relight_session(session, ["checkerboard"], backend="analytic", out=tmp_path / "a", formats="exr")
    monkeypatch.setattr(cache_module.FootprintCache, "__init__", init)
    (kept,) = (tmp_path / "a" / "cache").glob("sand_rake_v0_*_analytic_*.npz")
    lit = int(load_view(Session.open(session), 0).proj.mask.sum())
    with np.load(kept) as z:
        assert len(z["index"]) == calls[0] < lit  # the first chunk's footprints, and only those
    said = Recorder()
    again = relight_session(session, ["checkerboard"], backend="analytic", out=tmp_path / "a", formats="exr", narrator=said)
    whole = relight_session(session, ["checkerboard"], backend="analytic", out=tmp_path / "b", formats="exr")
    np.testing.assert_array_equal(read_exr(again.images[0].paths[0]), read_exr(whole.images[0].paths[0]))
    with np.load(kept) as z:
        assert len(z["index"]) == lit


@pytest.mark.slow
def test_footprints_a_device_keeps_reach_every_consumer_without_numpy_reading_them(session, tmp_path, monkeypatch):
    """On a GPU the decoder's footprints, the analytic model's beyond its training widths and its tail among them, stay
    tensors on the device, and NumPy cannot read those (``np.asarray`` of a CUDA tensor is a TypeError). Emulated on the
    CPU: tensors refuse NumPy's implicit conversion as CUDA ones do. The relight (cached or not), the evaluation, the
    geometry, the probe and ``footprints_at`` take them through ``footprint_array``, and the eigen-footprints of a view
    whose footprints the cache cannot hold are projected on the device."""
    import torch

    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import footprints_at
    from sssphase_core.relight.probe import probe_pixel

    run = _tiny_decoder(tmp_path / "run")
    ckpt = torch.load(run / "best.pt", weights_only=False)
    ckpt["domain"] = {"width_limit_px": [1.0, 1.0, 1.0], "tail_radius_px": [3, 4, 5]}  # some pixels beyond, a tail
    torch.save(ckpt, run / "best.pt")

    def refuse(self, *args, **kwargs):
        raise TypeError(f"can't convert {self.device} device type tensor to numpy (as a cuda:0 tensor)")

    monkeypatch.setattr(torch.Tensor, "__array__", refuse)
    with pytest.raises(TypeError, match="as a cuda:0 tensor"):
        np.asarray(torch.zeros(2))
    said = Recorder()
    with monkeypatch.context() as m:  # footprints beyond the cache's budget (a 1080p view's): only eigen-footprints kept,
        m.setattr("sssphase_core.relight.cache.CACHE_BYTES", 0)  # projected where the footprints are
        res = relight_session(session, ["checkerboard"], backend="torch", checkpoint=run, out=tmp_path / "r", narrator=said)
    assert res.backend == "torch" and "analytic model" in said.text()  # (the guard's line: its parts ran)
    assert "relit from its eigen-footprints alone" in said.text()
    assert [f.name.endswith("_lowrank.npz") for f in (tmp_path / "r" / "cache").iterdir()] == [True]  # (no footprints)
    (row,) = evaluate_sessions([session], backend="torch", checkpoint=run, out=tmp_path / "ev").rows  # (cached)
    assert np.isfinite(row["psnr"])
    geometry_session(session, backend="torch", checkpoint=run, out=tmp_path / "geo")
    rv = load_view(Session.open(session), 0)
    ys, xs = np.nonzero(rv.proj.mask)
    fps = footprints_at(rv, np.stack([ys[:3], xs[:3]], 1), ["torch", "analytic"], checkpoint=run)
    assert all(isinstance(f, np.ndarray) and f.shape[0] == 3 for f in fps.values())
    assert "torch" in probe_pixel(rv, (int(ys[0]), int(xs[0])), checkpoint=run).footprints


@pytest.mark.slow
def test_a_checkpoint_a_training_replaces_during_an_evaluation_is_refused_not_mixed(session, tmp_path, monkeypatch):
    """`sss eval relight --checkpoint runs/dec` while `sss train decoder` still wrote runs/dec/best.pt at its epoch
    ends scored its first view with one model and the next with another, under one "torch" row."""
    import dataclasses

    import torch

    from sssphase_core.errors import DataError
    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint
    from sssphase_core.relight import runner

    small = dataclasses.replace(get_preset("lite"), name="lite-small", stem=8, stages=(8, 12, 16), bottleneck=32,
                                proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4)
    run = tmp_path / "run"

    def epoch(seed: int) -> None:  # a training's checkpoint at an epoch end (written whole, then renamed)
        torch.manual_seed(seed)
        save_checkpoint(run / "best.pt", {"kind": "decoder", "preset": small.to_dict(), "config": {"head": "reciprocal"},
                                          "encoder": Encoder(small).state_dict(),
                                          "decoder": Decoder(small, head="reciprocal").state_dict()})

    epoch(0)
    real = runner.evaluate_view

    def then_the_next_epoch(*args, **kwargs):
        rows = real(*args, **kwargs)
        epoch(1)
        return rows

    monkeypatch.setattr(runner, "evaluate_view", then_the_next_epoch)
    with pytest.raises(DataError, match=r"best.pt was replaced while this command ran \(a training writing it"):
        evaluate_sessions([session], backend="torch,blend", checkpoint=run, out=tmp_path / "ev", cache=False)
    monkeypatch.setattr(runner, "evaluate_view", real)
    assert len(evaluate_sessions([session], backend="torch,blend", checkpoint=run, out=tmp_path / "ev2",
                                 cache=False).rows) == 2  # unchanged since: both backends with the same model
