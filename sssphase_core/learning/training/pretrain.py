"""SimSiam pretraining with the PSP augmentations: warmup-cosine schedule, collapse monitor, kNN monitor."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sssphase_core.errors import DataError
from sssphase_core.learning import augment
from sssphase_core.learning.data import PatchDataset
from sssphase_core.learning.inputs import check_pretrain_options
from sssphase_core.learning.models import Encoder, ModelPreset, SimSiam, get_preset
from sssphase_core.learning.training.checkpoints import CHECKPOINT, save_checkpoint
from sssphase_core.learning.training.loop import (
    Loop,
    LoopConfig,
    StepProgress,
    all_mean,
    autocast_for,
    config_dict,
    init_distributed,
    resume_state,
    start_fresh,
    wrap_ddp,
)


def projection_std(z: torch.Tensor) -> float:
    """Mean over dimensions of the batch std of L2-normalised projections (healthy ~ 1/sqrt(d), collapse -> 0)."""
    return float(nn.functional.normalize(z.float(), dim=1).std(dim=0).mean())


def effective_rank(x: torch.Tensor) -> float:
    """exp(entropy) of the normalised singular values of centred embeddings (Roy & Vetterli 2007)."""
    s = torch.linalg.svdvals(x.float() - x.float().mean(dim=0))
    p = s / s.sum().clamp_min(1e-12)
    return float(torch.exp(-(p * torch.log(p.clamp_min(1e-12))).sum()))


@dataclass
class PretrainConfig(LoopConfig):
    preset: str = "lite"
    # SimSiam resumed bit-exact on an H200 with CUDA's default kernels; deterministic ones ran it 3.9x slower
    deterministic: bool = False
    lr: float = 0.05  # not scaled with the batch size (the paper)
    momentum: float = 0.9
    weight_decay: float = 1e-4
    warmup_epochs: float = 2.0  # linear warmup, then cosine decay to 0 (paper: 20 of its epochs)
    fix_pred_lr: bool = True  # the predictor keeps the base lr (SimSiam's recommendation; kept kNN rising here)
    augment: str = "psp"  # psp (weak/strong) or imagenet
    collapse_std_frac: float = 0.1  # collapse when proj std < frac / sqrt(d)
    monitor_samples: int = 2048
    knn_monitor: int = 2000  # training patches in the end-of-epoch kNN monitor (view-level leave-one-out; 0: off)
    knn_k: int = 20
    # weight of the projections' decorrelation term (VICReg's covariance term) against SimSiam's dimensional collapse;
    # 0: SimSiam alone. At the demo's budget it took the kNN from 79-87% to 94-97% over four seeds (learning.md)
    decorrelate: float = 1.0
    # the psp strong view also moves the fringes by a random phase (augment.phase_shift; not the paper's): with the
    # scale-free encoder it took the demo's kNN from 94.3% to 96.0% on average over eight seeds (learning.md)
    phase_shift: bool = True


def warmup_cosine(opt: torch.optim.Optimizer, total: int, warmup: int, base_lr: float,
                  start: int = 0) -> torch.optim.lr_scheduler.LambdaLR:
    """Per-step schedule: linear warmup over ``warmup`` steps, then cosine decay to 0 at ``total`` (no
    restarts); parameter groups marked ``fix`` keep ``base_lr`` (SimSiam's predictor). ``start``: the
    global step a resumed run continues from (the schedule is a function of the step, nothing to save)."""

    def factor(step: int) -> float:
        step += start
        if step < warmup:
            return (step + 1) / warmup
        t = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(1.0, t)))

    for g in opt.param_groups:  # a resumed optimizer holds the last scheduled rate: restart from the base
        g["lr"] = base_lr
        g.pop("initial_lr", None)
    return torch.optim.lr_scheduler.LambdaLR(opt, [(lambda _: 1.0) if g.get("fix") else factor for g in opt.param_groups])


def knn_monitor_indices(dataset: PatchDataset, n: int, seed: int) -> np.ndarray | None:
    """A fixed, seeded subset of the training patches for the kNN monitor (None: off, or nothing to monitor:
    fewer than two objects seen in two or more views (leaving out the only view of an object leaves nothing of it
    to match, and a one-class vote is always right))."""
    if n <= 0:
        return None
    from sssphase_core.learning.evaluation import scorable_classes

    idx = np.sort(np.random.default_rng(seed + 7).permutation(len(dataset))[:n])
    return idx if len(scorable_classes(dataset.labels("object")[idx], dataset.labels("view")[idx])) >= 2 else None


#: Training patches whose batch statistics replace BatchNorm's running averages at each epoch's end.
PRECISE_BN_PATCHES = 8192


@torch.no_grad()
def precise_batchnorm(encoder: nn.Module, dataset: PatchDataset, n: int, batch_size: int, seed: int,
                      device: torch.device) -> None:
    """Recompute the encoder's BatchNorm running means and variances as the average over batches of ``n`` training
    patches (seeded, shuffled, as captured: the distribution the frozen encoder then embeds), in place of the
    exponential averages the last ~10 training batches of augmented views dominate ("precise BN", Wu & Johnson
    2021). Eval-mode embeddings then follow the weights, not the last steps' noise: on the demo's captures the
    kNN rose on all nine runs measured (+0.05 to +0.52 points, learning.md). Dropout is off while they are gathered,
    as when the encoder is used. Training itself uses batch statistics: nothing else changes, and a resumed run
    recomputes the same values."""
    bns = [m for m in encoder.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not bns or len(dataset) < 2:
        return
    idx = np.random.default_rng(seed + 11).permutation(len(dataset))[:n]
    momenta, was = [m.momentum for m in bns], encoder.training
    encoder.eval()  # dropout off, as the frozen encoder runs (it drew from the RNG and widened out_bn's input)
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # a cumulative average over the batches
        m.train()
    for i in range(0, len(idx) - 1, batch_size):  # (a last batch of one patch has no variance)
        encoder(dataset.batch(idx[i : i + batch_size])["psp"].to(device))
    for m, momentum in zip(bns, momenta, strict=True):
        m.momentum = momentum
    encoder.train(was)


@torch.no_grad()
def knn_monitor(encoder: Encoder, dataset: PatchDataset, idx: np.ndarray, k: int, device: torch.device) -> float:
    """Object kNN accuracy (cosine, majority vote, view-level leave-one-out) of the frozen embeddings of
    ``idx``: a cheap per-epoch check of representation quality. It uses training patches, so it is a
    monitor; the reported figure is ``sss eval knn`` on fresh patches.
    """
    from sssphase_core.learning.evaluation import knn_leave_one_view_out

    was = encoder.training
    encoder.eval()
    emb = torch.cat([encoder(dataset.batch(idx[i : i + 256])["psp"].to(device)).float().cpu()
                     for i in range(0, len(idx), 256)])
    encoder.train(was)
    res = knn_leave_one_view_out(emb.numpy(), dataset.labels("object")[idx], dataset.labels("view")[idx], k=k)
    return res["overall"]


def initial_encoder(path: Path | str) -> Encoder:
    """The encoder a pretraining checkpoint's run started from (eval mode): its seeded random initialisation,
    rebuilt as :func:`pretrain` builds it (the baseline its kNN is compared with). Torch's global RNG is left
    as it was."""
    from sssphase_core.learning.training.checkpoints import load_checkpoint

    ckpt = load_checkpoint(path, mmap=True)
    if ckpt.get("kind") != "pretrain":
        raise DataError(f"{path}: not a pretraining checkpoint, so its initial encoder is unknown")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(ckpt.get("config", {}).get("seed", 0)))
        encoder = SimSiam(get_preset(ckpt["preset"])).encoder
    return encoder.eval().requires_grad_(False)


def pretrain(
    cfg: PretrainConfig,
    dataset: PatchDataset,
    out_dir: Path | str,
    *,
    preset: ModelPreset | None = None,
    resume: bool = True,
    progress: StepProgress | bool | None = None,
) -> Path:
    """SimSiam pretraining of the encoder; returns the checkpoint path (``out_dir/last.pt``)."""
    check_pretrain_options(cfg.batch_size, cfg.warmup_epochs, cfg.augment, cfg.decorrelate)
    out_dir = Path(out_dir)
    d = init_distributed(cfg.device)
    p = preset or get_preset(cfg.preset)
    if p.patch != dataset.patch:
        raise DataError(f"preset {p.name} expects {p.patch}px patches, the dataset has {dataset.patch}px")
    torch.manual_seed(cfg.seed)
    model = SimSiam(p).to(d.device)
    net = wrap_ddp(model, d)
    pred_params = list(model.predictor.parameters())
    pred_ids = {id(q) for q in pred_params}
    groups = [
        {"params": [q for q in model.parameters() if id(q) not in pred_ids], "fix": False},
        {"params": pred_params, "fix": cfg.fix_pred_lr},
    ]
    opt = torch.optim.SGD(groups, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    loop = Loop(cfg, dataset, out_dir, d, "pretrain", best=("knn_acc", "max") if cfg.knn_monitor else None)
    ckpt = resume_state(out_dir, resume, "pretrain", p)
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        loop.restore(ckpt["loop"])
    elif d.main:
        start_fresh(out_dir)
    warmup = max(1, round(cfg.warmup_epochs * loop.steps_per_epoch))
    schedule = warmup_cosine(opt, loop.total_steps, warmup, cfg.lr, start=loop.global_step)
    monitor: dict[str, list[torch.Tensor]] = {"z": [], "y": []}
    augment_cfg = augment.AugmentConfig(phase_shift_p=1.0 if cfg.phase_shift else 0.0)

    def step(batch: dict[str, torch.Tensor], gstep: int) -> dict[str, float]:
        lr = opt.param_groups[0]["lr"]  # the backbone's (group 0): the scheduled one
        model.train()
        x1, x2 = augment.two_views(batch["psp"], cfg.augment, augment_cfg)
        with autocast_for(d, cfg.amp):
            out = net(x1, x2, cfg.decorrelate)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()
        schedule.step()
        if sum(len(t) for t in monitor["z"]) < cfg.monitor_samples:
            monitor["z"].append(out["projection"].float().cpu())
            monitor["y"].append(out["embedding"].float().cpu())
        values = {"loss": float(out["loss"].detach()), "lr": lr}
        if "decorrelation" in out:
            values["decorrelation"] = float(out["decorrelation"].detach())
        return values

    knn_idx = knn_monitor_indices(dataset, cfg.knn_monitor, cfg.seed)
    # the baseline measured in the same run: the monitor on the encoder before any step (its random initialisation),
    # kept in the checkpoint so that a run resumed before its first epoch ended still reports it
    knn_initial = (ckpt or {}).get("knn_initial")
    if knn_idx is not None and knn_initial is None and loop.global_step == 0:
        knn_initial = knn_monitor(model.encoder, dataset, knn_idx, cfg.knn_k, d.device)

    def end_epoch(epoch: int) -> dict[str, float]:
        z, y = torch.cat(monitor["z"]), torch.cat(monitor["y"])
        monitor["z"].clear()
        monitor["y"].clear()
        healthy = 1.0 / math.sqrt(z.shape[1])
        stats = all_mean({"proj_std": projection_std(z), "eff_rank": effective_rank(y)}, d)
        stats["proj_std_healthy"] = healthy
        stats["collapsed"] = float(stats["proj_std"] < cfg.collapse_std_frac * healthy)
        precise_batchnorm(model.encoder, dataset, PRECISE_BN_PATCHES, cfg.batch_size, cfg.seed, d.device)
        if knn_idx is not None:  # every rank computes the same number (same weights, same patches)
            stats["knn_acc"] = knn_monitor(model.encoder, dataset, knn_idx, cfg.knn_k, d.device)
            if knn_initial is not None and epoch == 0:  # once, in the first epoch's row
                stats["knn_initial"] = knn_initial
        return stats

    def save() -> None:
        if d.main:
            save_checkpoint(out_dir / CHECKPOINT, {
                "kind": "pretrain", "preset": p.to_dict(), "config": config_dict(cfg),
                "model": model.state_dict(), "encoder": model.encoder.state_dict(),
                "optimizer": opt.state_dict(), "loop": loop.state(), "knn_initial": knn_initial,
            })

    loop.run(step, end_epoch, save, progress=progress)
    return out_dir / CHECKPOINT
