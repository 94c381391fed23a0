"""Patch extraction, datasets, splits and deterministic sampling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sssphase_core.bench.synthetic import synthetic_views
from sssphase_core.errors import DataError, InputError
from sssphase_core.learning.data import (
    PatchDataset,
    ViewData,
    crop_patches,
    psp_patches,
    sample_pixels,
    split_by_object,
    split_by_view,
)


def test_crop_centres_the_pixel_and_zero_pads_outside():
    stack = torch.arange(2 * 5 * 6, dtype=torch.float32).view(2, 5, 6) + 1
    patches = crop_patches(stack, np.array([[2, 3], [0, 0]]), 4)
    assert patches.shape == (2, 2, 4, 4)
    assert torch.equal(patches[0, :, 2, 2], stack[:, 2, 3])
    assert torch.equal(patches[0, :, 0, 0], stack[:, 0, 1])
    assert torch.equal(patches[1, :, 2, 2], stack[:, 0, 0])
    assert (patches[1, :, :2, :] == 0).all() and (patches[1, :, :, :2] == 0).all()


def test_patch_channel_order_is_image_times_three_plus_colour():
    psp = np.zeros((8, 5, 5, 3), np.float32)
    for i in range(8):
        for c in range(3):
            psp[i, ..., c] = 10 * i + c
    p = psp_patches(psp, np.array([[2, 2]]), 3)
    assert p[0, :, 1, 1].tolist() == [10 * i + c for i in range(8) for c in range(3)]


def test_dataset_items_labels_and_targets(synthetic, dataset):
    views, kernels = synthetic
    assert len(dataset) == sum(len(v.pixels) for v in views)
    b = dataset.batch(np.array([0, len(dataset) - 1]))
    assert b["psp"].shape == (2, 24, 16, 16) and b["footprint"].shape == (2, 3, 16, 16)
    assert b["object"].tolist() == [0, 1] and b["view"].tolist() == [0, 1]
    assert torch.allclose(b["footprint"][1], torch.as_tensor(kernels["b"]).permute(2, 0, 1))
    item = dataset[3]
    assert item["psp"].shape == (24, 16, 16) and item["object"].ndim == 0
    assert set(np.unique(dataset.labels("view"))) == {0, 1}


def test_dataset_rejects_missing_footprints_and_unknown_classes(synthetic):
    views, _ = synthetic
    bare = [ViewData(v.object, v.view, v.psp, v.pixels, v.materials) for v in views]
    with pytest.raises(DataError, match="footprints"):
        PatchDataset(bare, 16, ["a", "b"], with_targets=True)
    with pytest.raises(InputError, match="classes"):
        PatchDataset(bare, 16, ["a"])
    with pytest.raises(DataError, match="8, H, W, 3"):
        ViewData("x", 0, np.zeros((4, 5, 5, 3), np.float32), np.zeros((0, 2), int), np.zeros(0, int))
    with pytest.raises(InputError, match="are 16x16 but this decoder predicts 32x32"):  # crops of another size
        PatchDataset(views, 32, ["a", "b"], with_targets=True)


def test_splits_by_object_and_by_view(synthetic):
    views, _ = synthetic
    train, test = split_by_object(views, ["b"])
    assert {v.object for v in train} == {"a"} and {v.object for v in test} == {"b"}
    train, test = split_by_view(views, [1])
    assert {v.view for v in train} == {0} and {v.view for v in test} == {1}


def test_sampling_is_deterministic_and_seed_dependent():
    mask = np.random.default_rng(0).random((40, 40)) > 0.3
    a, b, c = sample_pixels(mask, 50, 1), sample_pixels(mask, 50, 1), sample_pixels(mask, 50, 2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert mask[a[:, 0], a[:, 1]].all()
    v1, _ = synthetic_views(("a",), (0,), pixels_per_view=10, seed=3)
    v2, _ = synthetic_views(("a",), (0,), pixels_per_view=10, seed=3)
    assert np.array_equal(v1[0].psp, v2[0].psp) and np.array_equal(v1[0].pixels, v2[0].pixels)


def test_footprints_are_read_lazily_from_chunked_arrays(synthetic, tmp_path):
    zarr = pytest.importorskip("zarr")
    v = synthetic[0][0]
    z = zarr.open_array(tmp_path / "fp.zarr", mode="w", shape=np.asarray(v.footprints).shape, chunks=(8, 16, 16, 3), dtype="f4")
    z[:] = np.asarray(v.footprints)
    ds = PatchDataset([ViewData(v.object, v.view, v.psp, v.pixels, v.materials, z)], 16, ["a"], with_targets=True)
    idx = np.array([5, 1, 30])
    assert np.allclose(ds.batch(idx)["footprint"].numpy(), np.asarray(v.footprints)[idx].transpose(0, 3, 1, 2))


def test_each_session_holds_out_its_last_view_when_it_has_two_or_more(one_and_three_sessions, synthetic, tmp_path):
    from sssphase_core.learning.data import held_out_split, session_views

    one_and_three_sessions(tmp_path)
    train, val = held_out_split(tmp_path)
    assert train == {"one": [0], "three": [0, 2]} and val == {"one": [], "three": [5]}
    assert held_out_split(tmp_path, ["three"]) == ({"three": [0, 2]}, {"three": [5]})
    got = session_views(tmp_path, views=train, pixels_per_view=5)  # views per object
    assert [(d.object, d.view) for d in got] == [("one", 0), ("three", 0), ("three", 2)]
    assert [(d.object, d.view) for d in session_views(tmp_path, views=val, pixels_per_view=5)] == [("three", 5)]


def test_session_views_stream_footprints_from_the_store(synthetic, tmp_path, monkeypatch):
    session = pytest.importorskip("sssphase_core.store.session")
    v = synthetic[0][0]
    s = session.Session.create(tmp_path, "obj")
    w = s.begin_view(0)
    mask = np.zeros(v.psp.shape[1:3], bool)
    mask[v.pixels[:, 0], v.pixels[:, 1]] = True
    w.write("psp", v.psp)
    w.write("corr/mask", mask)
    w.write("footprints/pixels", v.pixels.astype(np.int32))
    w.write("footprints/crops", np.asarray(v.footprints) * np.arange(1, len(v.pixels) + 1)[:, None, None, None])
    w.commit()
    from sssphase_core.learning.data import session_views

    (vd,) = session_views(tmp_path, footprints=True, pixels_per_view=20, seed=0)
    assert vd.object == "obj" and len(vd.pixels) == 20 and (vd.materials == -1).all()
    ds = PatchDataset([vd], 16, ["obj"], with_targets=True)
    b = ds.batch(np.array([3, 0]))
    rows = [int(np.flatnonzero((v.pixels == vd.pixels[i]).all(1))[0]) for i in (3, 0)]
    expect = np.asarray(v.footprints)[rows] * (np.array(rows) + 1)[:, None, None, None]
    assert np.allclose(b["footprint"].numpy(), expect.transpose(0, 3, 1, 2))
    assert isinstance(vd.footprints, np.ndarray)  # a few rows: read once, not whole chunks per batch
    import sssphase_core.learning.data as data

    monkeypatch.setattr(data, "ROWS_IN_MEMORY_BYTES", 0)  # a paper-scale view: rows stay in the store
    (lazy,) = session_views(tmp_path, footprints=True, pixels_per_view=20, seed=0)
    assert isinstance(lazy.footprints, data.Rows)
    lazy_batch = PatchDataset([lazy], 16, ["obj"], with_targets=True).batch(np.array([3, 0]))
    assert torch.equal(lazy_batch["footprint"], b["footprint"])
    assert (b["camera"] == -1).all()  # no camera record, no correspondences: crops as they are, each its own pixel's
    assert torch.equal(b["dot"].sum(dim=(1, 2)), torch.ones(2)) and torch.equal(b["dot"][:, 3, 3], torch.ones(2))
    (plain,) = session_views(tmp_path, pixels_per_view=None)
    assert len(plain.pixels) == mask.sum() and plain.footprints is None
    # a run's steps read the same views: with a cache the PSP stack is read (repaired, checked) once for all of them
    reads = []
    monkeypatch.setattr(data, "repaired_psp", lambda s, view: reads.append(view) or np.asarray(s.load(view, "psp")))
    cache: dict = {}
    (first,) = session_views(tmp_path, pixels_per_view=20, seed=0, psp_cache=cache)
    (again,) = session_views(tmp_path, footprints=True, pixels_per_view=20, seed=0, psp_cache=cache)
    assert reads == [0] and again.psp is first.psp and np.array_equal(first.psp, plain.psp)
    assert again.footprints is not None and np.array_equal(again.pixels, lazy.pixels)
    with pytest.raises(DataError, match="no session"):
        session_views(tmp_path, ["apple"])


def test_footprint_batches_say_how_each_crop_was_recorded(synthetic, tmp_path):
    """A captured view's crops come with their camera (Bayer phase of each crop) and the camera pixels each one's dot
    lit, read from the view's correspondences: what decoder training passes its predictions through."""
    from sssphase_core.learning.camera import crop_codes
    from sssphase_core.learning.data import session_views
    from sssphase_core.processing.footprints import dot_kernels
    from sssphase_core.store.session import Session

    v = synthetic[0][0]
    h, w = v.psp.shape[1:3]
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    xp, yp = 1.2 * xx + 0.3, 0.9 * yy - 0.4
    s = Session.create(tmp_path, "obj")
    wr = s.begin_view(0)
    for name, arr in (("psp", v.psp), ("corr/mask", np.ones((h, w), bool)), ("corr/xp", xp), ("corr/yp", yp),
                      ("footprints/pixels", v.pixels.astype(np.int32)), ("footprints/crops", np.asarray(v.footprints))):
        wr.write(name, arr)
    isp_record = {"bayer": "GRBG", "demosaic": "opencv", "median": True}
    wr.commit({"camera_isp": isp_record})
    (vd,) = session_views(tmp_path, footprints=True, pixels_per_view=12, seed=0)
    assert vd.isp == isp_record
    b = PatchDataset([vd], 16, ["obj"], with_targets=True).batch(np.arange(12))
    np.testing.assert_array_equal(b["camera"].numpy(), crop_codes(isp_record, vd.pixels, 16))
    np.testing.assert_allclose(b["dot"].numpy(), dot_kernels(xp, yp, np.ones((h, w), bool), vd.pixels), atol=1e-6)
    assert b["dot"][:, 3, 3].max() < 0.9  # off-integer correspondences: the dots light pixels beside the crop's own


def test_a_stack_padded_once_gives_the_same_patches():
    from sssphase_core.learning.data import crop_patches, pad_for_patches

    stack = torch.rand(24, 17, 23)
    pixels = np.array([[0, 0], [16, 22], [8, 11], [3, 20]])
    for k in (4, 5, 9):
        np.testing.assert_array_equal(crop_patches(pad_for_patches(stack, k), pixels, k, padded=True).numpy(),
                                      crop_patches(stack, pixels, k).numpy())


def test_training_refuses_two_sessions_of_one_object(tmp_path):
    """Views are keyed by object name: a second session of the same object would be dropped without a word."""
    from sssphase_core.learning.data import session_views
    from sssphase_core.store.session import Session

    (tmp_path / "all").mkdir()
    for day in ("day1", "day2"):  # the same object captured twice, the second folder renamed by the user
        Session.create(tmp_path / day, "wax").path.rename(tmp_path / "all" / f"wax_{day}")
    with pytest.raises(InputError, match="two sessions hold the object 'wax'.*training would read one of them only"):
        session_views(tmp_path / "all")


@pytest.mark.parametrize("damage", ["fewer crops", "pixels outside"])
def test_validate_names_footprint_crops_that_do_not_match_their_pixels(one_and_three_sessions, tmp_path, damage):
    """Intact arrays (checksums as written) whose crops and pixels disagree: training refused them as 'damaged
    (index out of bounds ...); `sss validate` lists the damage' while `sss validate` said ok."""
    from sssphase_core.store.session import Session

    one_and_three_sessions(tmp_path, footprints=True)
    s = Session.open(tmp_path / "one")
    data = {name: np.array(s.load(0, name)) for name in s.arrays(0)}
    if damage == "fewer crops":
        data["footprints/crops"] = data["footprints/crops"][:10]
    else:
        data["footprints/pixels"][0] = (-1, 5)
    writer = s.begin_view(0)
    for name, array in data.items():
        writer.write(name, array)
    writer.commit()
    problems = Session.open(tmp_path / "one").validate()
    n = len(data["footprints/pixels"])
    expected = (f"view 0: array footprints/crops holds 10 crops for {n} footprint pixels" if damage == "fewer crops"
                else "view 0: array footprints/pixels holds pixels outside the 48x48 image")
    assert [p for p in problems if "required array" not in p and "capture plan" not in p
            and "rig record" not in p] == [expected], problems  # (synthetic:
    # no white, no plan, ...)
