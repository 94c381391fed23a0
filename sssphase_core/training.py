"""Training loops: SimSiam pretraining and decoder fitting, with exact resume, metrics and DDP.

Both loops share :class:`Loop`: a deterministic schedule (the epoch's sample order comes from
``DistributedSampler(seed, epoch)``, and torch's global RNG, which drives augmentations and dropout,
is re-seeded from (seed, global step) before every step), so a run resumed from a checkpoint
reproduces exactly the steps of an uninterrupted one. Checkpoints (``last.pt``) hold plain tensors
and dicts only and are read with ``torch.load(weights_only=True)``; they are written atomically at
the end of every epoch and every ``ckpt_every`` steps, so a run killed mid-epoch loses at most that
many steps. Metrics go to ``metrics.jsonl`` (one row per epoch with the cumulative run time
``wall_s``). Under ``torchrun`` (WORLD_SIZE > 1) the model is wrapped in DDP (gloo on CPU, NCCL on
GPU, SyncBatchNorm on GPU only: PyTorch's SyncBN has no CPU kernel) and rank 0 writes files.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from sssphase_core import augment
from sssphase_core.data import PatchDataset
from sssphase_core.errors import DataError, SssError
from sssphase_core.losses import LOG_EPS, SBHLoss, noise_floor
from sssphase_core.metrics import MSE_FLOOR, psnr
from sssphase_core.models import Decoder, Encoder, ModelPreset, SimSiam, get_preset
from sssphase_core.runlog import METRICS, METRICS_CSV, TB_DIR, RunLog

CHECKPOINT = "last.pt"
BEST = "best.pt"  # the epoch with the best monitored figure (kNN monitor / validation loss)
PRIOR_SAMPLES = 1024  # training footprints averaged into the reciprocal head's initial shape


class TrainingCollapsed(SssError):
    """SimSiam's representation collapsed (constant embeddings); training was stopped."""


class TrainingDiverged(SssError):
    """The loss became NaN or infinite; training stops before the next checkpoint would save it."""


class SimulatedInterrupt(RuntimeError):
    """Raised by ``stop_after_steps`` to emulate a run killed mid-epoch (tests)."""


# --- checkpoints ---------------------------------------------------------------------------------


def save_checkpoint(path: Path, payload: dict) -> None:
    """Atomic ``torch.save`` (write to a temporary file, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def resolve_checkpoint(path: Path | str) -> Path:
    """A run folder means its ``best.pt`` when training kept one, else its ``last.pt``; a file is itself."""
    path = Path(path)
    if path.is_dir():
        return path / BEST if (path / BEST).exists() else path / CHECKPOINT
    return path


def load_checkpoint(path: Path | str) -> dict:
    """Load with ``weights_only=True``: tensors, dicts, lists and numbers only, never arbitrary objects.
    A run folder loads its best checkpoint (:func:`resolve_checkpoint`). Anything that is not a
    sssphase checkpoint (pickled objects, an empty or truncated file, another program's tensors) is
    refused with a :class:`DataError` that says what it is."""
    import pickle

    path = resolve_checkpoint(path)
    if not path.exists():
        raise DataError(f"no checkpoint at {path}")
    if path.is_file() and path.stat().st_size == 0:
        raise DataError(f"cannot read checkpoint {path}: the file is empty")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        with open(path, "rb") as f:
            archive = f.read(4) == b"PK\x03\x04"  # what torch.save writes
        if not archive:
            raise DataError(f"{path} is not a checkpoint file (not written by torch.save)") from None
        raise DataError(f"{path} is not a sssphase checkpoint: it holds pickled Python objects, which are never "
                        "loaded (only tensors, numbers and dicts)") from None
    except Exception as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"cannot read checkpoint {path}: {reason}") from None
    missing = [k for k in ("kind", "preset", "encoder") if not isinstance(ckpt, dict) or k not in ckpt]
    if missing or ckpt.get("kind") not in ("pretrain", "decoder"):
        what = type(ckpt).__name__ if not isinstance(ckpt, dict) else f"a dict without {', '.join(missing) or 'a known kind'}"
        raise DataError(f"{path} is not a sssphase checkpoint ({what}); use a run folder or .pt written by "
                        "`sss train pretrain` or `sss train decoder`")
    return ckpt


def _load_weights(module: nn.Module, state: object, path: Path | str, what: str) -> None:
    try:
        module.load_state_dict(state)  # type: ignore[arg-type]
    except (RuntimeError, TypeError, AttributeError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{path}: the {what} weights do not fit the checkpoint's preset ({reason})") from None


def load_encoder(path: Path | str) -> Encoder:
    """The frozen encoder (eval mode) of a pretraining or decoder checkpoint."""
    ckpt = load_checkpoint(path)
    enc = Encoder(_preset_of(ckpt, path))
    _load_weights(enc, ckpt["encoder"], path, "encoder")
    return enc.eval().requires_grad_(False)


def _preset_of(ckpt: dict, path: Path | str) -> ModelPreset:
    try:
        return get_preset(ckpt["preset"])
    except (SssError, KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: its model preset cannot be read ({exc})") from None


def decoder_patch(encoder_ckpt: Path | str | None, preset: str | ModelPreset) -> int:
    """The footprint size K a decoder trains at: its frozen encoder's, or ``preset``'s end to end (no encoder)."""
    return get_preset(preset).patch if encoder_ckpt is None else load_encoder(encoder_ckpt).preset.patch


def load_decoder(path: Path | str) -> tuple[Encoder, Decoder]:
    """(encoder, decoder) of a decoder checkpoint, both in eval mode."""
    ckpt = load_checkpoint(path)
    if "decoder" not in ckpt:
        raise DataError(f"{path} is a pretraining checkpoint; train a decoder with `sss train decoder`")
    preset = _preset_of(ckpt, path)
    cfg = ckpt.get("config") if isinstance(ckpt.get("config"), dict) else {}  # old checkpoints: the direct head
    enc = Encoder(preset)
    dec = Decoder(preset, n_classes=int(cfg.get("aux_classes", 0)), head=cfg.get("head", "direct"))
    _load_weights(enc, ckpt["encoder"], path, "encoder")
    _load_weights(dec, ckpt["decoder"], path, "decoder")
    return enc.eval().requires_grad_(False), dec.eval()


# --- distributed ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str = "auto") -> Dist:
    """Join the torchrun process group when WORLD_SIZE > 1 (gloo on CPU, NCCL on CUDA)."""
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if use_cuda:
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    else:
        dev = torch.device("cpu")
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo")
    return Dist(rank, world, dev)


def _all_mean(values: dict[str, float], d: Dist) -> dict[str, float]:
    if d.world == 1 or not values:
        return values
    t = torch.tensor(list(values.values()), dtype=torch.float64)
    dist.all_reduce(t)
    return dict(zip(values, (t / d.world).tolist(), strict=True))


def _wrap(model: nn.Module, d: Dist) -> nn.Module:
    if d.world == 1:
        return model
    if d.device.type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
    return nn.parallel.DistributedDataParallel(model, device_ids=[d.device.index] if d.device.type == "cuda" else None)


# --- collapse monitor ------------------------------------------------------------------------------


def projection_std(z: torch.Tensor) -> float:
    """Mean over dimensions of the batch std of L2-normalised projections (healthy ~ 1/sqrt(d), collapse -> 0)."""
    return float(nn.functional.normalize(z.float(), dim=1).std(dim=0).mean())


def effective_rank(x: torch.Tensor) -> float:
    """exp(entropy) of the normalised singular values of centred embeddings (Roy & Vetterli 2007)."""
    s = torch.linalg.svdvals(x.float() - x.float().mean(dim=0))
    p = s / s.sum().clamp_min(1e-12)
    return float(torch.exp(-(p * torch.log(p.clamp_min(1e-12))).sum()))


# --- the shared loop -----------------------------------------------------------------------------


@dataclass
class LoopConfig:
    epochs: int = 10
    batch_size: int = 64
    seed: int = 0
    ckpt_every: int = 50  # steps between mid-epoch checkpoints (0: epoch ends only)
    device: str = "auto"
    amp: bool = True  # bfloat16 autocast on CUDA; ignored on CPU


#: ``progress(task, done, total, info)``: called after every training step (the CLI draws a bar from it).
StepProgress = Callable[[str, int, int, str], None]


class Loop:
    """Epoch/step bookkeeping, exact resume, checkpoints, metrics and progress for one task."""

    def __init__(self, cfg: LoopConfig, dataset: PatchDataset, out_dir: Path, d: Dist, kind: str,
                 best: tuple[str, str] | None = None) -> None:
        """``best``: (metric of the epoch row, "max" or "min"); the best epoch's checkpoint is copied to ``best.pt``."""
        self.cfg, self.dataset, self.out_dir, self.d, self.kind = cfg, dataset, Path(out_dir), d, kind
        self.best_metric = best
        self.best: dict[str, float] = {}  # {"epoch", "value"} of best.pt
        self._new_best = False  # the epoch just staged is the best: copy its checkpoint once saved
        self.sampler = torch.utils.data.DistributedSampler(
            dataset, num_replicas=d.world, rank=d.rank, shuffle=True, seed=cfg.seed, drop_last=True
        )
        self.steps_per_epoch = len(self.sampler) // cfg.batch_size
        if self.steps_per_epoch == 0:
            raise DataError(f"{len(dataset)} patches are fewer than one batch of {cfg.batch_size} per process")
        self.epoch, self.step_in_epoch, self.wall_s = 0, 0, 0.0
        self.sums: dict[str, float] = {}

    @property
    def total_steps(self) -> int:
        return self.cfg.epochs * self.steps_per_epoch

    @property
    def global_step(self) -> int:
        return self.epoch * self.steps_per_epoch + self.step_in_epoch

    def state(self) -> dict:
        return {"epoch": self.epoch, "step_in_epoch": self.step_in_epoch, "wall_s": self.wall_s, "sums": dict(self.sums),
                "best": dict(self.best)}

    def restore(self, state: dict) -> None:
        self.epoch, self.step_in_epoch = int(state["epoch"]), int(state["step_in_epoch"])
        self.wall_s, self.sums = float(state["wall_s"]), dict(state["sums"])
        self.best = dict(state.get("best", {}))

    def _stage_best(self, row: dict) -> None:
        """Note whether this epoch's monitored figure is the best so far (before the checkpoint is saved,
        so that the saved loop state already knows it)."""
        self._new_best = False
        name, mode = self.best_metric  # type: ignore[misc]
        value = row.get(name)
        if value is not None and math.isfinite(value):
            old = self.best.get("value")
            if old is None or (value > old if mode == "max" else value < old):
                self.best, self._new_best = {"epoch": row["epoch"], "value": float(value)}, True
        if self.best:
            row["best_epoch"] = self.best["epoch"]

    def keep_if_best(self) -> None:
        """Copy the checkpoint just written to ``best.pt`` when its epoch was staged as the best."""
        if self._new_best:
            tmp = self.out_dir / (BEST + ".tmp")
            shutil.copyfile(self.out_dir / CHECKPOINT, tmp)
            os.replace(tmp, self.out_dir / BEST)
            self._new_best = False

    def run(
        self,
        step: Callable[[dict[str, torch.Tensor], int], dict[str, float]],
        end_epoch: Callable[[int], dict[str, float]],
        save: Callable[[], None],
        *,
        progress: StepProgress | bool | None = None,
        stop_after_steps: int | None = None,
    ) -> None:
        """Run the remaining steps; ``progress(kind, done, total, info)`` after each (on the main process)."""
        steps_run = 0
        report = progress if callable(progress) and self.d.main else None
        runlog = RunLog(self.out_dir, resume_step=self.global_step, enabled=self.d.main)
        with contextlib.closing(runlog):
            if report is not None:
                report(self.kind, self.global_step, self.total_steps, "")
            while self.epoch < self.cfg.epochs:
                self.sampler.set_epoch(self.epoch)
                order = np.fromiter(iter(self.sampler), dtype=np.int64)
                t0 = time.perf_counter()
                while self.step_in_epoch < self.steps_per_epoch:
                    if stop_after_steps is not None and steps_run >= stop_after_steps:
                        raise SimulatedInterrupt(f"stopped after {steps_run} steps")
                    b = self.cfg.batch_size
                    idx = order[self.step_in_epoch * b : (self.step_in_epoch + 1) * b]
                    torch.manual_seed(self.cfg.seed * 1_000_003 + self.global_step)
                    batch = {k: v.to(self.d.device, non_blocking=True) for k, v in self.dataset.batch(idx).items()}
                    values = step(batch, self.global_step)
                    if not math.isfinite(values["loss"]):
                        raise TrainingDiverged(
                            f"the {self.kind} loss became {values['loss']} at epoch {self.epoch + 1}, step "
                            f"{self.step_in_epoch + 1}; lower the learning rate (the last good checkpoint is kept "
                            f"in {self.out_dir / CHECKPOINT}, which --resume continues from)"
                        )
                    for k, v in values.items():
                        self.sums[k] = self.sums.get(k, 0.0) + v
                    self.step_in_epoch += 1
                    steps_run += 1
                    runlog.step(self.global_step, values)
                    if report is not None:
                        report(self.kind, self.global_step, self.total_steps,
                               f"epoch {self.epoch + 1}/{self.cfg.epochs} loss {self.sums['loss'] / self.step_in_epoch:.4f}")
                    if self.cfg.ckpt_every and steps_run % self.cfg.ckpt_every == 0 and self.step_in_epoch < self.steps_per_epoch:
                        self.wall_s += time.perf_counter() - t0
                        t0 = time.perf_counter()
                        save()
                self.wall_s += time.perf_counter() - t0
                means = _all_mean({k: v / self.steps_per_epoch for k, v in self.sums.items()}, self.d)
                row = {"epoch": self.epoch + 1, "step": self.global_step, **means, **end_epoch(self.epoch)}
                row["wall_s"] = round(self.wall_s, 3)
                self.epoch, self.step_in_epoch, self.sums = self.epoch + 1, 0, {}
                if self.best_metric is not None and self.d.main:
                    self._stage_best(row)
                save()
                self.keep_if_best()
                runlog.epoch(row)
                collapse = row.get("collapsed", 0.0)
                if collapse:
                    raise TrainingCollapsed(
                        f"representation collapsed at epoch {row['epoch']}: std of normalised projections "
                        f"{row['proj_std']:.4g} (healthy ~ {row['proj_std_healthy']:.4g}), effective rank "
                        f"{row['eff_rank']:.1f}; lower the learning rate or lengthen the warmup "
                        f"(checkpoint kept in {self.out_dir / CHECKPOINT})"
                    )
        if self.d.world > 1:
            dist.barrier()  # every rank returns once rank 0 has written the final checkpoint


def _autocast(d: Dist, enabled: bool):
    return torch.autocast(d.device.type, dtype=torch.bfloat16, enabled=enabled and d.device.type == "cuda")


def _config_dict(cfg: object) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()}


def _resume_state(out_dir: Path, resume: bool, kind: str, preset: ModelPreset | None = None) -> dict | None:
    path = out_dir / CHECKPOINT
    if not resume or not path.exists():
        return None
    ckpt = load_checkpoint(path)
    if ckpt.get("kind") != kind:
        raise DataError(f"{path} holds a {ckpt.get('kind')} run, not {kind}; choose another output folder")
    if preset is not None and get_preset(ckpt["preset"]) != preset:
        raise DataError(f"{path} was trained with preset {ckpt['preset']['name']}, not {preset.name}: "
                        "resume with the same preset or pass --no-resume")
    return ckpt


# --- SimSiam pretraining ---------------------------------------------------------------------------


@dataclass
class PretrainConfig(LoopConfig):
    preset: str = "lite"
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


def _start_fresh(out_dir: Path) -> None:
    """A new run in a used folder: the old run's metrics and best checkpoint must not mix with it."""
    for name in (METRICS, METRICS_CSV, BEST):
        (out_dir / name).unlink(missing_ok=True)
    shutil.rmtree(out_dir / TB_DIR, ignore_errors=True)


def lr_at(step: int, total: int, warmup: int, base: float) -> float:
    """Linear warmup over ``warmup`` steps then cosine decay to 0 (no restarts)."""
    if step < warmup:
        return base * (step + 1) / warmup
    t = (step - warmup) / max(1, total - warmup)
    return base * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))


def _knn_monitor_indices(dataset: PatchDataset, n: int, seed: int) -> np.ndarray | None:
    """A fixed, seeded subset of the training patches for the kNN monitor (None: off or one view only)."""
    if n <= 0 or len(np.unique(dataset.labels("view"))) < 2:
        return None
    return np.sort(np.random.default_rng(seed + 7).permutation(len(dataset))[:n])


@torch.no_grad()
def knn_monitor(encoder: Encoder, dataset: PatchDataset, idx: np.ndarray, k: int, device: torch.device) -> float:
    """Object kNN accuracy (cosine, majority vote, view-level leave-one-out) of the frozen embeddings of
    ``idx``: a cheap per-epoch check of representation quality. It uses training patches, so it is a
    monitor; the reported figure is ``sss eval knn`` on fresh patches.
    """
    from sssphase_core.evaluation import knn_leave_one_view_out

    was = encoder.training
    encoder.eval()
    emb = torch.cat([encoder(dataset.batch(idx[i : i + 256])["psp"].to(device)).float().cpu()
                     for i in range(0, len(idx), 256)])
    encoder.train(was)
    res = knn_leave_one_view_out(emb.numpy(), dataset.labels("object")[idx], dataset.labels("view")[idx], k=k)
    return res["overall"]


def pretrain(
    cfg: PretrainConfig,
    dataset: PatchDataset,
    out_dir: Path | str,
    *,
    preset: ModelPreset | None = None,
    resume: bool = True,
    progress: StepProgress | bool | None = None,
    stop_after_steps: int | None = None,
) -> Path:
    """SimSiam pretraining of the encoder; returns the checkpoint path (``out_dir/last.pt``)."""
    out_dir = Path(out_dir)
    d = init_distributed(cfg.device)
    p = preset or get_preset(cfg.preset)
    if p.patch != dataset.patch:
        raise DataError(f"preset {p.name} expects {p.patch}px patches, the dataset has {dataset.patch}px")
    torch.manual_seed(cfg.seed)
    model = SimSiam(p).to(d.device)
    net = _wrap(model, d)
    pred_params = list(model.predictor.parameters())
    pred_ids = {id(q) for q in pred_params}
    groups = [
        {"params": [q for q in model.parameters() if id(q) not in pred_ids], "fix": False},
        {"params": pred_params, "fix": cfg.fix_pred_lr},
    ]
    opt = torch.optim.SGD(groups, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    loop = Loop(cfg, dataset, out_dir, d, "pretrain", best=("knn_acc", "max") if cfg.knn_monitor else None)
    ckpt = _resume_state(out_dir, resume, "pretrain", p)
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        loop.restore(ckpt["loop"])
    elif d.main:
        _start_fresh(out_dir)
    warmup = max(1, round(cfg.warmup_epochs * loop.steps_per_epoch))
    monitor: dict[str, list[torch.Tensor]] = {"z": [], "y": []}

    def step(batch: dict[str, torch.Tensor], gstep: int) -> dict[str, float]:
        lr = lr_at(gstep, loop.total_steps, warmup, cfg.lr)
        for g in opt.param_groups:
            g["lr"] = cfg.lr if g["fix"] else lr
        model.train()
        x1, x2 = augment.two_views(batch["psp"], cfg.augment)
        with _autocast(d, cfg.amp):
            out = net(x1, x2)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()
        if sum(len(t) for t in monitor["z"]) < cfg.monitor_samples:
            monitor["z"].append(out["projection"].float().cpu())
            monitor["y"].append(out["embedding"].float().cpu())
        return {"loss": float(out["loss"].detach()), "lr": lr}

    knn_idx = _knn_monitor_indices(dataset, cfg.knn_monitor, cfg.seed)

    def end_epoch(epoch: int) -> dict[str, float]:
        z, y = torch.cat(monitor["z"]), torch.cat(monitor["y"])
        monitor["z"].clear()
        monitor["y"].clear()
        healthy = 1.0 / math.sqrt(z.shape[1])
        stats = _all_mean({"proj_std": projection_std(z), "eff_rank": effective_rank(y)}, d)
        stats["proj_std_healthy"] = healthy
        stats["collapsed"] = float(stats["proj_std"] < cfg.collapse_std_frac * healthy)
        if knn_idx is not None:  # every rank computes the same number (same weights, same patches)
            stats["knn_acc"] = knn_monitor(model.encoder, dataset, knn_idx, cfg.knn_k, d.device)
        return stats

    def save() -> None:
        if d.main:
            save_checkpoint(out_dir / CHECKPOINT, {
                "kind": "pretrain", "preset": p.to_dict(), "config": _config_dict(cfg),
                "model": model.state_dict(), "encoder": model.encoder.state_dict(),
                "optimizer": opt.state_dict(), "loop": loop.state(),
            })

    loop.run(step, end_epoch, save, progress=progress, stop_after_steps=stop_after_steps)
    return out_dir / CHECKPOINT


# --- decoder -------------------------------------------------------------------------------------


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
                     log_eps: float = LOG_EPS) -> dict[str, float]:
    """SBH loss, MSE and PSNR (data range 1) on the first ``n`` patches of a fixed permutation."""
    enc.eval()
    dec.eval()
    idx = np.random.default_rng(0).permutation(len(dataset))[:n]
    net, loss_fn, sums, count = FootprintNet(enc, dec), SBHLoss(log_eps=log_eps), {"val_loss": 0.0, "val_mse": 0.0}, 0
    for i in range(0, len(idx), batch_size):
        b = dataset.batch(idx[i : i + batch_size])
        pred, _ = net(b["psp"].to(device))
        target = b["footprint"].to(device)
        sums["val_loss"] += float(loss_fn(pred, target)[0]) * len(target)
        sums["val_mse"] += float(((pred.float() - target) ** 2).mean()) * len(target)
        count += len(target)
    out = {k: v / count for k, v in sums.items()}
    out["val_psnr"] = psnr(max(out["val_mse"], MSE_FLOOR))
    return out


def train_decoder(
    cfg: DecoderConfig,
    encoder_ckpt: Path | str | None,
    dataset: PatchDataset,
    out_dir: Path | str,
    *,
    val: PatchDataset | None = None,
    resume: bool = True,
    progress: StepProgress | bool | None = None,
    stop_after_steps: int | None = None,
    preset: ModelPreset | None = None,
) -> Path:
    """Fit the decoder with the SBH loss on a frozen encoder (kept in eval mode: BN stats and dropout fixed).

    ``encoder_ckpt=None`` trains encoder and decoder together from random weights instead: the
    end-to-end supervised U-Net baseline without SSL pretraining (``preset`` or ``cfg.preset`` sizes it).
    """
    out_dir = Path(out_dir)
    d = init_distributed(cfg.device)
    torch.manual_seed(cfg.seed)
    if encoder_ckpt is None:
        p = preset or get_preset(cfg.preset)
        enc = Encoder(p).to(d.device)
    else:
        src = load_checkpoint(encoder_ckpt)
        p = get_preset(src["preset"])
        enc = Encoder(p)
        enc.load_state_dict(src["encoder"])
        enc = enc.to(d.device).eval().requires_grad_(False)
    cfg = replace(cfg, end_to_end=encoder_ckpt is None, preset=p.name)  # the checkpoint records what ran
    if p.patch != dataset.patch:
        raise DataError(f"the encoder's preset {p.name} expects {p.patch}px patches, the dataset has {dataset.patch}px")
    dec = Decoder(p, out_scale=cfg.out_scale, n_classes=cfg.aux_classes, head=cfg.head).to(d.device)
    if not cfg.learn_gain:
        dec.freeze_gain()  # before DDP wraps it: a fixed gain is no parameter to sync
    physics = dec.physics_parameters()
    net = _wrap(FootprintNet(enc, dec, train_encoder=cfg.end_to_end), d)
    ids = {id(q) for q in physics}
    trained = [*enc.parameters(), *dec.parameters()] if cfg.end_to_end else list(dec.parameters())
    opt = torch.optim.Adam([{"params": [q for q in trained if id(q) not in ids], "lr": cfg.lr},
                            {"params": physics, "lr": cfg.lr * cfg.physics_lr_mult}])
    loop = Loop(cfg, dataset, out_dir, d, "decoder", best=("val_loss", "min") if val is not None else None)

    @functools.cache
    def first_footprints() -> torch.Tensor:
        """Footprints of a seeded sample, the same on every rank (shape prior and noise floor); read once."""
        first = np.random.default_rng(cfg.seed).permutation(len(dataset))[:PRIOR_SAMPLES]
        return dataset.batch(np.sort(first))["footprint"]

    ckpt = _resume_state(out_dir, resume, "decoder", p)
    if ckpt is not None:
        if bool(ckpt["config"].get("end_to_end", False)) != cfg.end_to_end:
            raise DataError(f"{out_dir / CHECKPOINT} is {'an end-to-end' if not cfg.end_to_end else 'a frozen-encoder'} "
                            "decoder run; choose another output folder or pass --no-resume")
        if cfg.end_to_end:
            enc.load_state_dict(ckpt["encoder"])
        dec.load_state_dict(ckpt["decoder"])
        opt.load_state_dict(ckpt["optimizer"])
        loop.restore(ckpt["loop"])
    else:
        if d.main:
            _start_fresh(out_dir)
        if cfg.head == "reciprocal":
            dec.init_shape_prior(first_footprints().to(d.device))
    if cfg.log_eps is None:  # recorded in the checkpoint's config, so a resumed run uses the same value
        cfg = replace(cfg, log_eps=max(LOG_EPS, noise_floor(first_footprints())))
    loss_fn = SBHLoss(log_eps=cfg.log_eps)

    def step(batch: dict[str, torch.Tensor], gstep: int) -> dict[str, float]:
        dec.train()
        enc.train(cfg.end_to_end)  # a frozen encoder never leaves eval mode: BN statistics and dropout stay fixed
        with _autocast(d, cfg.amp):
            pred, logits = net(batch["psp"])
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
        return validate_decoder(enc, dec, val, cfg.val_samples, cfg.batch_size, d.device, cfg.log_eps or LOG_EPS)

    def save() -> None:
        if d.main:
            save_checkpoint(out_dir / CHECKPOINT, {
                "kind": "decoder", "preset": p.to_dict(), "config": _config_dict(cfg),
                "encoder": enc.state_dict(), "decoder": dec.state_dict(),
                "optimizer": opt.state_dict(), "loop": loop.state(),
            })

    loop.run(step, end_epoch, save, progress=progress, stop_after_steps=stop_after_steps)
    return out_dir / CHECKPOINT
