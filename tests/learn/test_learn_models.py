"""Model presets: parameter counts and shapes (forward at batch 1, no training)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.learning.models import Decoder, Encoder, SimSiam, get_preset
from sssphase_core.learning.models.decoder import UpStage


def n_params(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


@pytest.mark.parametrize(("name", "patch", "embed"), [("paper", 90, 1024), ("lite", 32, 128)])
def test_encoder_decoder_shapes_at_batch_one(name, patch, embed):
    p = get_preset(name)
    enc, dec = Encoder(p).eval(), Decoder(p).eval()
    x = torch.randn(1, 24, patch, patch)
    with torch.no_grad():
        bottleneck, skips = enc.features(x)
        assert enc(x).shape == (1, embed)
        assert dec(bottleneck, skips, x).shape == (1, 3, patch, patch)
    pad = p.padded
    assert pad % 16 == 0 and pad >= patch
    assert bottleneck.shape == (1, embed, pad // 16, pad // 16)
    assert [s.shape[-1] for s in skips] == [pad, pad // 2, pad // 4, pad // 8]


def test_paper_parameter_counts_match_the_authors():
    p = get_preset("paper")
    assert p.padded == 96
    assert 31e6 < n_params(Encoder(p)) < 33e6
    assert 21.5e6 < n_params(Decoder(p)) < 24e6


def test_lite_is_much_smaller_than_paper():
    assert n_params(SimSiam("lite")) * 20 < n_params(SimSiam("paper").encoder)


def test_simsiam_loss_is_symmetric_negative_cosine(tiny):
    m = SimSiam(tiny).train()
    x = torch.randn(8, 24, 16, 16)
    out = m(x, x.clone())
    assert -1.0 <= float(out["loss"].detach()) <= 1.0
    out["loss"].backward()
    assert all(p.grad is not None for p in m.predictor.parameters())
    # last projector BN has no affine parameters (SimSiam)
    assert m.projector[-1].affine is False


def test_decorrelation_loss_measures_how_much_the_features_move_together():
    from sssphase_core.learning.models.simsiam import decorrelation_loss

    g = torch.Generator().manual_seed(0)
    independent = torch.randn(4096, 16, generator=g)
    assert float(decorrelation_loss(independent)) < 0.01  # ~1/B for a finite batch
    collapsed = torch.randn(4096, 1, generator=g) * torch.linspace(0.5, 3.0, 16)  # rank one: every pair at |r| = 1
    assert float(decorrelation_loss(collapsed)) == pytest.approx(1.0, abs=1e-4)
    # features 8-15 are 0-7 rescaled and offset: 16 of the 240 ordered pairs at r = 1, whatever the scale
    half = torch.cat([independent[:, :8], independent[:, :8] * 7.0 + 3.0], dim=1)
    assert float(decorrelation_loss(half)) == pytest.approx(16 / 240, abs=0.01)
    assert decorrelation_loss(independent.half()).dtype == torch.float32  # computed in float32 under autocast


def test_decorrelation_term_is_added_to_simsiam_and_reaches_the_encoder(tiny):
    x1, x2 = torch.randn(8, 24, 16, 16), torch.randn(8, 24, 16, 16)
    torch.manual_seed(0)
    plain = SimSiam(tiny).train()
    torch.manual_seed(0)
    regular = SimSiam(tiny).train()
    torch.manual_seed(1)  # the same dropout draws in both
    a = plain(x1, x2)
    torch.manual_seed(1)
    b = regular(x1, x2, decorrelate=2.0)
    assert "decorrelation" not in a and 0 < float(b["decorrelation"]) <= 1
    assert float(b["loss"]) == pytest.approx(float(a["loss"]) + 2.0 * float(b["decorrelation"]), rel=1e-5)
    b["decorrelation"].backward()
    assert any(q.grad is not None and q.grad.abs().sum() > 0 for q in regular.encoder.parameters())
    assert all(q.grad is None for q in regular.predictor.parameters())  # it acts on the projections only


def test_preset_roundtrip_and_unknown_name(tiny):
    assert get_preset(tiny.to_dict()) == tiny
    with pytest.raises(InputError, match="lite"):
        get_preset("huge")


def test_icnr_init_gives_no_checkerboard():
    stage = UpStage(8, 4, 4, 2)
    x = torch.randn(1, 8, 5, 5)
    up = stage.shuffle(stage.expand(x))
    # every 2x2 block produced from one input pixel is constant at initialisation
    assert torch.allclose(up[..., 0::2, 0::2], up[..., 1::2, 1::2])
    assert torch.allclose(up[..., 0::2, 0::2], up[..., 0::2, 1::2])


def test_auxiliary_material_head(tiny):
    enc, dec = Encoder(tiny).eval(), Decoder(tiny, n_classes=5)
    x = torch.randn(2, 24, 16, 16)
    fp, logits = dec(*enc.features(x), x)
    assert fp.shape == (2, 3, 16, 16) and logits.shape == (2, 5)


@pytest.mark.parametrize("head", ["reciprocal", "direct"])
def test_scale_invariant_encoder_reads_the_light_whatever_its_level(tiny, head, monkeypatch):
    """s times the light: the same features, s times the footprint (both heads); a raw-level encoder differs."""
    monkeypatch.setattr("sssphase_core.learning.models.encoder.LEVEL_FLOOR", 0.0)  # exact (the floor: below)
    torch.manual_seed(0)
    enc, dec = Encoder(tiny).eval(), Decoder(tiny, head=head).eval()
    x = 0.2 + 0.1 * torch.rand(3, 24, 16, 16)  # lit patches, far above the level floor
    with torch.no_grad():
        fp = dec(*enc.features(x), x)
        for s in (0.05, 8.0):
            assert torch.allclose(enc(s * x), enc(x), rtol=1e-3, atol=1e-4)
            assert torch.allclose(dec(*enc.features(s * x), s * x), s * fp, rtol=1e-3, atol=1e-7)
        raw = Encoder(dataclasses.replace(tiny, scale_invariant=False)).eval()
        assert not torch.allclose(raw(8.0 * x), raw(x), rtol=1e-2, atol=1e-3)


def test_patch_level_leaves_a_dark_patch_dark():
    from sssphase_core.learning.models.encoder import LEVEL_FLOOR, patch_level

    dark = torch.full((1, 24, 16, 16), 1e-5)
    assert float((dark / patch_level(dark)).max()) < 0.02  # its noise is not raised to a lit patch's level
    negative = torch.full((1, 24, 16, 16), -0.01)  # a dark frame minus its black level
    assert float(patch_level(negative)) == pytest.approx(LEVEL_FLOOR)


def test_presets_of_older_checkpoints_read_raw_levels(tiny):
    old = tiny.to_dict()
    old.pop("scale_invariant")  # checkpoints made before the field existed
    assert get_preset(old).scale_invariant is False
    assert get_preset("lite").scale_invariant and get_preset("paper").scale_invariant
    with pytest.raises(InputError, match="scale_invariant"):
        get_preset({**old, "scale_invariant": "yes"})
