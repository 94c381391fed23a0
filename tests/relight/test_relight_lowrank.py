"""Eigen-footprints (relight.lowrank): a view's footprints as a few basis images per colour, so that a new
pattern is relit by r filters instead of a splat of every footprint; and `sss relight`'s fast path on them."""

import numpy as np
import pytest

from sssphase_core.relight import relight
from sssphase_core.relight.lowrank import LowRankFootprints, LowRankTap, fit_basis, load_lowrank, save_lowrank

K = 9


def _rank3_source(proj, seed=0):
    """Footprints that are per-pixel mixtures of three Gaussian images per colour (rank 3), off-centre ones
    too (a mirrored kernel would show), seeded per pixel so that every call gives the same ones."""
    d = np.arange(K) - K // 2
    yy, xx = np.meshgrid(d, d, indexing="ij")
    bases = np.stack([np.exp(-(xx**2 + yy**2) / 2.0), np.exp(-((xx - 2) ** 2 + yy**2) / 4.0),
                      np.exp(-(xx**2 + (yy + 1) ** 2) / 9.0)]).astype(np.float32)
    width = proj.mask.shape[1]

    def source(pixels):
        flat = pixels[:, 0] * width + pixels[:, 1]
        a = np.stack([np.random.default_rng([seed, int(f)]).random((3, 3)) for f in flat]).astype(np.float32)  # (n, colour, basis)
        return np.einsum("ncb,byx->nyxc", a, bases) * np.float32(0.01)

    return source


def _tapped_view(make_projection, seed):
    """A toy view with rank-3 footprints, a tap on them over every decoded pixel, two random patterns and a white."""
    proj = make_projection(black=0.002)
    source = _rank3_source(proj)
    valid = np.argwhere(proj.mask)
    rng = np.random.default_rng(seed)
    patterns = rng.random((2, 50, 60)).astype(np.float32)
    white = rng.random((*proj.mask.shape, 3)).astype(np.float32)
    return proj, source, valid, LowRankTap(source, valid, proj.mask.shape, sample=64), patterns, white


def test_relit_from_eigen_footprints_equals_the_splat_when_they_span_the_footprints(tmp_path, make_projection):
    proj, source, valid, tap, patterns, white = _tapped_view(make_projection, seed=1)
    direct = relight(tap, proj, patterns, K, white=white)  # the pass collects every lit pixel's coefficients
    assert tap.covers(valid) and tap.basis.shape == (3, 3, K, K)  # three components found, no more
    low = tap.result()
    assert low.rank == 3 and low.residual < 1e-7
    fast = low.relight(proj, patterns, white=white)
    np.testing.assert_allclose(fast, direct, atol=1e-6 * np.abs(direct).max())
    gains = np.random.default_rng(2).uniform(0.5, 2.0, (1, *proj.mask.shape, 3)).astype(np.float32)
    save_lowrank(tmp_path / "v.npz", [low], np.ones((1, *proj.mask.shape, 3)), np.ones((1, 3)), gains, white, proj.mask)
    (back,), weights, view_weights, kept_gains, kept_white = load_lowrank(tmp_path / "v.npz", proj.mask)
    np.testing.assert_allclose(back.relight(proj, patterns, white=white), fast, atol=1e-3 * np.abs(direct).max())  # float16
    assert weights.shape == (1, *proj.mask.shape, 3) and view_weights.shape == (1, 3)
    n = int(proj.mask.sum())  # the gains and the white are kept at the decoded pixels, as they were
    assert kept_gains.shape == (1, n, 3) and kept_white.shape == (n, 3)
    np.testing.assert_array_equal(kept_gains[0], gains[0][proj.mask])
    np.testing.assert_array_equal(kept_white, white[proj.mask])


def test_a_models_tensors_are_projected_where_they_are_and_handed_on_as_they_are(make_projection):
    """A GPU relight's footprints are tensors on the device: the tap projects them there and passes them on as
    tensors (not copied to the host and back); the same coefficients and residual as from arrays, a NaN zeroed alike."""
    import torch

    proj = make_projection(black=0.002)
    arrays = _rank3_source(proj)
    valid = np.argwhere(proj.mask)

    def damaged(px):  # (one non-finite value: the splat zeroes it, the coefficients too)
        out = arrays(px)
        out[px[:, 0] * proj.mask.shape[1] + px[:, 1] == valid[5, 0] * proj.mask.shape[1] + valid[5, 1], 0, 0, 0] = np.nan
        return out

    taps = [LowRankTap(lambda px, f=f: f(damaged(px)), valid, proj.mask.shape, sample=64) for f in (np.asarray, torch.from_numpy)]
    for tap in taps:
        for chunk in (valid[:7], valid[5:40], valid):  # repeated pixels: each kept once
            out = tap(chunk)
            assert torch.is_tensor(out) == (tap is taps[1])
    want, got = taps[0].result(), taps[1].result()
    np.testing.assert_array_equal(got.pixels, want.pixels)
    np.testing.assert_allclose(got.coefficients, want.coefficients, rtol=1e-5, atol=1e-5 * np.abs(want.coefficients).max())
    assert np.isfinite(got.coefficients).all() and got.residual == pytest.approx(want.residual, abs=1e-7)  # (rank 3: ~0 either way)
    new = np.ones(40, bool)  # the device's projection itself (a CPU tensor takes NumPy's faster path): the same
    on_device = taps[1]._project_tensor(torch.from_numpy(damaged(valid[:40])), new)
    on_host = taps[0]._project(damaged(valid[:40]), new)
    np.testing.assert_allclose(on_device[0], on_host[0], rtol=1e-5, atol=1e-5 * np.abs(on_host[0]).max())
    assert on_device[1:] == pytest.approx(on_host[1:], rel=1e-6)


def test_widened_eigen_footprints_relight_as_the_widened_footprints_and_are_kept_with_their_stretch(tmp_path, make_projection):
    """The view calibration's members (``relight_view(widen=S)``: stretched along x, y and both, and softened) from
    the cache: the eigen-footprints mapped, each pixel's coefficients rescaled to keep its colours' energy, relight as
    the splat of the mapped footprints; the file keeps the stretch, gives each model its four members in that order,
    and is not read for another stretch."""
    import torch

    from sssphase_core.relight.engine import calibration_members, member_maps

    proj, source, valid, tap, patterns, white = _tapped_view(make_projection, seed=3)
    plain, *wides = relight(tap, proj, patterns, K, white=white, variants=calibration_members(1.4))
    low = tap.result()
    assert len(wides) == 4 and np.abs(wides[0] - wides[1]).max() > 0.05 * np.abs(plain).max()  # x and y apart
    for change, kept, wide in zip(member_maps(1.4), calibration_members(1.4), wides, strict=True):
        member = low.mapped(change)
        np.testing.assert_allclose(member.relight(proj, patterns, white=white), wide, atol=2e-6 * np.abs(wide).max())
        assert np.abs(wide - plain).max() > 0.02 * np.abs(plain).max()  # the change is not lost on the way
        direct = kept(torch.from_numpy(source(valid[:5]))).numpy()  # rebuilt from the coefficients
        rebuilt = np.einsum("ncr,cryx->nyxc", member.coefficients[:5], member.basis)
        np.testing.assert_allclose(rebuilt, direct, atol=1e-6 * np.abs(direct).max())
    ones = np.ones((4, *proj.mask.shape, 3), np.float32)
    save_lowrank(tmp_path / "w.npz", [low], ones, np.ones((4, 3)), ones, white, proj.mask, widen=1.4)
    members, weights, view_weights, gains, _ = load_lowrank(tmp_path / "w.npz", proj.mask, widen=1.4)
    assert len(members) == 4 and weights.shape[0] == view_weights.shape[0] == gains.shape[0] == 4
    for member, wide in zip(members, wides, strict=True):
        np.testing.assert_allclose(member.relight(proj, patterns, white=white), wide, atol=1e-3 * np.abs(wide).max())
    assert load_lowrank(tmp_path / "w.npz", proj.mask) is None and load_lowrank(tmp_path / "w.npz", proj.mask, widen=1.3) is None
    save_lowrank(tmp_path / "p.npz", [low], ones[:1], np.ones((1, 3)), ones[:1], white, proj.mask)
    assert load_lowrank(tmp_path / "p.npz", proj.mask, widen=1.4) is None and load_lowrank(tmp_path / "p.npz", proj.mask)


def test_a_basis_of_fewer_components_says_how_much_it_leaves_out(make_projection):
    rng = np.random.default_rng(2)
    sample = rng.random((40, K, K, 3)).astype(np.float32)  # noise: no few components hold it
    basis = fit_basis(sample, max_rank=5)
    assert basis.shape == (3, 5, K, K)
    flat = basis.reshape(3, 5, -1)
    np.testing.assert_allclose(flat[0] @ flat[0].T, np.eye(5), atol=1e-5)  # orthonormal
    proj = make_projection()
    valid = np.argwhere(proj.mask)
    table = rng.random((*proj.mask.shape, K, K, 3)).astype(np.float32)
    tap = LowRankTap(lambda px: table[px[:, 0], px[:, 1]], valid, proj.mask.shape, sample=40)
    tap(valid)
    fp = table[valid[:, 0], valid[:, 1]].reshape(len(valid), -1, 3).astype(np.float64)
    b = tap.basis.reshape(3, tap.basis.shape[1], -1).astype(np.float64)
    kept = sum(np.square(fp[..., c] @ b[c].T).sum() for c in range(3))
    # (measured on every RESIDUAL_STRIDE-th footprint as they go by: an estimate of the whole's)
    assert tap.result().residual == pytest.approx(1 - kept / np.square(fp).sum(), rel=0.05)
    assert tap.result().residual > 0.05  # and it is large: noise is not low-rank


def _calibration(proj) -> tuple[np.ndarray, ...]:
    """Zero weights, unit gains and a white of ones for a view of ``proj``: ``save_lowrank``'s calibration arguments."""
    shape = (*proj.mask.shape, 3)
    return np.zeros((1, *shape)), np.zeros((1, 3)), np.ones((1, *shape)), np.ones(shape), proj.mask


@pytest.mark.parametrize("damage", ["garbage", "other view", "missing", "earlier format", "members", "basis"])
def test_a_damaged_or_foreign_eigen_footprint_file_is_not_read(tmp_path, damage, make_projection):
    proj = make_projection()
    path = tmp_path / "v.npz"
    low = LowRankFootprints(np.zeros((3, 2, K, K), np.float32), np.argwhere(proj.mask), np.zeros((proj.mask.sum(), 3, 2)),
                            proj.mask.shape, 0.0)
    if damage == "garbage":
        path.write_bytes(b"not a zip")
    elif damage == "other view":
        save_lowrank(path, [low], *_calibration(proj))
    elif damage == "earlier format":  # weights fitted before white-consistent relighting: not this version's
        save_lowrank(path, [low], *_calibration(proj))
        assert load_lowrank(path, proj.mask) is not None
        with np.load(path) as z:
            old = {k: z[k] for k in z.files if k != "format"}
        np.savez(path, **old)
    elif damage in ("members", "basis"):  # edited or damaged after it was written: a claim of 10^9 members once hung
        save_lowrank(path, [low], *_calibration(proj))
        with np.load(path) as z:
            edited = {k: z[k] for k in z.files}
        if damage == "members":
            edited["members"] = np.asarray(10**9)
        else:  # same shapes, other values: only the digest tells
            edited["m0_basis"] = np.ones_like(edited["m0_basis"])
        np.savez(path, **edited)
    other = np.zeros((proj.mask.shape[0] + 1, proj.mask.shape[1]), bool)  # a view of another size
    assert load_lowrank(path, other if damage == "other view" else proj.mask) is None


def test_a_blend_stretches_its_first_model_only_and_its_weights_split_per_model():
    """``relight_view(widen=S)`` with ``also``: the first source is four members (stretched along x, y and both,
    softened), the others one each; ``split_stretches`` gives one weight per model and the first model's split."""
    from sssphase_core.relight.pipeline import split_stretches

    weights = np.array([[0.1, 0.2, 0.0], [0.3, 0.0, 0.1], [0.0, 0.1, 0.1], [0.1, 0.0, 0.2], [0.4, 0.5, 0.6]], np.float32)
    per_model, shares = split_stretches(weights, True)
    np.testing.assert_allclose(per_model, [[0.5, 0.3, 0.4], [0.4, 0.5, 0.6]], atol=1e-6)
    np.testing.assert_array_equal(shares, weights[:4])
    unstretched, none = split_stretches(weights[:2], False)
    assert none is None and unstretched.shape == (2, 3)
