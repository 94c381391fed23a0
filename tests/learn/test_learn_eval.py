"""kNN view-level leave-one-out, footprint metrics, PCA-RGB, plots."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.learning.evaluation import (
    embed_pixels,
    footprint_metrics,
    knn_leave_one_view_out,
    knn_predict,
    paint,
    pca_rgb,
    summarise,
)
from sssphase_core.learning.models import Encoder
from sssphase_core.reporting.figures import plot_metric_vs_time, plot_profiles


def clusters(n: int = 400, d: int = 8, noise: float = 0.3, seed: int = 0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(3, d))
    labels = rng.integers(0, 3, n)
    views = rng.integers(0, 4, n)
    return centres[labels] + noise * rng.normal(size=(n, d)), labels, views


def test_knn_separable_clusters_are_classified():
    emb, labels, views = clusters()
    for vote in ("majority", "weighted"):
        res = knn_leave_one_view_out(emb, labels, views, k=5, vote=vote, class_names=["x", "y", "z"])
        assert res["overall"] == 1.0 and res["mean_per_view"] == 1.0
        assert set(res["per_class"]) == {"x", "y", "z"} and set(res["per_view"]) == {0, 1, 2, 3}


def test_knn_never_uses_patches_of_the_held_out_view():
    # each view's patches sit on their own point; only another view's points carry the true label
    emb = np.repeat(np.eye(4), 10, axis=0)
    views = np.repeat(np.arange(4), 10)
    labels = views % 2
    res = knn_leave_one_view_out(emb + 1e-3, labels, views, k=3)
    # same-view neighbours would give 100 %; cross-view neighbours are orthogonal (ties) -> not perfect
    assert res["overall"] < 1.0


def test_an_object_seen_in_one_view_is_left_out_of_the_scores_not_counted_wrong():
    # z is only in view 0: leaving view 0 out leaves no z to match, whatever the embedding
    emb, labels, views = clusters()
    views = np.where(labels == 2, 0, views)
    res = knn_leave_one_view_out(emb, labels, views, k=5, class_names=["x", "y", "z"])
    assert res["unscored"] == {"z": int((labels == 2).sum())} and set(res["per_class"]) == {"x", "y"}
    assert res["overall"] == 1.0 and res["mean_per_view"] == 1.0  # z's patches neither counted wrong nor right
    for one_view_each in (labels, np.where(labels == 2, views, labels)):  # no class, or one, in two or more views
        with pytest.raises(InputError, match="scores only classes seen in two or more views and needs two"):
            knn_leave_one_view_out(emb, labels, one_view_each, k=5)


def test_overall_and_mean_per_view_accuracy_differ_with_unequal_views():
    emb, labels, views = clusters(noise=2.0, seed=1)
    views = np.where(np.arange(len(views)) < 40, 0, 1 + views % 3)
    res = knn_leave_one_view_out(emb, labels, views, k=7)
    pv = res["per_view"]
    counts = {v: int((views == v).sum()) for v in pv}
    assert res["mean_per_view"] == pytest.approx(np.mean(list(pv.values())))
    assert res["overall"] == pytest.approx(sum(pv[v] * counts[v] for v in pv) / len(views))


def test_weighted_vote_prefers_closer_neighbours():
    db = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.6, 0.8]]), dim=1)
    q = torch.tensor([[1.0, 0.0]])
    labels = torch.tensor([0, 1, 1])
    assert knn_predict(q, db, labels, 2, 3, "majority").item() == 1
    assert knn_predict(q, db, labels, 2, 3, "weighted").item() == 0
    with pytest.raises(InputError):
        knn_predict(q, db, labels, 2, 3, "median")


def test_footprint_metrics():
    rng = np.random.default_rng(0)
    gt = 0.04 * rng.random((6, 16, 16, 3)).astype(np.float32)
    same = footprint_metrics(gt, gt)
    assert np.allclose(same["ssim"], 1, atol=1e-4) and (same["psnr"] > 150).all()
    noisy = footprint_metrics(gt + 0.004 * rng.standard_normal(gt.shape).astype(np.float32), gt)
    s = summarise(noisy)
    assert s["psnr"] == pytest.approx(10 * np.log10(1 / 0.004**2), abs=0.3)
    assert s["ssim"] < s["ssim_r1"]  # data range 1 is nearly blind to footprint-level errors


def test_pca_rgb_is_joint_and_in_range():
    emb, labels, _ = clusters()
    a, b = pca_rgb([emb[:150], emb[150:]])
    assert a.shape == (150, 3) and b.shape == (250, 3)
    assert 0 <= min(a.min(), b.min()) and max(a.max(), b.max()) <= 1
    # same cluster -> similar colour, different clusters -> different colours
    allc = np.concatenate([a, b])
    means = np.stack([allc[labels == c].mean(0) for c in range(3)])
    spread = max(allc[labels == c].std(0).max() for c in range(3))
    assert min(np.linalg.norm(means[i] - means[j]) for i in range(3) for j in range(i)) > 2 * spread
    img = paint((4, 5), np.array([[1, 2]]), np.array([[0.1, 0.2, 0.3]]))
    assert img[1, 2].tolist() == pytest.approx([0.1, 0.2, 0.3]) and img.sum() == pytest.approx(0.6)


def test_embed_pixels_matches_a_direct_forward(tiny, synthetic):
    enc = Encoder(tiny).eval()
    v = synthetic[0][0]
    emb = embed_pixels(enc, v.psp, v.pixels[:10], batch_size=4)
    from sssphase_core.learning.data import psp_patches

    with torch.no_grad():
        direct = enc(torch.as_tensor(psp_patches(v.psp, v.pixels[:10], 16))).numpy()
    assert emb.shape == (10, tiny.embed_dim) and np.allclose(emb, direct, atol=1e-5)


def test_plots_are_written(tmp_path):
    gt = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    plot_profiles(gt, gt * 0.9, tmp_path / "p.png")
    (tmp_path / "m.jsonl").write_text('{"wall_s": 1, "val_mse": 0.1}\n{"wall_s": 2, "val_mse": 0.05}\n')
    plot_metric_vs_time(tmp_path / "m.jsonl", "val_mse", tmp_path / "t.png")
    assert (tmp_path / "p.png").stat().st_size > 1000 and (tmp_path / "t.png").stat().st_size > 1000
    with pytest.raises(InputError):
        plot_metric_vs_time(tmp_path / "m.jsonl", "missing", tmp_path / "x.png")


def test_a_validation_psnr_that_hardly_moves_is_not_drawn_corner_to_corner(tmp_path, monkeypatch):
    """The decoder's run plot drew a change of 0.014 dB as a steep diagonal across the whole figure."""
    from sssphase_core.reporting import figures

    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, out, dpi=100: drawn.append(fig))
    (tmp_path / "m.jsonl").write_text('{"wall_s": 1, "loss": 0.3, "val_psnr": 58.942}\n'
                                      '{"wall_s": 2, "loss": 0.2, "val_psnr": 58.928}\n')
    figures.plot_metric_vs_time(tmp_path / "m.jsonl", "loss", tmp_path / "t.png", right=("val_psnr",), right_span=1.0)
    figures.plot_metric_vs_time(tmp_path / "m.jsonl", "loss", tmp_path / "t.png", right=("val_psnr",))
    spanned, free = (fig.axes[1].get_ylim() for fig in drawn)
    assert spanned[1] - spanned[0] == pytest.approx(1.0) and spanned[0] < 58.928 < 58.942 < spanned[1]
    assert free[1] - free[0] < 0.1  # (without it: matplotlib's own margins)


def test_throughput_measure_reports_rates_and_sizes():
    from sssphase_core.bench.learn_bench import measure_throughput

    r = measure_throughput("lite", batch=2, repeats=1)
    assert r["infer_patches_s"] > 0 and r["train_patches_s"] > 0
    assert r["encoder_params"] > r["decoder_params"] > 0


def test_knn_of_views_is_the_leave_one_view_out_table_of_every_pixel(synthetic, tiny):
    """The one function the CLI and the demo share: embeddings of every pixel of every view, labelled by
    object (or material) and held out by view."""
    from sssphase_core.learning.evaluation import knn_of_views

    views = synthetic[0]
    torch.manual_seed(0)
    enc = Encoder(tiny).eval()
    emb = np.concatenate([embed_pixels(enc, v.psp, v.pixels) for v in views])
    objects = np.concatenate([np.full(len(v.pixels), ["a", "b"].index(v.object)) for v in views])
    held = np.concatenate([np.full(len(v.pixels), v.view) for v in views])
    got = knn_of_views(enc, views, ["a", "b"], ks=(3, 7))
    for k in (3, 7):
        want = knn_leave_one_view_out(emb, objects, held, k=k, class_names=["a", "b"])
        assert got[k]["overall"] == pytest.approx(want["overall"]) and got[k]["per_class"] == want["per_class"]
        assert "pred" not in got[k]
    materials = knn_of_views(enc, views, ["a", "b"], label="material", material_names=["m0", "m1", "m2", "m3"])[20]
    assert set(materials["per_class"]) <= {"m0", "m1", "m2", "m3"} and 0 <= materials["overall"] <= 1
    with pytest.raises(InputError, match="object or material"):
        knn_of_views(enc, views, ["a", "b"], label="view")
    from dataclasses import replace

    from sssphase_core.errors import DataError

    damaged = [replace(views[0], materials=np.full(len(views[0].pixels), 30000)), *views[1:]]  # was an IndexError
    with pytest.raises(DataError, match=r"material labels \(gt/labels\) of a reach 30000, past the 4 known materials"):
        knn_of_views(enc, damaged, ["a", "b"], label="material", material_names=["m0", "m1", "m2", "m3"])


def test_knn_and_footprint_tables_are_built_in_core():
    from sssphase_core.learning.evaluation import footprint_table, knn_tables

    run = {"per_class": {"apple": 0.5, "star": 1.0}, "overall": 0.75, "mean_per_view": 0.7, "overall_by_k": {5: 0.75, 1: 0.8}}
    other = {**run, "per_class": {"apple": 0.25}, "overall": 0.125}
    main, by_k = knn_tables({"psp": run, "imagenet": other}, label="object", ks=[5, 1], vote="majority", views="0,1")
    assert main.columns == ["Object", "psp", "imagenet"]
    assert main.rows[0] == ["apple", "50.00", "25.00"] and main.rows[1][2] == "n/a"  # star unseen by the second run
    assert not main.note
    one_view = knn_tables({"psp": {**run, "unscored": {"soap": 40}}}, label="object", ks=[5], vote="majority", views="0,1")[0]
    assert one_view.rows[1] == ["soap", "n/a"] and "soap in one view only" in one_view.note
    assert main.rows[2] == ["**overall**", "75.00", "12.50"] and by_k.rows == [[5, "75.00", "75.00"], [1, "80.00", "80.00"]]
    assert knn_tables({"psp": run}, label="material", ks=[5], vote="weighted", views="0")[0].columns[0] == "Material"
    res = {"soap": {"torch": {"mse": 2e-5, "psnr": 47.0, "ssim": 0.9912}, "analytic": {"mse": 1e-4, "psnr": 40.0, "ssim": 0.5}}}
    table = footprint_table(res, views="0", note="n")
    assert table.columns[:4] == ["Object", "torch MSE×1e-5", "torch PSNR", "torch SSIM"] and len(table.columns) == 7
    assert table.rows == [["soap", "2.00", "47.00", "0.991", "10.00", "40.00", "0.500"]]
    assert "| soap | 2.00 |" in table.markdown()
