"""Decoder fitting with the SBH loss on a frozen encoder (or end to end: the supervised U-Net baseline)."""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sssphase_core.errors import DataError, InputError
from sssphase_core.learning import augment
from sssphase_core.learning.camera import NO_CAMERA, as_captured
from sssphase_core.learning.data import PatchDataset
from sssphase_core.learning.domain import tail_radius, training_domain
from sssphase_core.learning.inputs import check_aux_class_count
from sssphase_core.learning.losses import LOG_EPS, SBHLoss, noise_floor
from sssphase_core.learning.metrics import MSE_FLOOR, psnr
from sssphase_core.learning.models import Decoder, Encoder, ModelPreset, get_preset
from sssphase_core.learning.training.checkpoints import CHECKPOINT, load_encoder, save_checkpoint
from sssphase_core.learning.training.loop import (
    Loop,
    LoopConfig,
    StepProgress,
    autocast_for,
    config_dict,
    init_distributed,
    resume_state,
    start_fresh,
    wrap_ddp,
)

PRIOR_SAMPLES = 1024  # training footprints averaged into the reciprocal head's initial shape


@dataclass
class DecoderConfig(LoopConfig):
    epochs: int = 10
    batch_size: int = 32
    lr: float = 1e-3  # Adam (the paper)
    out_scale: float = 0.05
    head: str = "reciprocal"  # reciprocal (energy from the PSP patch x learned shape) or direct (the paper's)
    physics_lr_mult: float = 10.0  # the reciprocal head's small profile MLP, prior map and gain learn faster
    aux_classes: int = 0  # > 0: auxiliary material-classification head on the embedding
    aux_weight: float = 0.1
    log_eps: float | None = None  # SBH log offset; None: max(LOG_EPS, noise floor of the training footprints)
    learn_gain: bool = False  # reciprocal head: learn the per-colour energy gain (else 1: energy from reciprocity)
    val_samples: int = 512
    end_to_end: bool = False  # set when no encoder checkpoint is given: the supervised U-Net baseline (no SSL)
    preset: str = "lite"  # sizes an end-to-end model; a frozen encoder brings its own (recorded either way)
    # Compare each predicted footprint with its captured crop as the crop recorded it (summed over the camera
    # pixels its dot lit, then Bayer sampling and demosaicing: learning.camera.as_captured), so the decoder
    # predicts the light entering at the pixel, before the sensor; False: the crops themselves are the targets
    capture_model: bool = True
    # Probability per patch of each step of the camera augmentation of the decoder's input (augment.camera:
    # Bayer resampling and demosaicing, lens blur, noise, fringe response error); 0: the patches as captured
    camera_augment: float = 0.0


def check_aux_classes(n: int, dataset: PatchDataset | None = None) -> None:
    """``n`` (``--aux-classes``) is 0 (no auxiliary head) or a number of material classes >= 2 that covers
    every material label of ``dataset``, which must have some (else the head would never train)."""
    check_aux_class_count(n)
    if n == 0 or dataset is None:
        return
    labels = dataset.labels("material")
    known = labels[labels >= 0]
    if not len(known):
        raise InputError(f"--aux-classes {n}: the training data have no material labels (captured sessions have them "
                         "only with gt/labels, as simulated ones do), so the auxiliary head would never train; leave "
                         "--aux-classes 0")
    if int(known.max()) >= n:
        raise InputError(f"--aux-classes {n} is too few: the training data have material label {int(known.max())} "
                         f"(labels count from 0); give at least {int(known.max()) + 1}")


class FootprintNet(nn.Module):
    """PSP patches -> (footprints, aux logits or None): the encoder's features through the decoder.

    The encoder gets gradients only when ``train_encoder`` (the end-to-end U-Net baseline); one module
    so that DDP sees every trained parameter.
    """

    def __init__(self, encoder: Encoder, decoder: Decoder, *, train_encoder: bool = False) -> None:
        super().__init__()
        self.encoder, self.decoder, self.train_encoder = encoder, decoder, train_encoder

    def forward(self, psp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        with torch.set_grad_enabled(self.train_encoder and torch.is_grad_enabled()):
            bottleneck, skips = self.encoder.features(psp)
        out = self.decoder(bottleneck, skips, psp)
        return (out, None) if isinstance(out, torch.Tensor) else out


@torch.no_grad()
def validate_decoder(enc: Encoder, dec: Decoder, dataset: PatchDataset, n: int, batch_size: int, device: torch.device,
                     log_eps: float = LOG_EPS, capture_model: bool = True) -> dict[str, float]:
    """SBH loss, MSE and PSNR (data range 1) on the first ``n`` patches of a fixed permutation (predictions
    as their targets recorded them with ``capture_model``: :attr:`DecoderConfig.capture_model`)."""
    enc.eval()
    dec.eval()
    idx = np.random.default_rng(0).permutation(len(dataset))[:n]
    net, loss_fn, sums, count = FootprintNet(enc, dec), SBHLoss(log_eps=log_eps), {"val_loss": 0.0, "val_mse": 0.0}, 0
    for i in range(0, len(idx), batch_size):
        b = dataset.batch(idx[i : i + batch_size])
        pred, _ = net(b["psp"].to(device))
        if capture_model:
            pred = as_captured(pred, b["camera"].to(device), b["dot"].to(device))
        target = b["footprint"].to(device)
        sums["val_loss"] += float(loss_fn(pred, target)[0]) * len(target)
        sums["val_mse"] += float(((pred.float() - target) ** 2).mean()) * len(target)
        count += len(target)
    out = {k: v / count for k, v in sums.items()}
    out["val_psnr"] = psnr(max(out["val_mse"], MSE_FLOOR))
    return out


def data_fingerprint(footprints: torch.Tensor, n_patches: int) -> str:
    """What a decoder run was fitted on, in a few bytes: a hash of its seeded sample of target footprints (the same
    sessions, views and pixels give the same) and the number of training patches."""
    import hashlib

    digest = hashlib.sha256(np.ascontiguousarray(footprints.detach().cpu().numpy()).tobytes())
    digest.update(str(n_patches).encode())
    return digest.hexdigest()[:32]


def train_decoder(
    cfg: DecoderConfig,
    encoder_ckpt: Path | str | None,
    dataset: PatchDataset,
    out_dir: Path | str,
    *,
    val: PatchDataset | None = None,
    resume: bool = True,
    progress: StepProgress | bool | None = None,
    preset: ModelPreset | None = None,
) -> Path:
    """Fit the decoder with the SBH loss on a frozen encoder (kept in eval mode: BN stats and dropout fixed).

    ``encoder_ckpt=None`` trains encoder and decoder together from random weights instead: the
    end-to-end supervised U-Net baseline without SSL pretraining (``preset`` or ``cfg.preset`` sizes it).
    """
    check_aux_classes(cfg.aux_classes, dataset)
    out_dir = Path(out_dir)
    d = init_distributed(cfg.device)
    torch.manual_seed(cfg.seed)
    if encoder_ckpt is None:
        p = preset or get_preset(cfg.preset)
        enc = Encoder(p).to(d.device)
    else:
        enc = load_encoder(encoder_ckpt).to(d.device)  # eval mode, frozen; weights checked (finite, fitting)
        p = enc.preset
    cfg = replace(cfg, end_to_end=encoder_ckpt is None, preset=p.name)  # the checkpoint records what ran
    if p.patch != dataset.patch:
        raise DataError(f"the encoder's preset {p.name} expects {p.patch}px patches, the dataset has {dataset.patch}px")
    dec = Decoder(p, out_scale=cfg.out_scale, n_classes=cfg.aux_classes, head=cfg.head).to(d.device)
    if not cfg.learn_gain:
        dec.freeze_gain()  # before DDP wraps it: a fixed gain is no parameter to sync
    physics = dec.physics_parameters()
    net = wrap_ddp(FootprintNet(enc, dec, train_encoder=cfg.end_to_end), d)
    ids = {id(q) for q in physics}
    trained = [*enc.parameters(), *dec.parameters()] if cfg.end_to_end else list(dec.parameters())
    opt = torch.optim.Adam([{"params": [q for q in trained if id(q) not in ids], "lr": cfg.lr},
                            {"params": physics, "lr": cfg.lr * cfg.physics_lr_mult}])
    loop = Loop(cfg, dataset, out_dir, d, "decoder", best=("val_loss", "min") if val is not None else None)

    @functools.cache
    def first_footprints() -> tuple[torch.Tensor, bool]:
        """Footprints of a seeded sample, the same on every rank (shape prior and noise floor), and whether a
        Bayer camera demosaiced any of them; read once (their PSP patches are not kept)."""
        first = np.random.default_rng(cfg.seed).permutation(len(dataset))[:PRIOR_SAMPLES]
        batch = dataset.batch(np.sort(first))
        loop.check_finite(batch)  # a NaN crop here would make every prediction NaN: named as the data's, not the rate's
        return batch["footprint"], bool((batch["camera"] != NO_CAMERA).any())

    ckpt = resume_state(out_dir, resume, "decoder", p)
    data = data_fingerprint(first_footprints()[0], len(dataset))
    if ckpt is not None:
        if ckpt.get("data", data) != data:  # (checkpoints before it was recorded: not checked)
            raise DataError(f"{out_dir / CHECKPOINT} was fitted on other training data than it is given now (sessions "
                            "captured again, or other views or pixels): resuming would fit the rest of the run to "
                            "these; pass --no-resume, or another --out")
        if bool(ckpt["config"].get("end_to_end", False)) != cfg.end_to_end:
            raise DataError(f"{out_dir / CHECKPOINT} is {'an end-to-end' if not cfg.end_to_end else 'a frozen-encoder'} "
                            "decoder run; choose another output folder or pass --no-resume")
        if cfg.end_to_end:
            enc.load_state_dict(ckpt["encoder"])
        elif "encoder" in ckpt and not all(torch.equal(v.to(d.device), enc.state_dict()[k]) for k, v in ckpt["encoder"].items()):
            raise DataError(f"{out_dir / CHECKPOINT} was fitted on other encoder weights than {encoder_ckpt} holds now "
                            "(was the pretraining run continued?): resuming would swap its frozen encoder midway; pass "
                            "--no-resume, or another --out")
        dec.load_state_dict(ckpt["decoder"])
        opt.load_state_dict(ckpt["optimizer"])
        loop.restore(ckpt["loop"])
    else:
        if d.main:
            start_fresh(out_dir)
        if cfg.head == "reciprocal":
            footprints, demosaiced = first_footprints()
            dec.init_shape_prior(footprints.to(d.device), demosaiced=demosaiced)
    noise = noise_floor(first_footprints()[0])  # the camera's, in the training footprints
    if cfg.log_eps is None:  # recorded in the checkpoint's config, so a resumed run uses the same value
        cfg = replace(cfg, log_eps=max(LOG_EPS, noise))
    loss_fn = SBHLoss(log_eps=cfg.log_eps)
    # the footprint widths it learns from, and how far out its targets hold light above their noise: the torch
    # backend hands pixels beyond those widths, and each footprint's rings beyond that radius, to the analytic model
    domain = None
    if d.main:
        domain = replace(training_domain(dataset.views, dataset.patch, seed=cfg.seed),
                         tail_radius=tail_radius(first_footprints()[0].cpu().numpy(), noise)).to_dict()

    def step(batch: dict[str, torch.Tensor], gstep: int) -> dict[str, float]:
        dec.train()
        enc.train(cfg.end_to_end)  # a frozen encoder never leaves eval mode: BN statistics and dropout stay fixed
        psp = batch["psp"]
        if cfg.camera_augment > 0:  # another camera's view of the same light; the target stays what it is
            psp = augment.camera(psp, augment.CameraAugment(p=cfg.camera_augment))
        with autocast_for(d, cfg.amp):
            pred, logits = net(psp)
        if cfg.capture_model:  # the light entering at the pixel, recorded as its target crop was
            pred = as_captured(pred.float(), batch["camera"].to(pred.device), batch["dot"].to(pred.device))
        loss, terms = loss_fn(pred, batch["footprint"])
        if logits is not None:
            known = batch["material"] >= 0
            if known.any():
                aux = nn.functional.cross_entropy(logits[known].float(), batch["material"][known])
                loss = loss + cfg.aux_weight * aux
                terms["aux"] = float(aux.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach()), **terms, "lr": opt.param_groups[0]["lr"]}

    def end_epoch(epoch: int) -> dict[str, float]:
        if val is None or not d.main:
            return {}
        return validate_decoder(enc, dec, val, cfg.val_samples, cfg.batch_size, d.device, cfg.log_eps or LOG_EPS,
                                cfg.capture_model)

    # what its footprints were fitted on ({object: views}): evaluations say when they score it
    trained_on = {o: sorted({int(v.view) for v in dataset.views if v.object == o}) for o in {v.object for v in dataset.views}}

    def save() -> None:
        if d.main:
            save_checkpoint(out_dir / CHECKPOINT, {
                "kind": "decoder", "preset": p.to_dict(), "config": config_dict(cfg),
                "encoder": enc.state_dict(), "decoder": dec.state_dict(),
                "optimizer": opt.state_dict(), "loop": loop.state(), "domain": domain, "trained_on": trained_on,
                "data": data,
            })

    loop.run(step, end_epoch, save, progress=progress)
    return out_dir / CHECKPOINT
