"""The decoder's training domain: its checkpoint records how wide its training footprints were, and the torch
backend gives the analytic model's footprints to pixels far beyond that (not the decoder's extrapolation)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from sssphase_core.errors import DataError
from sssphase_core.learning.backends import get_backend
from sssphase_core.learning.backends.analytic_backend import AnalyticBackend
from sssphase_core.learning.data import psp_patches
from sssphase_core.learning.domain import (
    WIDTH_MARGIN,
    WidthDomain,
    beyond,
    cuts_tail,
    pixel_widths,
    tail_radius,
    training_domain,
    with_physics_tail,
)
from sssphase_core.learning.losses import noise_floor


def _washed_out(psp: np.ndarray, contrast: float) -> np.ndarray:
    """The same view with its fringes' modulation scaled by ``contrast``: light spread far wider than the
    period (the fringes' MTF falls with the footprint's width), the offset, i.e. the energy, kept."""
    mean = psp.reshape(2, 4, *psp.shape[1:]).mean(axis=1, keepdims=True)
    return (mean + contrast * (psp.reshape(2, 4, *psp.shape[1:]) - mean)).reshape(psp.shape).astype(np.float32)


@pytest.fixture(scope="module")
def decoder_run(synthetic, pretrained, tmp_path_factory):
    from sssphase_core.learning.training import DecoderConfig

    out = tmp_path_factory.mktemp("domain") / "dec"
    get_backend("torch").fit(synthetic[0], out, encoder=pretrained,
                             config=DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), progress=False)
    return out / "last.pt"


def test_the_checkpoint_records_the_widths_its_training_pixels_reach(decoder_run, synthetic):
    views = synthetic[0]
    domain = WidthDomain.from_dict(torch.load(decoder_run, weights_only=False, map_location="cpu")["domain"])
    assert domain is not None and domain.pixels == sum(len(v.pixels) for v in views)
    assert replace(domain, tail_radius=None) == training_domain(views, 16)
    widths = np.concatenate([pixel_widths(psp_patches(v.psp, v.pixels, 5), 16)["widths"] for v in views])
    assert (widths.max(axis=0) * 0.5 < np.asarray(domain.limit)).all()  # beyond the bulk, by the margin
    assert np.allclose(np.asarray(domain.limit), np.quantile(widths, domain.quantile, axis=0) * WIDTH_MARGIN)
    assert beyond(domain, widths).mean() < 0.01


def test_pixels_beyond_the_training_widths_get_the_analytic_footprints_and_the_others_the_decoders(decoder_run, synthetic):
    v = synthetic[0][0]
    guarded = get_backend("torch", checkpoint=decoder_run, black=0.0)
    plain = get_backend("torch", checkpoint=decoder_run, guard=False)
    own = guarded.predict_footprints((v.psp, v.pixels))
    assert guarded.beyond_domain == 0 and guarded.predicted == len(v.pixels)
    decoders = plain.predict_footprints((v.psp, v.pixels))
    tail = guarded.domain.tail_radius
    if cuts_tail(tail, 16):  # the rings beyond the recorded tail are the physics' (the test below)
        near = psp_patches(v.psp, v.pixels, 16)
        est = pixel_widths(near, 16, 0.0)
        decoders = with_physics_tail(decoders, AnalyticBackend(patch=16, black=0.0).render(est["energy"], est["axes"]), tail)
    assert np.allclose(own, decoders, rtol=1e-5, atol=1e-8)

    wide = _washed_out(v.psp, 0.02)
    patches = psp_patches(wide, v.pixels, 16)
    assert beyond(guarded.domain, pixel_widths(patches, 16, 0.0)["widths"]).all()
    out = guarded.predict_footprints(patches)
    assert guarded.beyond_domain == len(v.pixels) and guarded.predicted == 2 * len(v.pixels)
    analytic = AnalyticBackend(patch=16, black=0.0).predict_footprints(patches)
    assert np.allclose(out, analytic, rtol=1e-5, atol=1e-7)
    extrapolated = plain.predict_footprints(patches)
    assert not np.allclose(out, extrapolated, rtol=1e-2, atol=1e-4)
    # spread far wider: the analytic footprints keep less of their energy in the centre 3 x 3 than the decoder's own
    centre = lambda f: f[:, 7:10, 7:10].sum(axis=(1, 2)) / f.sum(axis=(1, 2))  # noqa: E731
    assert np.median(centre(out)) < np.median(centre(own))


def test_patches_as_tensors_give_the_footprints_of_the_same_patches_as_arrays(decoder_run, synthetic):
    """The relight crops a view's patches on the model's device and hands them over as tensors: the same
    footprints as from arrays, the guard's widths read from each patch's centre window, beyond the domain too;
    a tensor of the wrong shape is one clear line."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.backends.base import centre_window
    from sssphase_core.learning.backends.torch_backend import GUARD_WINDOW
    from sssphase_core.relight.sources import backend_source

    v = synthetic[0][0]
    for contrast in (1.0, 0.02):  # inside the domain; beyond it (the analytic model's footprints)
        psp = v.psp if contrast == 1.0 else _washed_out(v.psp, contrast)
        # (float32: bf16 kernels round differently with the batch's size, and chunk=7 below makes other batches)
        arrays = get_backend("torch", checkpoint=decoder_run, black=0.0, precision="fp32")
        tensors = get_backend("torch", checkpoint=decoder_run, black=0.0, precision="fp32")
        patches = psp_patches(psp, v.pixels, 16)
        want = arrays.predict_footprints(patches)
        got = tensors.predict_footprints(torch.from_numpy(patches))
        assert isinstance(want, np.ndarray) and torch.is_tensor(got) and got.device == tensors.device  # stays there
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)  # (float rounding: another memory layout)
        for window in (centre_window(patches, GUARD_WINDOW), centre_window(torch.from_numpy(patches), GUARD_WINDOW)):
            for key, value in pixel_widths(patches, 16, 0.0).items():  # what the guard reads of the whole patches
                np.testing.assert_array_equal(pixel_widths(window, 16, 0.0)[key], value)
        assert tensors.beyond_domain == arrays.beyond_domain == (0 if contrast == 1.0 else len(v.pixels))
        np.testing.assert_allclose(backend_source(tensors, psp, chunk=7)(v.pixels), want, rtol=1e-5, atol=1e-9)
    for be in (arrays, tensors):  # a tail from 3 / 4 / 5 px out: the physics' rings rendered on the model's device
        be.domain = replace(be.domain, tail_radius=(3, 4, 5))
    want = arrays.predict_footprints(psp_patches(v.psp, v.pixels, 16))
    got = tensors.predict_footprints(torch.from_numpy(psp_patches(v.psp, v.pixels, 16)))
    assert tensors.tail_applied == arrays.tail_applied == (3, 4, 5)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)
    with pytest.raises(InputError, match=r"PSP patches must be \(N, 24, K, K\)"):
        tensors.predict_footprints(torch.zeros((2, 8, 16, 16)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_a_gpu_the_footprints_and_their_analytic_parts_stay_on_it(decoder_run, synthetic):
    """On CUDA the decoder's footprints, the analytic model's beyond the domain and its tail are made on the GPU
    and handed on there: the CPU's footprints within float32 (TF32 convolutions off)."""
    v = synthetic[0][0]
    torch.backends.cudnn.allow_tf32 = False
    for contrast in (1.0, 0.02):
        patches = psp_patches(v.psp if contrast == 1.0 else _washed_out(v.psp, contrast), v.pixels, 16)
        cpu, gpu = (get_backend("torch", checkpoint=decoder_run, black=0.0, precision="fp32", device=d) for d in ("cpu", "cuda"))
        for be in (cpu, gpu):
            be.domain = replace(be.domain, tail_radius=(3, 4, 5))
        want = cpu.predict_footprints(patches)
        got = gpu.predict_footprints(torch.from_numpy(patches).cuda())
        assert got.is_cuda and gpu.beyond_domain == cpu.beyond_domain and gpu.tail_applied == (3, 4, 5)
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-4, atol=1e-7)


def test_a_checkpoint_from_before_the_domain_uses_the_decoder_everywhere(decoder_run, synthetic, tmp_path):
    old = torch.load(decoder_run, weights_only=False, map_location="cpu")
    old.pop("domain")
    torch.save(old, tmp_path / "old.pt")
    v = synthetic[0][0]
    patches = psp_patches(_washed_out(v.psp, 0.02), v.pixels, 16)
    be = get_backend("torch", checkpoint=tmp_path / "old.pt")
    assert be.domain is None
    assert np.array_equal(be.predict_footprints(patches), get_backend("torch", checkpoint=decoder_run, guard=False).predict_footprints(patches))
    assert be.beyond_domain == 0


@pytest.mark.parametrize("limits", [[1.0, 2.0], [1.0, float("nan"), 2.0], [0.0, 1.0, 1.0], "wide"])
def test_a_damaged_domain_is_one_clear_line(limits):
    with pytest.raises(DataError, match="training domain is damaged"):
        WidthDomain.from_dict({"width_limit_px": limits})


def test_relighting_says_how_many_pixels_the_analytic_model_took_over(decoder_run, synthetic, tmp_path):
    from types import SimpleNamespace

    from sssphase_core.relight.backends import domain_line

    ckpt = torch.load(decoder_run, weights_only=False, map_location="cpu")
    tail = ckpt["domain"].pop("tail_radius_px")
    torch.save(ckpt, tmp_path / "untailed.pt")
    v = synthetic[0][0]
    be = get_backend("torch", checkpoint=tmp_path / "untailed.pt", black=0.0)
    source = SimpleNamespace(backend=be)
    rv = SimpleNamespace(object="a", view=0)
    be.predict_footprints((v.psp, v.pixels))
    assert domain_line(rv, "torch", source) is None  # nothing handed over: nothing said
    be.predict_footprints(psp_patches(_washed_out(v.psp, 0.02), v.pixels[:16], 16))
    line = domain_line(rv, "torch", source)
    n = len(v.pixels) + 16
    assert line is not None and line.startswith(f"a view 0: torch: 16 of {n} pixels") and "analytic model" in line
    assert "/".join(f"{x:.1f}" for x in be.domain.limit) in line
    tailed = get_backend("torch", checkpoint=decoder_run, black=0.0)  # its recorded tail (noisy crops: inside the patch)
    tailed.predict_footprints((v.psp, v.pixels))
    line = domain_line(rv, "torch", SimpleNamespace(backend=tailed))
    radii = "/".join(str(r) for r in tail)
    assert line == (f"a view 0: torch: footprints from {radii} px out (R/G/B) are the analytic model's: its training "
                    "crops' median light was below their noise there")


def _rings(k: int) -> np.ndarray:
    off = np.arange(k) - k // 2
    return np.hypot(off[:, None], off[None, :])


def test_the_tail_radius_is_where_the_crops_hold_no_light_at_most_pixels_though_their_mean_does():
    """Crops of a wide footprint counted in photons (Poisson): far out most pixels count none, so the SBH loss's
    median-fitting terms teach no light there, while the light is there on average."""
    k, n, w = 32, 600, 4.0
    rng = np.random.default_rng(0)
    profile = np.exp(-_rings(k) / w)
    profile /= profile.sum()
    photons = np.array([500.0, 2e3, 8e3])  # per footprint: the dimmer the colour, the nearer its radius
    counts = rng.poisson(photons[None, :, None, None] * profile[None, None], size=(n, 3, k, k))
    radius = tail_radius(counts / photons[None, :, None, None])
    assert radius[0] < radius[1] < radius[2] <= np.rint(_rings(k).max())
    for c, r in enumerate(radius):
        mean_count = photons[c] * profile[np.rint(_rings(k)) == r].mean()
        assert 0.1 < mean_count < 1.5  # about ln 2: a Poisson count's median is 0 below it
        assert counts[:, c, np.rint(_rings(k)) >= r].mean() > 0  # the light the decoder would not learn
    exact = np.broadcast_to(profile, (4, 3, k, k))
    assert tail_radius(exact) == (np.rint(_rings(k).max()) + 1,) * 3  # noise-free: no tail to hand over


def test_under_gaussian_noise_the_tail_radius_is_where_the_light_falls_below_the_noise():
    """Symmetric noise keeps each ring's median at its light however faint (the old rule, median > 0, ran to the
    patch's corners); the loss learns light there only from many crops' average, so the radius is the first ring
    whose median light is not above the crops' noise floor."""
    k, n, w = 32, 800, 1.5
    rng = np.random.default_rng(2)
    profile = np.exp(-_rings(k) / w)
    energy = np.array([1.0, 0.5, 0.2])  # the dimmer the colour, the nearer its radius
    light = energy[None, :, None, None] * profile[None, None] / profile.sum() * np.ones((n, 3, 1, 1))
    sigma = 1e-3
    crops = light + rng.normal(0.0, sigma, light.shape)
    noise = noise_floor(torch.as_tensor(crops, dtype=torch.float32))
    assert 0.8 * sigma < noise < 1.2 * sigma
    assert min(tail_radius(crops)) > 8  # the median alone: light taught out to faint rings
    radius = tail_radius(crops, noise)
    rings = np.rint(_rings(k))
    for c, r in enumerate(radius):
        ring_light = light[0, c][rings == r].mean()
        inner = light[0, c][rings == r - 1].mean()
        assert ring_light < 1.5 * noise and inner > 0.5 * noise  # at the noise, give or take a ring's spread
    assert radius[0] > radius[1] > radius[2]
    assert tail_radius(light, 0.0) == (np.rint(_rings(k).max()) + 1,) * 3  # noise-free: no tail to hand over


def test_a_physics_tail_replaces_the_rings_beyond_each_colours_radius_and_keeps_the_decoders_energy():
    rng = np.random.default_rng(1)
    k = 16
    decoder = rng.uniform(0.0, 1.0, (5, k, k, 3)).astype(np.float32)
    physics = rng.uniform(0.0, 1.0, (5, k, k, 3)).astype(np.float32)
    radius = (2, 4, 12)
    out = with_physics_tail(decoder, physics, radius)
    assert np.allclose(out.sum(axis=(1, 2)), decoder.sum(axis=(1, 2)), rtol=1e-5)
    rings = np.rint(_rings(k))
    for c, r in enumerate(radius):
        near, far = rings < r, rings >= r
        scale = out[:, near, c] / decoder[:, near, c]  # one factor per footprint and colour
        assert np.allclose(scale, scale[:, :1], rtol=1e-5)
        assert np.allclose(out[:, far, c], physics[:, far, c] * scale[:, :1], rtol=1e-5)


def test_the_checkpoint_records_its_tail_and_the_backend_takes_the_rings_beyond_it_from_the_analytic_model(
        decoder_run, synthetic, tmp_path):
    ckpt = torch.load(decoder_run, weights_only=False, map_location="cpu")
    recorded = WidthDomain.from_dict(ckpt["domain"]).tail_radius
    assert recorded is not None and all(1 <= r <= np.rint(_rings(16).max()) + 1 for r in recorded)
    ckpt["domain"]["tail_radius_px"] = [2, 3, 5]
    torch.save(ckpt, tmp_path / "tail.pt")
    v = synthetic[0][0]
    patches = psp_patches(v.psp, v.pixels, 16)
    tailed = get_backend("torch", checkpoint=tmp_path / "tail.pt", black=0.0)
    out = tailed.predict_footprints(patches)
    assert tailed.beyond_domain == 0
    plain = get_backend("torch", checkpoint=decoder_run, guard=False).predict_footprints(patches)
    est = pixel_widths(patches, 16, 0.0)
    physics = AnalyticBackend(patch=16, black=0.0).render(est["energy"], est["axes"])
    assert np.allclose(out, with_physics_tail(plain, physics, (2, 3, 5)), rtol=1e-4, atol=1e-8)
    assert not np.allclose(out, plain, rtol=1e-3, atol=1e-6)
    # without the record (a checkpoint from before it), or unguarded, the decoder's own footprints
    ckpt["domain"].pop("tail_radius_px")
    torch.save(ckpt, tmp_path / "before.pt")
    assert np.array_equal(get_backend("torch", checkpoint=tmp_path / "before.pt").predict_footprints(patches), plain)
    assert np.array_equal(get_backend("torch", checkpoint=tmp_path / "tail.pt", guard=False).predict_footprints(patches), plain)


@pytest.mark.parametrize("tail", [[1, 2], [0, 2, 3], [1.5, 2, 3], "far", [True, 2, 3], [2, 3, 10**6]])
def test_a_damaged_tail_radius_is_one_clear_line(tail):
    with pytest.raises(DataError, match="training domain is damaged: tail radii"):
        WidthDomain.from_dict({"width_limit_px": [1.0, 1.0, 1.0], "tail_radius_px": tail})


def test_relighting_says_from_which_ring_out_the_footprints_are_the_analytic_models(decoder_run, synthetic, tmp_path):
    from types import SimpleNamespace

    from sssphase_core.relight.backends import domain_line

    ckpt = torch.load(decoder_run, weights_only=False, map_location="cpu")
    ckpt["domain"]["tail_radius_px"] = [4, 4, 6]
    torch.save(ckpt, tmp_path / "tail.pt")
    v = synthetic[0][0]
    be = get_backend("torch", checkpoint=tmp_path / "tail.pt", black=0.0)
    source, rv = SimpleNamespace(backend=be), SimpleNamespace(object="a", view=0)
    assert domain_line(rv, "torch", source) is None  # nothing predicted yet
    be.predict_footprints((v.psp, v.pixels))
    line = domain_line(rv, "torch", source)
    assert line is not None and line.startswith("a view 0: torch: footprints from 4/4/6 px out") and "wider" not in line


@pytest.mark.parametrize(("field", "value"), [("quantile", "abc"), ("quantile", 7.0), ("pixels", [1, 2]), ("pixels", -1),
                                              ("pixels", 2.5)])
def test_a_damaged_domain_record_is_one_clear_line_not_an_internal_error(field, value):
    """A checkpoint whose domain said quantile 'abc' or pixels [1, 2] ended relighting in an internal ValueError."""
    with pytest.raises(DataError, match=f"training domain is damaged: {field}"):
        WidthDomain.from_dict({"width_limit_px": [1.0, 1.0, 1.0], field: value})
