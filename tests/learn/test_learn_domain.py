"""The decoder's training domain: its checkpoint records how wide its training footprints were, and the torch
backend gives the analytic model's footprints to pixels far beyond that (not the decoder's extrapolation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sssphase_core.errors import DataError
from sssphase_core.learning.backends import get_backend
from sssphase_core.learning.backends.analytic_backend import AnalyticBackend
from sssphase_core.learning.data import psp_patches
from sssphase_core.learning.domain import WIDTH_MARGIN, WidthDomain, beyond, pixel_widths, training_domain


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
    assert domain == training_domain(views, 16)
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
    assert np.array_equal(own, plain.predict_footprints((v.psp, v.pixels)))

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


def test_relighting_says_how_many_pixels_the_analytic_model_took_over(decoder_run, synthetic):
    from types import SimpleNamespace

    from sssphase_core.relight.backends import domain_line

    v = synthetic[0][0]
    be = get_backend("torch", checkpoint=decoder_run, black=0.0)
    source = SimpleNamespace(backend=be)
    rv = SimpleNamespace(object="a", view=0)
    be.predict_footprints((v.psp, v.pixels))
    assert domain_line(rv, "torch", source) is None  # nothing handed over: nothing said
    be.predict_footprints(psp_patches(_washed_out(v.psp, 0.02), v.pixels[:16], 16))
    line = domain_line(rv, "torch", source)
    n = len(v.pixels) + 16
    assert line is not None and line.startswith(f"a view 0: torch: 16 of {n} pixels") and "analytic model" in line
    assert "/".join(f"{x:.1f}" for x in be.domain.limit) in line
