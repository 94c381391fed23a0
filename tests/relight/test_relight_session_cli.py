"""Relighting a simulated session from the CLI, and evaluating it against its reference captures."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from sssphase_cli.main import app
from sssphase_core.relight import load_view
from sssphase_core.relight.evaluation import relight_metrics
from sssphase_core.store.session import Session

runner = CliRunner()


#: The analytic model's patch in the calibration tests: they test linear algebra on any model's
#: footprints, and 11 x 11 footprints cost a tenth of the view's 32 x 32.
SMALL_PATCH = 11


@pytest.fixture(scope="module")
def session(tmp_path_factory, sim_daemon):
    """View 1 of 4 of the sand rake with two reference patterns, captured through the daemon."""
    from sssphase_core.capture import CaptureRequest, run_capture

    req = CaptureRequest("sand_rake", views=2, references=("checkerboard", "stripes_x"), out=tmp_path_factory.mktemp("s"))
    return run_capture(sim_daemon, req).path


def test_load_view_reads_projection_references_and_truth(session):
    rv = load_view(Session.open(session), 1)
    assert rv.proj.projector_size == (256, 192) and rv.patch == 32 and rv.sim["object"] == "sand_rake"
    assert set(rv.references) == {"checkerboard", "stripes_x"}
    assert rv.psp.shape == (8, 192, 256, 3) and rv.proj.mask.sum() > 500
    assert np.isnan(rv.proj.xp[~rv.proj.mask]).all()


def test_cli_relight_writes_images_and_scores_named_references(session, tmp_path):
    out = tmp_path / "relit"
    res = runner.invoke(app, ["relight", str(session), "--pattern", "checkerboard", "--pattern", "white",
                              "--backend", "exact", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "PSNR" in res.output  # checkerboard has a reference capture
    for name in ("checkerboard", "white"):
        assert (out / f"sand_rake_v1_{name}_exact.png").exists()
        assert (out / f"sand_rake_v1_{name}_exact_display.png").exists()
    assert (out / "sand_rake_v1_checkerboard_exact_compare.png").exists()
    assert len(list((out / "cache").glob("sand_rake_v1_*_exact_*.npz"))) == 1


def test_cli_relight_rejects_a_wrong_pattern_size(session, tmp_path):
    from PIL import Image

    Image.fromarray(np.zeros((10, 12), np.uint8)).save(tmp_path / "small.png")
    res = runner.invoke(app, ["relight", str(session), "--pattern", str(tmp_path / "small.png"), "--backend", "none",
                              "--out", str(tmp_path / "o")])
    assert res.exit_code != 0
    assert "--resize" in str(res.exception)
    ok = runner.invoke(app, ["relight", str(session), "--pattern", str(tmp_path / "small.png"), "--backend", "none",
                             "--resize", "stretch", "--out", str(tmp_path / "o")])
    assert ok.exit_code == 0, ok.output


def test_each_pattern_gets_its_own_files_whatever_its_name(session, tmp_path):
    """A dot in a pattern's name is no file suffix (lamp.v1 and lamp.v2 are two outputs, the backend kept in
    both names); two patterns whose files share a name are refused before anything is written."""
    from PIL import Image

    pats = tmp_path / "pats"
    for rel in ("lamp.v1.png", "lamp.v2.png", "a/x.png", "b/x.png"):
        (pats / rel).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((192, 256), 200 if "v1" in rel else 40, np.uint8)).save(pats / rel)
    out = tmp_path / "o"
    res = runner.invoke(app, ["relight", str(session), "--views", "1", "--pattern", str(pats / "lamp.v1.png"), "--pattern",
                              str(pats / "lamp.v2.png"), "--backend", "none", "--format", "png,exr", "--out", str(out)])
    assert res.exit_code == 0, res.output
    for v in ("v1", "v2"):
        assert {p.name for p in out.glob(f"sand_rake_v1_lamp.{v}_none*")} == {
            f"sand_rake_v1_lamp.{v}_none{end}" for end in (".png", ".exr", "_display.png")}
    from sssphase_core.store.exr import read_exr

    assert read_exr(out / "sand_rake_v1_lamp.v1_none.exr").mean() > 2 * read_exr(out / "sand_rake_v1_lamp.v2_none.exr").mean()
    twins = runner.invoke(app, ["relight", str(session), "--views", "1", "--pattern", str(pats / "a/x.png"), "--pattern",
                                str(pats / "b/x.png"), "--backend", "none", "--out", str(tmp_path / "twins")])
    assert twins.exit_code != 0 and "both be written as 'x'" in str(twins.exception)
    assert not (tmp_path / "twins").exists()


def test_eval_relight_table_exact_beats_no_scattering(session, tmp_path):
    res = runner.invoke(app, ["eval", "relight", str(session), "--backend", "none,exact", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "relight_eval.json").read_text())
    psnr = {(a["backend"], a["pattern"]): a["psnr"] for a in data["aggregate"]}
    for pattern in ("checkerboard", "stripes_x"):
        assert psnr[("exact", pattern)] > psnr[("none", pattern)] + 3
    md = (tmp_path / "relight_eval.md").read_text()
    assert "LPIPS skipped" in md and "px inside (dB)" in md
    for r in data["rows"]:  # each row also scored away from the silhouette, where the camera mixes in background
        assert np.isfinite(r["psnr_interior"]) and r["psnr_interior"] != r["psnr"]


def test_eval_relight_says_when_a_model_cannot_be_calibrated_to_the_view(session, tmp_path):
    import shutil

    copy = tmp_path / "sand_rake"
    shutil.copytree(session, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    for f in manifest["plan"]["frames"]:  # a plan that no longer says which 8 patterns the PSP stack was taken under
        if f["kind"] == "psp":
            f["params"]["shift"] = 0
    (copy / "manifest.json").write_text(json.dumps(manifest))
    res = runner.invoke(app, ["eval", "relight", str(copy), "--backend", "none,analytic", "--views", "1",
                              "--out", str(tmp_path / "e")])
    assert res.exit_code == 0, res.output
    assert "note: sand_rake view 1: analytic is not calibrated to the view" in " ".join(res.output.split())
    assert "none is not calibrated" not in res.output  # data, not a model: nothing to calibrate


def test_metrics_on_mask():
    rng = np.random.default_rng(0)
    ref = rng.random((20, 24, 3)).astype(np.float32)
    mask = np.zeros((20, 24), bool)
    mask[5:15, 5:20] = True
    same = relight_metrics(ref, ref, mask)
    assert same["mse"] == 0 and same["psnr"] == float("inf") and same["ssim"] == pytest.approx(1.0, abs=1e-4)
    off = ref.copy()
    off[mask] += 0.1
    off[~mask] = 5.0  # outside the mask: ignored
    m = relight_metrics(off, ref, mask)
    assert m["mse"] == pytest.approx(0.01, rel=1e-4) and m["psnr"] == pytest.approx(20.0, abs=1e-3)
    assert relight_metrics(off, ref, mask, data_range=0.5)["psnr"] == pytest.approx(20 + 20 * np.log10(0.5), abs=1e-3)


def test_interior_psnr_leaves_out_the_silhouette_band_only():
    from sssphase_core.relight.evaluation import edge_band, interior_psnr

    ref = np.full((20, 24, 3), 0.5, np.float32)
    mask = np.zeros((20, 24), bool)
    mask[4:16, 4:20] = True
    band = edge_band(mask)
    assert band.sum() == mask.sum() - 8 * 12  # the 2 px next to the edge of a 12 x 16 rectangle
    at_edge = ref.copy()
    at_edge[band] += 0.1
    assert relight_metrics(at_edge, ref, mask)["psnr"] < 25 and interior_psnr(at_edge, ref, mask) == float("inf")
    inside = ref.copy()
    inside[mask & ~band] += 0.1
    assert interior_psnr(inside, ref, mask) == pytest.approx(20.0, abs=1e-3)
    assert np.isnan(interior_psnr(ref, ref, band & ~band))  # nothing inside: not a number, not an error


def test_bench_gap_decomposes_a_model_against_the_exact_footprints(session, tmp_path):
    from sssphase_core.bench.gap_bench import HYBRIDS, hybrid

    out = tmp_path / "gap.json"
    res = runner.invoke(app, ["bench", "gap", str(session), "--backend", "analytic", "--views", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())["rows"]
    assert {r["pattern"] for r in rows} == {"checkerboard", "stripes_x"}
    for r in rows:
        assert r["psnr_exact"] > r["psnr_analytic"] + 5
        assert all(r["psnr_exact"] > r[f"psnr_{h}"] for h in ("energy", "shape", "centre"))  # each swap costs accuracy
        assert all(np.isfinite(r[f"share_{h}"]) for h in HYBRIDS) and 0 < r["share_silhouette"] < 1
        assert r["psnr_inside_exact"] > r["psnr_inside_analytic"] and r["psnr_inside_none"] != r["psnr_none"]
        # the camera's noisy, demosaiced white bounds what captured light allows, below the exact footprints
        assert r["psnr_exact"] > r["psnr_white"] and 20 < r["psnr_white_capture"] < r["psnr_inside_white_capture"]
    md = out.with_suffix(".md").read_text()
    assert "silhouette" in md and "away from the silhouette" in md and "What captured light allows" in md
    fps = np.random.default_rng(0).random((4, 7, 7, 3)).astype(np.float32)
    for h in ("energy", "shape", "centre"):  # a model equal to the exact footprints changes nothing
        np.testing.assert_allclose(hybrid(h, fps, fps), fps, rtol=1e-5)
    np.testing.assert_allclose(hybrid("white", fps, fps, 2 * fps.sum(axis=(1, 2))), 2 * fps, rtol=1e-5)
    bad = runner.invoke(app, ["bench", "gap", str(session), "--views", "x", "--out", str(out)])
    assert bad.exit_code != 0 and "--views" in str(bad.exception)


def test_a_model_is_mixed_with_no_scattering_by_the_views_own_fringe_captures(session):
    from sssphase_core.relight import fit_view_mix, make_source, no_scattering_source, relight

    rv = load_view(Session.open(session), 1)
    assert rv.psp_patterns is not None and rv.psp_patterns.shape == (8, 192, 256)
    raw, k = make_source("analytic", rv, calibrate=False, patch=SMALL_PATCH)
    mixed, _ = make_source("analytic", rv, patch=SMALL_PATCH)
    mix = mixed.mix
    assert mix.shape == (3,) and ((mix >= 0) & (mix <= 1)).all()
    np.testing.assert_allclose(fit_view_mix(raw, k, rv), mix, atol=1e-6)
    px = np.argwhere(rv.proj.mask)[::97]
    want = raw(px) * mix
    want[:, k // 2, k // 2] += (1 - mix) * rv.white[px[:, 0], px[:, 1]]
    np.testing.assert_allclose(mixed(px), want, rtol=1e-5, atol=1e-7)
    m = rv.proj.mask  # what the calibration fits on

    def residual(source, patch):  # how well a source relights the view's own fringe captures, as the camera sees them
        out = rv.through_camera(relight(source, rv.proj, rv.psp_patterns, patch, white=rv.white))
        return float(((out[:, m] - rv.psp[:, m]) ** 2).mean())

    none = residual(no_scattering_source(rv.white), 1)
    assert residual(mixed, k) <= min(residual(raw, k), none) * (1 + 1e-6)


def test_the_calibration_compares_relit_fringes_as_the_camera_records_them(session):
    """The exact footprints relight the fringe captures best at full weight once the relit fringes go
    through the camera's Bayer sampling and demosaicing (recorded by the capture); compared raw, the
    demosaicing's contrast changes read as too much scattering and pull the weight towards none."""
    from sssphase_core.relight import fit_view_mix, make_source

    rv = load_view(Session.open(session), 1)
    assert rv.camera_isp == {"demosaic": "malvar", "median": False, "bayer": "RGGB"}  # the sim camera's own pipeline
    exact, k = make_source("exact", rv)
    seen = fit_view_mix(exact, k, rv)
    assert (seen > 0.9).all(), seen
    rv.camera_isp = None  # a session that does not say how its frames were made: compared raw
    raw = fit_view_mix(exact, k, rv)
    assert (raw < 0.8).any() and (raw <= seen + 1e-6).all(), (raw, seen)


def test_through_camera_is_the_sim_cameras_image_without_noise(session):
    from sssphase_core.processing.isp import through_camera

    rv = load_view(Session.open(session), 1)
    scene = rv.scene()
    render = scene.render(rv.references["checkerboard"][None])
    sensor = scene.rig.sensor
    want = scene.sense_noise_free(render)
    got = through_camera(render, demosaic=sensor.demosaic, median=sensor.isp_median)
    np.testing.assert_allclose(got, want, atol=2e-4)
    odd = through_camera(render[:, :-1, :-3])  # odd sides: padded by a reflected row or column, cut back
    assert odd.shape == render[:, :-1, :-3].shape and np.isfinite(odd).all()


def test_the_local_mixture_finds_each_materials_weight():
    """Two materials in one view (an object on a diffuse table): on the left the captures are the model's
    fringes, on the right no scattering's. The view-wide weight is their compromise; the local one is 1
    and 0 away from the border, and the view-wide weight where no pixel has evidence."""
    from types import SimpleNamespace

    from sssphase_core.relight.calibration import local_mixture

    rng = np.random.default_rng(0)
    h, w = 40, 60
    none = rng.random((8, h, w, 3)).astype(np.float32)
    model = (none + 0.2 * rng.standard_normal((8, h, w, 3))).astype(np.float32)
    captured = np.where(np.arange(w)[None, None, :, None] < w // 2, model, none)
    mask = np.ones((h, w), bool)
    mask[:, -15:] = False  # no evidence there
    rv = SimpleNamespace(proj=SimpleNamespace(mask=mask), camera_isp=None)
    (weight,), (view,) = local_mixture(rv, [model], none, captured, None)
    assert weight.shape == (h, w, 3) and ((view > 0.1) & (view < 0.9)).all()  # the compromise of the two
    np.testing.assert_allclose(weight[:, :20], 1.0, atol=0.04)  # the prior pulls 5% toward the view weight
    np.testing.assert_allclose(weight[:, 35:40], 0.0, atol=0.04)
    np.testing.assert_allclose(weight[:, -1], np.broadcast_to(view, (h, 3)), atol=0.05)


def test_a_blend_is_weighted_per_pixel_by_each_materials_own_source():
    """Three materials in one view: the captures are source A's fringes on the left, B's in the middle and
    no scattering's on the right. Each region's weights come out (1, 0), (0, 1) and (0, 0), always within
    ``a >= 0``, ``sum(a) <= 1``; the view-wide weights are the constrained fit over the whole view."""
    from types import SimpleNamespace

    from sssphase_core.relight import mixture_weights
    from sssphase_core.relight.calibration import local_mixture

    rng = np.random.default_rng(1)
    h, w = 30, 90
    none = rng.random((8, h, w, 3)).astype(np.float32)
    a, b = ((none + 0.2 * rng.standard_normal((8, h, w, 3))).astype(np.float32) for _ in range(2))
    col = np.arange(w)[None, None, :, None]
    captured = np.where(col < 30, a, np.where(col < 60, b, none))
    rv = SimpleNamespace(proj=SimpleNamespace(mask=np.ones((h, w), bool)), camera_isp=None)
    weights, view = local_mixture(rv, [a, b], none, captured, None)
    assert weights.shape == (2, h, w, 3) and view.shape == (2, 3)
    assert (weights >= 0).all() and (weights.sum(axis=0) <= 1 + 1e-5).all()
    for lo, want in ((0, (1, 0)), (30, (0, 1)), (60, (0, 0))):
        got = weights[:, :, lo + 8:lo + 22].reshape(2, -1)
        np.testing.assert_allclose(got, np.broadcast_to(np.array(want, np.float32)[:, None], got.shape), atol=0.06)
    d = np.stack([(a - none).ravel(), (b - none).ravel()]).reshape(2, -1, 3)
    e = (captured - none).reshape(-1, 3)
    for c in range(3):
        want = mixture_weights(d[:, :, c] @ d[:, :, c].T, d[:, :, c] @ e[:, c])
        np.testing.assert_allclose(view[:, c], want, atol=1e-4)


def test_the_local_mixture_works_on_the_fitted_pixels_box_only(monkeypatch):
    """Only the fitted pixels' box is worked on (a 1080p view is mostly background): the weights of a small object
    in a large frame, wherever it lies (at the frame's corners too), equal those fitted over the whole frame, and
    are the view-wide weights away from it; for one source and for three."""
    from types import SimpleNamespace

    from sssphase_core.relight import calibration
    from sssphase_core.relight.calibration import local_mixture

    rng = np.random.default_rng(2)
    h, w = 24, 30
    none = rng.random((8, h, w, 3)).astype(np.float32)
    sources = [(none + 0.2 * rng.standard_normal((8, h, w, 3))).astype(np.float32) for _ in range(3)]
    captured = np.where(np.arange(w)[None, None, :, None] < 12, sources[0], 0.5 * sources[1] + 0.5 * none)
    mask = np.zeros((h, w), bool)
    mask[3:-3, 3:-3] = True
    for y, x in ((120, 200), (0, 0), (176, 270)):  # inside, at the top-left corner, at the bottom-right one
        def framed(a, y=y, x=x):
            out = np.full((a.shape[0], 200, 300, *a.shape[3:]), 0.3, a.dtype)  # background: unfitted, any value
            out[:, y:y + h, x:x + w] = a
            return out
        big = np.zeros((200, 300), bool)
        big[y:y + h, x:x + w] = mask
        rv = SimpleNamespace(proj=SimpleNamespace(mask=big), camera_isp=None)
        for s in (1, 3):
            args = ([framed(a) for a in sources[:s]], framed(none), framed(captured), None)
            weights, view = local_mixture(rv, *args)
            with monkeypatch.context() as patched:
                patched.setattr(calibration, "LOCAL_MIX_REACH", 10**6)  # the box: the whole frame
                whole, whole_view = local_mixture(rv, *args)
            np.testing.assert_array_equal(view, whole_view)
            np.testing.assert_allclose(weights, whole, atol=1e-6)
            far = np.ones((200, 300), bool)
            far[max(0, y - 10):y + h + 10, max(0, x - 10):x + w + 10] = False
            np.testing.assert_array_equal(weights[:, far], np.broadcast_to(view[:, None], (s, int(far.sum()), 3)))


def test_relighting_with_the_view_calibration_takes_one_footprint_pass(session):
    """`relight_view` fits the calibration on the same pass as the user's patterns: the view-wide mix of the
    white-consistent model (`white_consistent`, the white pattern on the same pass) against no scattering,
    refined per pixel (`local_mixture`), with each footprint predicted once."""
    from sssphase_core.processing.patterns import white
    from sssphase_core.relight import make_source, relight, relight_view
    from sssphase_core.relight.calibration import exit_white, local_mixture, model_inputs
    from sssphase_core.relight.pipeline import white_consistent
    from sssphase_core.relight.sources import no_scattering_source

    rv = load_view(Session.open(session), 1)
    raw, k = make_source("analytic", rv, calibrate=False, patch=SMALL_PATCH)
    calls = []

    def counted(pixels):
        calls.append(len(pixels))
        return raw(pixels)

    pats = [rv.references["checkerboard"], rv.references["stripes_x"]]
    fused, mix = relight_view(counted, k, rv, pats, calibrate=True)
    assert sum(calls) <= rv.proj.mask.sum()  # one footprint per lit pixel: no second pass
    every = pats + list(rv.psp_patterns)
    model = white_consistent(rv, relight(raw, rv.proj, every + [white(*rv.proj.projector_size)], k, white=rv.white))[0]
    none = relight(no_scattering_source(exit_white(rv)), rv.proj, every, 1, white=rv.white)
    psp, lost = model_inputs(rv)
    (weight,), (view_weight,) = local_mixture(rv, [model[2:]], none[2:], psp, lost)
    np.testing.assert_allclose(view_weight, mix, atol=1e-6)
    np.testing.assert_allclose(fused, none[:2] + weight * (model[:2] - none[:2]), rtol=1e-4, atol=1e-6)
    inside = rv.proj.mask & (weight > 0).all(axis=-1) & (weight < 1).all(axis=-1)
    assert np.abs(np.median(weight[inside], axis=0) - mix).max() < 0.1  # one material: near the view's weight
    plain, none_mix = relight_view(raw, k, rv, pats, calibrate=False)
    assert none_mix is None and plain.shape == fused.shape


def test_a_view_relit_under_white_returns_its_white_capture_a_bayer_cameras_too(session):
    """A model's images are made consistent with the view's white (`exit_gain`; the nine-capture white of
    `exit_white`): relit under full white, the calibrated model returns that white, whatever its weights, as far as
    it stands above its noise (`noise_shrinkage`: nearly all of it here), and exact footprints need no gain. A Bayer
    camera's views were left as the model relit them: with the nine-capture white they too relight better made
    consistent (analytic +1.3 to +4.7 dB on five sim objects)."""
    from sssphase_core.processing.patterns import white
    from sssphase_core.relight import make_source, relight, relight_view
    from sssphase_core.relight.calibration import EXIT_GAIN_RANGE, exit_gain, exit_white, white_usable

    rv = load_view(Session.open(session), 1)
    assert rv.camera_isp and rv.camera_isp["bayer"]  # a Bayer camera's session
    raw, k = make_source("analytic", rv, calibrate=False, patch=SMALL_PATCH)
    pats = [white(*rv.proj.projector_size), rv.references["checkerboard"]]
    plain, _ = relight_view(raw, k, rv, pats, calibrate=False)
    full, _ = relight_view(raw, k, rv, pats, calibrate=True)
    gain = exit_gain(rv, relight(raw, rv.proj, pats[:1], k, white=rv.white)[0])
    lo, hi = EXIT_GAIN_RANGE
    ok = rv.proj.mask & white_usable(rv.white, rv.white_saturation) & ((gain > lo) & (gain < hi)).all(axis=-1)
    assert ok.mean() > 0.5 * rv.proj.mask.mean()
    white = exit_white(rv)
    # under white the calibration's no-scattering term is that white, and the model's share of the image is moved a
    # share `keep` of the way from its own white to it: what is left is (1 - keep) of the way at most
    left, whole = np.abs(full[0][ok] - white[ok]), np.abs(plain[0][ok] - white[ok])
    share = np.percentile(left / np.maximum(whole, 1e-6), [50, 99])  # (a few pixels' gains reach EXIT_GAIN_RANGE)
    assert share[0] < 0.02 and share[1] < 0.05, share
    exact, ke = make_source("exact", rv, calibrate=False)
    exact_gain = exit_gain(rv, relight(exact, rv.proj, pats[:1], ke, white=rv.white)[0])[rv.proj.mask]
    assert np.abs(np.median(exact_gain, axis=0) - 1).max() < 0.05  # the capture's noise and demosaicing only
    spread = lambda g: np.subtract(*np.percentile(g, [90, 10], axis=0))  # noqa: E731
    assert (spread(exact_gain) < spread(gain[rv.proj.mask])).all()  # a model's energy errors need more


def test_geometry_cli_writes_both_maps_and_scores_them(session, tmp_path):
    res = runner.invoke(app, ["geometry", str(session), "--backend", "exact", "--views", "1", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    data = np.load(tmp_path / "sand_rake" / "view_001" / "correspondence_for_geometry.npz")
    s = Session.open(session)
    gt = np.asarray(s.load(1, "gt/proj_xy"))
    ok = data["mask"] & np.isfinite(gt[..., 0])
    err = lambda x, y: np.median(np.hypot(x - gt[..., 0], y - gt[..., 1])[ok])  # noqa: E731
    # the sand rake's footprints are symmetric (burley): little to remove, but never worse
    assert err(data["xp"], data["yp"]) < err(data["xp_decoded"], data["yp_decoded"])
    np.testing.assert_array_equal(data["xp_decoded"], np.asarray(s.load(1, "corr/xp")))
    assert "against the exact points" in res.output
    bad = runner.invoke(app, ["geometry", str(session), "--backend", "measured", "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "placed by the decoded correspondences" in str(bad.exception)


@pytest.mark.parametrize("s", [1, 2, 3])
def test_mixture_weights_are_the_constrained_least_squares_optimum(s):
    """``a >= 0``, ``sum(a) <= 1``, and no point of a fine grid over that simplex fits better."""
    from sssphase_core.relight import mixture_weights

    rng = np.random.default_rng(s)
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 41)] * s, indexing="ij"), -1).reshape(-1, s)
    grid = grid[grid.sum(1) <= 1 + 1e-9]
    for _ in range(20):
        d = rng.normal(size=(s, 50)) * rng.uniform(0.1, 2, (s, 1))
        e = rng.normal(size=50) + d.T @ rng.uniform(-0.5, 1.5, s)
        gram, cross = d @ d.T, d @ e
        a = mixture_weights(gram, cross)
        assert (a >= 0).all() and a.sum() <= 1 + 1e-9
        costs = ((grid @ d - e) ** 2).sum(axis=1)
        assert ((a @ d - e) ** 2).sum() <= costs.min() + 1e-9
        if s == 1:
            assert a[0] == pytest.approx(np.clip(cross[0] / gram[0, 0], 0, 1))
    assert (mixture_weights(np.zeros((2, 2)), np.zeros(2)) == 0).all()  # sources equal to none: no weight


def test_a_blend_relights_the_fringe_captures_at_least_as_well_as_each_member(session):
    """Blending two sources by the view calibration: its images are the sum weighted pixel by pixel
    (`local_mixture`), and since each member's own calibration is a feasible blend, the blend fits the
    view's captures no worse."""
    from sssphase_core.processing.patterns import white
    from sssphase_core.relight import make_source, model_inputs, no_scattering_source, relight, relight_view
    from sssphase_core.relight.calibration import exit_white, local_mixture
    from sssphase_core.relight.pipeline import white_consistent

    rv = load_view(Session.open(session), 1)
    members = [make_source("analytic", rv, calibrate=False, patch=SMALL_PATCH), make_source("exact", rv, calibrate=False)]
    pats = list(rv.psp_patterns)  # relit under its own fringe patterns: the fitted quantity
    blend, mix = relight_view(*members[0], rv, pats, calibrate=True, also=members[1:])
    assert mix.shape == (2, 3) and (mix >= 0).all() and (mix.sum(0) <= 1 + 1e-6).all()
    none = relight(no_scattering_source(exit_white(rv)), rv.proj, pats, 1, white=rv.white)
    relits = [white_consistent(rv, relight(src, rv.proj, pats + [white(*rv.proj.projector_size)], k, white=rv.white))[0]
              for src, k in members]
    psp, lost = model_inputs(rv)
    weights, view_weights = local_mixture(rv, relits, none, psp, lost)
    np.testing.assert_allclose(view_weights, mix, atol=1e-5)
    want = none + sum(w * (r - none) for w, r in zip(weights, relits, strict=True))
    np.testing.assert_allclose(blend, want, rtol=1e-4, atol=1e-6)
    m = rv.proj.mask & ~lost
    residual = lambda img: float(((rv.through_camera(img)[:, m] - psp[:, m]) ** 2).sum())  # noqa: E731
    alone = [relight_view(src, k, rv, pats, calibrate=True)[0] for src, k in members]
    assert residual(blend) <= min(residual(a) for a in alone) * (1 + 1e-5)
    with pytest.raises(Exception, match="blending sources needs the view calibration"):
        relight_view(*members[0], rv, pats, calibrate=False, also=members[1:])


def test_blend_without_a_decoder_is_one_clear_error(session, tmp_path):
    res = runner.invoke(app, ["relight", str(session), "--pattern", "checkerboard", "--backend", "blend",
                              "--out", str(tmp_path)])
    assert res.exit_code != 0 and "blend backend blends the decoder in" in str(res.exception)


def test_a_pattern_is_scored_against_a_reference_only_when_it_is_that_pattern(session, tmp_path):
    """A file called checkerboard.png that holds stripes was scored against the captured checkerboard
    (10.7 dB, a comparison figure and all); the real checkerboard, as an 8-bit file, still is."""
    import cv2

    from sssphase_core.processing.patterns import reference_pattern

    rv = load_view(Session.open(session), 1)
    wp, hp = rv.proj.projector_size
    for folder, name in ((tmp_path / "liar", "stripes_x"), (tmp_path / "honest", "checkerboard")):
        folder.mkdir()
        cv2.imwrite(str(folder / "checkerboard.png"), np.round(reference_pattern(name, wp, hp) * 255).astype(np.uint8))
        res = runner.invoke(app, ["relight", str(session), "--pattern", str(folder / "checkerboard.png"), "--backend",
                                  "none", "--views", "1", "--out", str(folder / "out")])
        assert res.exit_code == 0, res.output
        scored = "vs reference" in res.output
        assert scored == (name == "checkerboard"), res.output
        assert any((folder / "out").glob("*_compare.png")) == scored
    # the stripes relit as "checkerboard" into the folder of the scored one: the comparison of the checkerboard stayed
    # beside the stripes' image, contradicting it
    res = runner.invoke(app, ["relight", str(session), "--pattern", str(tmp_path / "liar" / "checkerboard.png"),
                              "--backend", "none", "--views", "1", "--out", str(tmp_path / "honest" / "out")])
    assert res.exit_code == 0 and not any((tmp_path / "honest" / "out").glob("*_compare.png")), res.output


def test_relight_without_a_backend_takes_the_analytic_model_until_a_decoder_is_given(session, tmp_path):
    """`--backend auto` (the default): the blend of decoder and analytic model with --checkpoint (ahead of
    the decoder alone on every object measured), the analytic model without one, saying which."""
    res = runner.invoke(app, ["relight", str(session), "--views", "1", "--pattern", "checkerboard", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "backend: analytic (no --checkpoint" in res.output
    assert (tmp_path / "sand_rake_v1_checkerboard_analytic.png").exists()


def test_display_images_of_a_view_share_one_exposure_and_an_empty_view_is_refused(session, tmp_path):
    """Each display PNG was exposed to its own 99.5th percentile: a view relit under black looked as bright as
    under white. A view whose decode mask was empty relit as black without a word (and failed when scored)."""
    import hashlib
    import shutil

    import cv2
    import zarr

    from sssphase_core.errors import DataError

    out = tmp_path / "relit"
    res = runner.invoke(app, ["relight", str(session), "--pattern", "black", "--pattern", "white", "--backend", "none",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    black, white = (cv2.imread(str(out / f"sand_rake_v1_{n}_none_display.png")) for n in ("black", "white"))
    assert black.mean() < 0.1 * white.mean() and white.max() == 255
    empty = tmp_path / "empty" / "sand_rake"
    shutil.copytree(session, empty)
    with zarr.config.set({"array.write_empty_chunks": True}):
        arr = zarr.open_array(str(empty / "view_001" / "corr" / "mask"), mode="r+")
        arr[...] = np.zeros(arr.shape, bool)
    s = Session.open(empty)
    data = np.ascontiguousarray(arr[...])
    s.manifest["views"]["1"]["arrays"]["corr/mask"]["checksum"] = "sha256:" + hashlib.sha256(memoryview(data).cast("B")).hexdigest()
    s.save()
    assert Session.open(empty).validate() == []  # a consistent session, only with nothing decoded
    res = runner.invoke(app, ["relight", str(empty), "--pattern", "checkerboard", "--backend", "none", "--views", "1",
                              "--out", str(tmp_path / "e")])
    assert isinstance(res.exception, DataError) and "no pixel decoded (corr/mask is empty)" in str(res.exception)
    assert not list(tmp_path.glob("e/*.png"))


def test_geometry_names_the_backends_it_takes_and_checks_the_device(session, tmp_path):
    from sssphase_core.errors import InputError

    res = runner.invoke(app, ["geometry", str(session), "--backend", "blend", "--out", str(tmp_path / "g")])
    assert isinstance(res.exception, InputError) and "use one of exact, analytic, torch" in str(res.exception)
    res = runner.invoke(app, ["geometry", str(session), "--backend", "exact", "--device", "tpu", "--out", str(tmp_path / "g")])
    assert isinstance(res.exception, InputError) and "unknown device 'tpu'" in str(res.exception)  # was ignored
    assert not (tmp_path / "g").exists()


def test_outputs_of_another_session_of_the_same_object_are_not_replaced(session, tmp_path):
    """Outputs are named by object: a second session of the same object (a re-capture, a copy) relit, evaluated
    or exported into the same --out is refused before any work, whatever its patterns; a rerun of the first is
    not. A record that cannot be read is named, not ignored."""
    import shutil

    twin = tmp_path / "again" / session.name
    shutil.copytree(session, twin)
    out = tmp_path / "o"
    args = ["--views", "1", "--backend", "none", "--out", str(out)]
    assert runner.invoke(app, ["relight", str(session), "--pattern", "white", *args]).exit_code == 0
    first = (out / "sand_rake_v1_white_none.png").read_bytes()
    (out / "sand_rake_v1_white_none.png").write_bytes(first + b"mark")  # any rewrite would drop the mark
    for cmd in (["relight", str(twin), "--pattern", "white", *args], ["relight", str(twin), "--pattern", "black", *args],
                ["eval", "relight", str(twin), *args], ["export", str(twin), "--out", str(out)]):
        res = runner.invoke(app, cmd)
        assert res.exit_code != 0 and "holds outputs of 'sand_rake' from another session" in str(res.exception), cmd
        assert str(session.resolve()) in str(res.exception)
    assert (out / "sand_rake_v1_white_none.png").read_bytes() == first + b"mark"
    assert not list(out.glob("*black*")) and not (out / "sand_rake").exists()
    again = runner.invoke(app, ["relight", str(session), "--pattern", "white", *args])  # the same session: a rerun
    assert again.exit_code == 0, again.output
    assert not (out / "sand_rake_v1_white_none.png").read_bytes().endswith(b"mark")
    assert runner.invoke(app, ["relight", str(twin), "--pattern", "white", *args[:-1], str(tmp_path / "o2")]).exit_code == 0
    (out / "sources.json").write_text('{"sand_rake": "/x"')  # truncated
    res = runner.invoke(app, ["relight", str(session), "--pattern", "white", *args])
    assert res.exit_code != 0 and "sources.json cannot be read" in str(res.exception)


def test_objects_whose_output_names_can_coincide_are_refused_one_out(session, tmp_path):
    """Outputs are OBJECT_v<view>_PATTERN_BACKEND: objects a and a_v0_b relit under the patterns b_v0_c and c wrote
    the same file into one --out, the second replacing the first without a word."""
    import json
    import shutil

    from sssphase_core.errors import InputError

    twin = tmp_path / "others" / f"{session.name}_v1_white"
    shutil.copytree(session, twin)
    manifest = json.loads((twin / "manifest.json").read_text())
    (twin / "manifest.json").write_text(json.dumps({**manifest, "object": twin.name}))
    out = tmp_path / "o"
    args = ["--views", "1", "--backend", "none", "--out", str(out)]
    assert runner.invoke(app, ["relight", str(session), "--pattern", "white", *args]).exit_code == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    res = runner.invoke(app, ["relight", str(twin), "--pattern", "black", *args])
    assert isinstance(res.exception, InputError), res.output
    assert f"objects '{session.name}' and '{twin.name}', whose file names" in str(res.exception)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert runner.invoke(app, ["relight", str(twin), "--pattern", "black", *args[:-1], str(tmp_path / "o2")]).exit_code == 0


def test_a_pattern_whose_name_cannot_make_a_file_name_is_refused_before_the_relighting(session, tmp_path):
    """A 250-character pattern file name passed every check and failed when its relit image was written, after the
    footprints ("could not write ... is the name too long")."""
    from PIL import Image

    from sssphase_core.errors import InputError

    long = tmp_path / ("p" * 240 + ".png")
    Image.fromarray(np.zeros((192, 256), np.uint8)).save(long)
    res = runner.invoke(app, ["relight", str(session), "--pattern", str(long), "--views", "1", "--backend", "none",
                              "--out", str(tmp_path / "o")])
    assert isinstance(res.exception, InputError), res.output
    assert "makes its output file names longer than a file name may be (255 bytes)" in str(res.exception)
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").rglob("*.png"))


def test_several_backends_are_relit_in_one_command_and_a_bad_name_is_refused_before_any(session, tmp_path):
    out = tmp_path / "relit"
    res = runner.invoke(app, ["relight", str(session), "--pattern", "checkerboard", "--views", "1",
                              "--backend", "none,exact", "--out", str(out)])
    assert res.exit_code == 0, res.output
    relit = {b: (out / f"sand_rake_v1_checkerboard_{b}.png") for b in ("none", "exact")}
    assert all(f.exists() for f in relit.values())
    assert relit["none"].read_bytes() != relit["exact"].read_bytes()
    assert res.output.count("PSNR") == 2  # each scored against the view's reference
    res = runner.invoke(app, ["relight", str(session), "--pattern", "checkerboard", "--views", "1", "--backend",
                              "none,exact", "--checkpoint", str(tmp_path / "unused.pt"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "not used" not in res.output  # listed with others, a backend without the decoder is not told so
    for backend, said in (("none,bogus", "unknown backend 'bogus'"), ("auto,none", "--backend auto chooses one backend"),
                          ("none,torch", "torch backend needs --checkpoint")):
        bad = tmp_path / backend.replace(",", "_")
        res = runner.invoke(app, ["relight", str(session), "--pattern", "checkerboard", "--backend", backend, "--out", str(bad)])
        assert res.exit_code != 0 and said in str(res.exception), (backend, res.exception)
        assert not bad.exists() or not any(bad.rglob("*.png"))  # nothing relit before the refusal


def test_the_calibration_widens_footprints_that_are_too_narrow_when_told_to(session):
    """`relight_view(widen=S)`: each model's footprints, stretched S times along x and apart along y in the same pass,
    join the fit, so the view's fringes can widen a model, not only narrow it toward no scattering. The exact footprints made too narrow relight
    the sand rake closer to its render with it; the mix returned is still one row per source; the factor is checked."""
    import torch

    from sssphase_core.errors import InputError
    from sssphase_core.relight import make_source, relight_view
    from sssphase_core.relight.engine import widened

    rv = load_view(Session.open(session), 1)
    exact, k = make_source("exact", rv)
    calls = []

    def narrow(pixels):
        calls.append(len(pixels))
        return widened(torch.as_tensor(np.asarray(exact(pixels), np.float32)), 0.5)

    pats = [rv.references["checkerboard"], rv.references["stripes_x"]]
    truth = [rv.captured["checkerboard"], rv.captured["stripes_x"]]
    one_sided, mix = relight_view(narrow, k, rv, pats, calibrate=True)
    calls.clear()
    two_sided, mix2 = relight_view(narrow, k, rv, pats, calibrate=True, widen=2.0)
    assert sum(calls) <= rv.proj.mask.sum()  # the stretched members are splatted from the same footprints
    assert mix.shape == mix2.shape == (3,) and (mix2 > 0).all()
    score = lambda imgs: np.mean([relight_metrics(i, t, rv.proj.mask)["psnr"] for i, t in zip(imgs, truth, strict=True)])  # noqa: E731
    assert score(two_sided) > score(one_sided) + 0.5
    for bad in (1.0, 0.8, 5.0):
        with pytest.raises(InputError, match="widen"):
            relight_view(narrow, k, rv, pats, calibrate=True, widen=bad)


def test_relight_with_widen_says_so_and_keeps_eigen_footprints_of_its_own_calibration(session, tmp_path):
    """`sss relight --widen S`: one line says the calibration may widen the footprints; the eigen-footprints of a
    relight without it are not used with it; a widened relight keeps its own (named with the stretch), from which the
    next pattern is relit close to the full widened relight; `--widen 1` is the plain calibration (the analytic
    model's default: the decoder's is in test_relight_runner); a stretch below 1 is one line."""
    from sssphase_core.store.exr import read_exr

    base = ["relight", str(session), "--views", "1", "--backend", "analytic", "--format", "exr"]
    plain = runner.invoke(app, [*base, "--pattern", "checkerboard", "--out", str(tmp_path)])
    assert plain.exit_code == 0, plain.output
    assert list((tmp_path / "cache").glob("*_lowrank.npz")) and "stretched" not in plain.output
    first = read_exr(tmp_path / "sand_rake_v1_checkerboard_analytic.exr")
    wide = runner.invoke(app, [*base, "--pattern", "checkerboard", "--out", str(tmp_path), "--widen", "1.5"])
    assert wide.exit_code == 0, wide.output
    assert "stretched 1.5 x" in wide.output and "eigen-footprints" not in wide.output  # not relit from the plain cache
    assert np.abs(read_exr(tmp_path / "sand_rake_v1_checkerboard_analytic.exr") - first).max() > 1e-4
    assert len(list((tmp_path / "cache").glob("*_analytic_*_w1.5_lowrank.npz"))) == 1
    again = runner.invoke(app, [*base, "--pattern", "stripes_x", "--out", str(tmp_path), "--widen", "1.5"])
    assert again.exit_code == 0 and "relit from its cached eigen-footprints" in again.output, again.output
    told = [line for out in (wide.output, again.output) for line in out.splitlines() if "calibrated to the view" in line]
    assert len(told) == 2 and told[0] == told[1] and "(stretched along x " in told[0]  # how x and y split, cached or not
    full = runner.invoke(app, [*base, "--pattern", "stripes_x", "--out", str(tmp_path / "full"), "--widen", "1.5", "--no-cache"])
    assert full.exit_code == 0, full.output
    x, y = (read_exr(d / "sand_rake_v1_stripes_x_analytic.exr") for d in (tmp_path, tmp_path / "full"))
    assert 10 * np.log10(y.max() ** 2 / np.mean((x - y) ** 2)) > 55  # PSNR at the image's peak
    off = runner.invoke(app, [*base, "--pattern", "checkerboard", "--out", str(tmp_path), "--widen", "1"])
    assert off.exit_code == 0 and "stretched" not in off.output and "eigen-footprints" in off.output, off.output
    x = read_exr(tmp_path / "sand_rake_v1_checkerboard_analytic.exr")  # from the plain relight's eigen-footprints
    assert 10 * np.log10(first.max() ** 2 / np.mean((x - first) ** 2)) > 55
    for value in ("0.9", "nan", "4.0000001"):  # NaN is refused as what it is, not as a number above 4; 4.0000001 as such
        bad = runner.invoke(app, [*base, "--pattern", "checkerboard", "--out", str(tmp_path), "--widen", value])
        assert bad.exit_code != 0 and f"{value} is not a stretch from 1 to 4" in bad.output and "Traceback" not in bad.output


def test_a_cache_the_file_system_refuses_costs_its_time_not_the_images(session, tmp_path):
    """`OUT/cache` that cannot be written (here a file where its folder goes; a full disk alike) was one raw OS error
    after the work, and no image: the images are written, and one line per cache file says it was not kept."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "cache").write_text("a file where the cache folder goes")
    res = runner.invoke(app, ["relight", str(session), "--views", "1", "--pattern", "checkerboard", "--backend", "analytic",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "sand_rake_v1_checkerboard_analytic.png").is_file()
    assert res.output.count("was not kept") == 2 and "--no-cache keeps none" in res.output  # the footprints, the eigen-footprints
    assert (out / "cache").read_text() == "a file where the cache folder goes"


def test_eval_relight_says_when_it_scores_views_the_decoder_was_trained_on(session, tmp_path):
    """A decoder scored on the views it was fitted on read as relighting of unseen objects, without a word. (With
    --no-calibrate the decoder itself was an internal error: the calibration's --widen was passed to the backend.)"""
    import torch

    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint

    preset = get_preset("lite")
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "dec.pt", {"kind": "decoder", "preset": preset.to_dict(), "config": {"head": "reciprocal"},
                                          "encoder": Encoder(preset).state_dict(),
                                          "decoder": Decoder(preset, head="reciprocal").state_dict(),
                                          "trained_on": {"sand_rake": [1], "apple": [0, 1]}})
    res = runner.invoke(app, ["eval", "relight", str(session), "--views", "1", "--backend", "torch", "--checkpoint",
                              str(tmp_path / "dec.pt"), "--no-calibrate", "--out", str(tmp_path / "e")])
    assert res.exit_code == 0, res.output
    said = "the decoder was trained on sand_rake view 1: the torch and blend figures there measure how it fits"
    assert said in res.output and said in (tmp_path / "e" / "relight_eval.md").read_text()
    assert said in json.loads((tmp_path / "e" / "relight_eval.json").read_text())["training_overlap"]
    for extra, said in ((["--backend", "blend"], "--no-calibrate: blend weights its members by the view calibration"),
                        (["--backend", "torch", "--widen", "1.5"], "--widen 1.5 stretches footprints within the view "
                                                                      "calibration, which --no-calibrate turns off")):
        res = runner.invoke(app, ["eval", "relight", str(session), "--views", "1", *extra, "--checkpoint",
                                  str(tmp_path / "dec.pt"), "--no-calibrate", "--out", str(tmp_path / "refused")])
        assert res.exit_code != 0 and said in str(res.exception), res.output  # before any work (a blend: at its view)
        assert not (tmp_path / "refused").exists()


def test_the_decoder_infers_in_the_precision_asked_each_with_its_own_cache(session, tmp_path):
    """bf16 inference (``auto`` where the device computes it natively) against float32: the footprints differ by
    bf16's rounding, the relit images by far less than a hundredth of a dB, and neither run reads the other's cache."""
    import dataclasses

    import torch

    from sssphase_core.learning.models import Decoder, Encoder, get_preset
    from sssphase_core.learning.training import save_checkpoint

    preset = dataclasses.replace(get_preset("lite"), name="lite-small", stem=8, stages=(8, 12, 16), bottleneck=32,
                                 proj_hidden=32, proj_dim=32, pred_hidden=8, decoder=(16, 12, 8, 8), attention=4)
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "dec.pt", {"kind": "decoder", "preset": preset.to_dict(), "config": {"head": "direct"},
                                          "encoder": Encoder(preset).state_dict(),
                                          "decoder": Decoder(preset, head="direct").state_dict()})
    rows = {}
    for precision in ("bf16", "fp32"):
        res = runner.invoke(app, ["eval", "relight", str(session), "--views", "1", "--backend", "torch", "--checkpoint",
                                  str(tmp_path / "dec.pt"), "--out", str(tmp_path / "e"), "--precision", precision,
                                  "--no-calibrate"])  # (the model's own footprints: what the precision changes)
        assert res.exit_code == 0 and f"({precision} inference)" in res.output, res.output
        rows[precision] = json.loads((tmp_path / "e" / "relight_eval.json").read_text())["rows"]
        assert {r["precision"] for r in rows[precision]} == {precision}
    caches = sorted((tmp_path / "e" / "cache").glob("sand_rake_v1_*_torch_*.npz"))
    assert [p.name.endswith("_bf16.npz") for p in caches] == [False, True], caches
    fp32, bf16 = (np.load(p)["data"].astype(np.float32) for p in caches)
    assert 0 < np.abs(bf16 - fp32).mean() < 0.02 * np.abs(fp32).mean()  # computed again, not read from the bf16 cache
    for a, b in zip(rows["bf16"], rows["fp32"], strict=True):
        assert abs(a["psnr"] - b["psnr"]) < 0.01, (a["psnr"], b["psnr"])
    res = runner.invoke(app, ["eval", "relight", str(session), "--backend", "torch", "--checkpoint", str(tmp_path / "dec.pt"),
                              "--precision", "fp16", "--out", str(tmp_path / "half")])
    assert res.exit_code != 0 and "unknown precision 'fp16': use auto, fp32, bf16" in str(res.exception), res.output
    assert not (tmp_path / "half").exists()
