"""The decoder's reciprocal head: physics read from PSP patches, energy conservation, stability."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sssphase_core.learning.data import psp_patches
from sssphase_core.learning.models import Decoder, Encoder, get_preset
from sssphase_core.learning.models.physics import (
    N_FEATURES,
    RadialProfile,
    RingAverage,
    modulation_features,
    white_from_psp,
)
from sssphase_core.learning.training import (
    DecoderConfig,
    TrainingDiverged,
    load_checkpoint,
    load_decoder,
    train_decoder,
)

PERIOD = 6.0  # synthetic_views' fringe period (px)


def _patches(synthetic, obj: str) -> tuple[torch.Tensor, np.ndarray]:
    views, kernels = synthetic
    v = next(v for v in views if v.object == obj)
    return torch.as_tensor(psp_patches(v.psp, v.pixels, 16)), kernels[obj]


@pytest.mark.parametrize("obj", ["a", "b"])
def test_white_from_psp_is_the_footprint_energy(synthetic, obj):
    x, kernel = _patches(synthetic, obj)
    white = white_from_psp(x).numpy()
    np.testing.assert_allclose(white, np.broadcast_to(kernel.sum(axis=(0, 1)), white.shape), rtol=0.02, atol=0.003)


@pytest.mark.parametrize("obj", ["a", "b"])
def test_modulation_features_measure_the_footprint_mtf_and_fringe_frequency(synthetic, obj):
    x, kernel = _patches(synthetic, obj)
    f = modulation_features(x).numpy()  # (N, 3, N_FEATURES)
    assert f.shape[1:] == (3, N_FEATURES)
    c = kernel.shape[0] // 2
    d = np.arange(kernel.shape[0]) - c
    k = 2 * np.pi / PERIOD
    mtf_x = (kernel * np.cos(k * d)[None, :, None]).sum(axis=(0, 1)) / kernel.sum(axis=(0, 1))
    mtf_y = (kernel * np.cos(k * d)[:, None, None]).sum(axis=(0, 1)) / kernel.sum(axis=(0, 1))
    bright = kernel.sum(axis=(0, 1)) > 0.1  # the modulation of very dim channels is noise-limited
    np.testing.assert_allclose(np.median(f[:, :, 0], 0)[bright], np.log(mtf_x)[bright], atol=0.03)
    np.testing.assert_allclose(np.median(f[:, :, 1], 0)[bright], np.log(mtf_y)[bright], atol=0.03)
    # x fringes vary along x, y fringes along y: (k_xx^2, k_xy^2, k_yx^2, k_yy^2) = (k^2, 0, 0, k^2)
    np.testing.assert_allclose(np.median(f[:, 0, 2:6], 0), [k * k, 0, 0, k * k], atol=0.02)
    share = np.exp(f[:, :, 6]).mean(0)  # each colour's share of the light
    np.testing.assert_allclose(share, kernel.sum(axis=(0, 1)) / kernel.sum(), atol=0.02)


def test_reciprocal_head_conserves_the_white_energy_at_start(tiny, dataset):
    torch.manual_seed(0)
    enc, dec = Encoder(tiny).eval(), Decoder(tiny).eval()
    batch = dataset.batch(np.arange(32))
    dec.init_shape_prior(batch["footprint"])
    with torch.no_grad():
        fp = dec(*enc.features(batch["psp"]), batch["psp"])
    assert (fp >= 0).all()
    torch.testing.assert_close(fp.sum(dim=(2, 3)), white_from_psp(batch["psp"]), rtol=1e-4, atol=1e-6)
    # the shape at start is the mean normalised training shape
    target = batch["footprint"] / batch["footprint"].sum(dim=(2, 3), keepdim=True)
    shape = fp / fp.sum(dim=(2, 3), keepdim=True)
    torch.testing.assert_close(shape[0], target.mean(dim=0), rtol=1e-3, atol=1e-5)


def test_shape_prior_of_noisy_crops_keeps_their_tail(tiny):
    """Captured crops carry zero-mean camera noise over the whole window: the prior is their mean shape with
    the noise averaged out, not the mean of the clipped crops (whose positive noise was a fat tail: on Mitsuba
    renders half of the prior's energy beyond 3 px where the signed mean has 11%)."""
    k = tiny.patch
    d = torch.arange(k, dtype=torch.float32) - k // 2
    r = torch.sqrt(d[:, None] ** 2 + d[None, :] ** 2)
    shape = torch.exp(-r / 1.2)
    shape = (shape / shape.sum()).expand(3, k, k)
    gen = torch.Generator().manual_seed(0)
    crops = 0.12 * shape + 4e-4 * torch.randn(1024, 3, k, k, generator=gen)  # noise ~ 1 % of the peak
    dec = Decoder(tiny)
    dec.init_shape_prior(crops)
    prior = torch.softmax(dec.shape_prior.detach().flatten(1), -1).view(3, k, k)
    far = r >= 3
    assert abs(float(prior[:, far].sum(-1).mean()) - float(shape[0][far].sum())) < 0.01
    assert abs(float(prior[:, k // 2, k // 2].mean()) - float(shape[0, k // 2, k // 2])) < 0.01
    # demosaiced crops ring: a negative lobe next to the centre is no hole in the prior of Bayer crops
    lobed = crops.clone()
    lobed[:, 2, k // 2, k // 2 + 2] = 0.004 * torch.randn(1024, generator=gen) - 0.002  # its mean is negative
    dec.init_shape_prior(lobed)
    assert float(dec.shape_prior.detach()[2, k // 2, k // 2 + 2]) < -15  # linear crops: nothing there
    dec.init_shape_prior(lobed, demosaiced=True)
    assert float(dec.shape_prior.detach()[2, k // 2, k // 2 + 2]) > -8


def test_reciprocal_head_needs_the_psp_patches(tiny):
    from sssphase_core.errors import InputError

    enc, dec = Encoder(tiny).eval(), Decoder(tiny).eval()
    with pytest.raises(InputError, match="PSP patches"):
        dec(*enc.features(torch.rand(1, 24, 16, 16)))
    with pytest.raises(InputError, match="direct"):
        Decoder(tiny, head="linear")


def test_gradients_are_finite_on_extreme_patches(tiny):
    """Zero light, negative noise and saturated patches: no NaN/inf in the output or any gradient
    (the radius's sqrt at the centre and the modulation's sqrt at zero amplitude are the traps)."""
    enc, dec = Encoder(tiny).eval(), Decoder(tiny).train()
    with torch.no_grad():
        dec.profile.mlp[-1].weight.normal_()  # a non-zero profile, so the stretch gets gradients
    x = torch.cat([torch.zeros(2, 24, 16, 16), -1e-3 * torch.rand(2, 24, 16, 16), torch.ones(2, 24, 16, 16)])
    fp = dec(*enc.features(x), x)
    assert torch.isfinite(fp).all()
    (fp.sum() + fp.square().sum()).backward()
    for name, p in dec.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_radial_profile_interpolates_its_knots():
    prof = RadialProfile(16)
    with torch.no_grad():
        prof.mlp[-1].bias[: len(prof.knots)] = -prof.knots  # log-profile = -r
    out = prof(torch.zeros(1, 3, N_FEATURES))[0, 0]
    r = torch.sqrt(prof.dx**2 + prof.dy**2)
    torch.testing.assert_close(out, -r, rtol=0, atol=1e-5)


def test_direct_head_checkpoints_round_trip(pretrained, dataset, tmp_path):
    cfg = DecoderConfig(epochs=1, batch_size=16, ckpt_every=0, head="direct")
    train_decoder(cfg, pretrained, dataset, tmp_path / "dec", progress=False)
    assert load_checkpoint(tmp_path / "dec")["config"]["head"] == "direct"
    _, dec = load_decoder(tmp_path / "dec")
    assert dec.head_kind == "direct"


def test_a_diverging_loss_stops_training_with_the_last_good_checkpoint(pretrained, dataset, tmp_path, monkeypatch):
    import sssphase_core.learning.training as training

    cfg = DecoderConfig(epochs=2, batch_size=16, ckpt_every=0)
    train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pretrained, dataset, tmp_path / "dec", progress=False)
    good = load_checkpoint(tmp_path / "dec")

    class NaNLoss(training.decoder.SBHLoss):
        def forward(self, pred, target):
            loss, terms = super().forward(pred, target)
            return loss * float("nan"), terms

    monkeypatch.setattr(training.decoder, "SBHLoss", NaNLoss)
    with pytest.raises(TrainingDiverged, match="nan"):
        train_decoder(cfg, pretrained, dataset, tmp_path / "dec", progress=False)
    after = load_checkpoint(tmp_path / "dec")
    assert after["loop"] == good["loop"]
    assert all(torch.isfinite(v).all() for v in after["decoder"].values() if v.is_floating_point())



@pytest.mark.parametrize("crops", ["all", "three"])
def test_nan_in_the_training_data_is_named_not_blamed_on_the_learning_rate(pretrained, synthetic, tmp_path, crops):
    """NaN footprint crops gave 'the decoder loss became nan ... lower the learning rate (the last good
    checkpoint is kept in last.pt ...)', and no last.pt existed; a few of them, in the sample the shape prior is
    made of, made every prediction NaN, a clean batch's too, and gave the same."""
    from dataclasses import replace

    from sssphase_core.errors import DataError
    from sssphase_core.learning.data import PatchDataset

    views = list(synthetic[0])
    fp = np.array(views[1].footprints, copy=True)
    fp[slice(None) if crops == "all" else slice(0, 3), 3, 3] = np.nan  # object a's view 1: every crop, or three
    # three crops of a Bayer camera's (demosaiced: clipped, not dropped, into the shape prior's mean)
    views[1] = replace(views[1], footprints=fp, isp=None if crops == "all" else {"demosaic": "opencv", "bayer": "RGGB"})
    with pytest.raises(DataError, match=r"hold NaN or infinite values \(a view 1; psp or footprint crops\)"):
        train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pretrained,
                      PatchDataset(views, 16, ["a", "b"], with_targets=True), tmp_path / "dec", progress=False)


def test_ring_average_keeps_only_angular_detail():
    ring = RingAverage(16)
    prof = RadialProfile(16)
    radial = torch.sqrt(prof.dx**2 + prof.dy**2).expand(2, 3, 16, 16)
    torch.testing.assert_close(ring(radial.round()), torch.zeros_like(radial), rtol=0, atol=1e-5)
    x = torch.randn(2, 3, 16, 16)
    out = ring(x)
    torch.testing.assert_close(ring(out), out, rtol=0, atol=1e-5)  # a projection
    assert out.abs().sum() > 0.5 * x.abs().sum()  # most of a random map is angular


def test_ring_average_is_the_averaging_matrix_it_replaces_and_old_checkpoints_load(tmp_path):
    """Ring means by a (K*K, R) product gathered back to the pixels equal the (K*K, K*K) averaging matrix earlier
    decoders multiplied by (and saved: a checkpoint holding it still loads, the matrix dropped)."""
    ring = RingAverage(32)
    member = torch.nn.functional.one_hot(ring.ring).float()
    matrix = member @ torch.diag(1.0 / member.sum(0)) @ member.T  # what earlier decoders kept as `average`
    x = torch.randn(4, 3, 32, 32)
    torch.testing.assert_close(ring(x), (x.flatten(2) - x.flatten(2) @ matrix).view(x.shape), rtol=0, atol=1e-6)
    assert not any("average" in k for k in ring.state_dict())  # derived from K: not saved
    lite = get_preset("lite")
    old = {**Decoder(lite).state_dict(), "angular.average": matrix}
    Decoder(lite).load_state_dict(old)  # strict: only the matrix is dropped
    from sssphase_core.learning.models import Encoder
    from sssphase_core.learning.training import load_decoder

    torch.save({"kind": "decoder", "preset": lite.to_dict(), "encoder": Encoder(lite).state_dict(), "decoder": old,
                "config": {"head": "reciprocal"}}, tmp_path / "old.pt")  # checked on the meta device first, then loaded
    assert isinstance(load_decoder(tmp_path / "old.pt")[1], Decoder)
