"""The loop both trainings share: deterministic order and RNG per step (exact resume), checkpoints
every ``ckpt_every`` steps and epoch, metrics, progress callbacks and DDP under ``torchrun``."""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from sssphase_core.compute import compute_device
from sssphase_core.errors import DataError, InputError, SssError
from sssphase_core.learning.data import PatchDataset
from sssphase_core.learning.models import ModelPreset, get_preset
from sssphase_core.learning.runlog import METRICS, METRICS_CSV, TB_DIR, RunLog
from sssphase_core.learning.training.checkpoints import BEST, CHECKPOINT, load_checkpoint
from sssphase_core.store.files import atomic_path


class TrainingCollapsed(SssError):
    """SimSiam's representation collapsed (constant embeddings); training was stopped."""


class TrainingStopped(KeyboardInterrupt):
    """Training stopped between two steps when asked (Ctrl-C, SIGTERM), after saving a checkpoint at that step."""

    def __init__(self, step: int, total: int, checkpoint: Path) -> None:
        super().__init__(f"stopped at step {step} of {total}; saved {checkpoint}")
        self.step, self.total, self.checkpoint = step, total, checkpoint


class TrainingDiverged(SssError):
    """The loss became NaN or infinite; training stops before the next checkpoint would save it."""


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
    use_cuda = compute_device(device).type == "cuda"
    from sssphase_core.settings import env_count

    world = env_count("WORLD_SIZE", 1, minimum=1)
    rank = env_count("RANK", 0)
    if rank >= world:
        raise InputError(f"RANK={rank} is not below WORLD_SIZE={world} (torchrun sets both; unset them to run alone)")
    if use_cuda:
        # cuBLAS reads its workspace size once per process: deterministic kernels (LoopConfig.deterministic)
        # need this one set before the first matrix product
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        local = env_count("LOCAL_RANK", 0)
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    else:
        dev = torch.device("cpu")
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo")
        # left to the interpreter's teardown, gloo's threads can abort the process ("terminate called without an
        # active exception": a torchrun test's rank exited -6 once, with both cores busy)
        atexit.register(_destroy_process_group)
    return Dist(rank, world, dev)


def _destroy_process_group() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def all_mean(values: dict[str, float], d: Dist) -> dict[str, float]:
    if d.world == 1 or not values:
        return values
    t = torch.tensor(list(values.values()), dtype=torch.float64)
    dist.all_reduce(t)
    return dict(zip(values, (t / d.world).tolist(), strict=True))


def wrap_ddp(model: nn.Module, d: Dist) -> nn.Module:
    if d.world == 1:
        return model
    if d.device.type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
    return nn.parallel.DistributedDataParallel(model, device_ids=[d.device.index] if d.device.type == "cuda" else None)


@dataclass
class LoopConfig:
    epochs: int = 10
    batch_size: int = 64
    seed: int = 0
    ckpt_every: int = 50  # steps between mid-epoch checkpoints (0: epoch ends only)
    device: str = "auto"
    amp: bool = True  # bfloat16 autocast on CUDA; ignored on CPU
    prefetch: bool | None = None  # build the next batch on a worker thread during the step (None: off the CPU)
    stacks_on_device: bool | None = None  # crop patches on the device (None: on CUDA when the stacks fit)
    deterministic: bool = True  # CUDA: deterministic kernels, so a resumed run ends bit-identical (CPU: always are)
    #: seconds this call may train: it ends at the first epoch end after which one more epoch (at this call's
    #: mean epoch time) would pass them; None: every epoch. The checkpoint is the last finished epoch's, so a
    #: rerun with ``resume`` continues; the run's own schedule (sized to ``epochs``) is left as it is.
    time_limit_s: float | None = None


#: ``stacks_on_device=None`` moves the PSP view stacks to a CUDA device when they take at most this share
#: of its free memory.
STACK_MEMORY_SHARE = 0.25


def place_stacks(dataset: PatchDataset, device: torch.device, wanted: bool | None) -> bool:
    """Copy ``dataset``'s PSP view stacks to ``device`` when ``wanted`` (None: on CUDA when they fit in
    :data:`STACK_MEMORY_SHARE` of its free memory); returns whether patches are now cropped there."""
    if wanted is False or device.type == "cpu" or (wanted is None and device.type != "cuda"):
        return False
    if wanted is None and dataset.stack_bytes > STACK_MEMORY_SHARE * torch.cuda.mem_get_info(device)[0]:
        return False
    dataset.place(device)
    return True


@contextlib.contextmanager
def stop_between_steps(enabled: bool) -> Iterator[threading.Event]:
    """While training: the first Ctrl-C or SIGTERM only sets the event the loop checks after each step, so that it
    saves a checkpoint at that step before it stops (an interrupt lost every step since the last checkpoint: all of
    them before the first); a second one interrupts at once. A plain event where signals cannot be taken (not the
    main thread) or must not be (several processes: each would stop at another step)."""
    asked = threading.Event()
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield asked
        return
    kinds = (signal.SIGINT, signal.SIGTERM)
    before = {k: signal.getsignal(k) for k in kinds}

    def ask(signum: int, frame: object) -> None:
        if asked.is_set():  # the second: at once
            for k in kinds:
                signal.signal(k, before[k])
            raise KeyboardInterrupt
        asked.set()
        with contextlib.suppress(OSError, ValueError):  # (a closed stderr)
            sys.stderr.write("\nstopping after this step to save a checkpoint there (again to stop at once)\n")
            sys.stderr.flush()

    for k in kinds:
        signal.signal(k, ask)
    try:
        yield asked
    finally:
        for k in kinds:
            signal.signal(k, before[k])


@contextlib.contextmanager
def deterministic_kernels(device: torch.device, enabled: bool = True) -> Iterator[None]:
    """Within the block, CUDA uses deterministic kernels where it has them (cuDNN's convolutions, the
    backward of gather and of reflection padding, ...), so the same steps give the same weights: an
    interrupted run resumes to exactly what an uninterrupted one ends with. An op with no deterministic
    kernel warns (it is not refused). The previous setting is restored on exit. CPU kernels are
    deterministic already: nothing changes there."""
    if device.type != "cuda" or not enabled:
        yield
        return
    was, was_warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was, warn_only=was_warn)


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
        self.prefetch = d.device.type != "cpu" if cfg.prefetch is None else cfg.prefetch

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
            with atomic_path(self.out_dir / BEST) as tmp:
                shutil.copyfile(self.out_dir / CHECKPOINT, tmp)
            self._new_best = False

    def check_finite(self, batch: dict[str, torch.Tensor]) -> None:
        """Raise DataError naming the views whose crops in ``batch`` (its psp and footprint) hold NaN/inf."""
        bad = torch.zeros(len(batch["object"]), dtype=torch.bool)
        for key in ("psp", "footprint"):
            if key in batch:
                bad |= ~torch.isfinite(batch[key].flatten(1)).all(dim=1).cpu()
        if bad.any():
            where = sorted({(self.dataset.classes[int(o)], int(v)) for o, v in zip(batch["object"][bad], batch["view"][bad],
                                                                                     strict=True)})
            raise DataError(f"the {self.kind} training data hold NaN or infinite values ("
                            f"{', '.join(f'{o} view {v}' for o, v in where)}; psp or footprint crops): re-capture or "
                            "leave those views out")

    def _diverged(self, batch: dict[str, torch.Tensor], loss: float) -> None:
        """Raise for a non-finite loss: DataError naming the views when the batch itself holds NaN/inf (the
        footprint crops, say: :meth:`check_finite`), else TrainingDiverged (the learning rate)."""
        self.check_finite(batch)
        kept = self.out_dir / CHECKPOINT
        raise TrainingDiverged(
            f"the {self.kind} loss became {loss} at epoch {self.epoch + 1}, step {self.step_in_epoch + 1}; lower the "
            "learning rate" + (f" (the last good checkpoint is kept in {kept}, which --resume continues from)"
                               if kept.exists() else " (no checkpoint was written yet)"))

    def _out_of_time(self, elapsed: float, epochs_run: int) -> bool:
        """Whether another epoch would end past ``time_limit_s`` (every rank agrees: rank 0's clock decides)."""
        limit = self.cfg.time_limit_s
        if limit is None or self.epoch >= self.cfg.epochs:
            return False
        stop = torch.tensor([float(elapsed + elapsed / epochs_run > limit)])
        if self.d.world > 1:
            stop = stop.to(self.d.device)
            dist.broadcast(stop, 0)
        return bool(stop.item())

    def _load(self, idx: np.ndarray) -> dict[str, torch.Tensor]:
        return {k: v.to(self.d.device, non_blocking=True) for k, v in self.dataset.batch(idx).items()}

    def run(
        self,
        step: Callable[[dict[str, torch.Tensor], int], dict[str, float]],
        end_epoch: Callable[[int], dict[str, float]],
        save: Callable[[], None],
        *,
        progress: StepProgress | bool | None = None,
    ) -> None:
        """Run the remaining steps; ``progress(kind, done, total, info)`` after each (on the main process).
        An interrupt (Ctrl-C) between steps loses only the steps since the last checkpoint. With
        ``prefetch`` the next batch is built on a worker thread while the device runs the step; each
        epoch's row records ``data_wait_s``, the time the loop waited for batches."""
        steps_run, started, epochs_run = 0, time.perf_counter(), 0
        report = progress if callable(progress) and self.d.main else None
        runlog = RunLog(self.out_dir, resume_step=self.global_step, enabled=self.d.main)
        with contextlib.ExitStack() as cleanup:  # left in reverse: pending batch, device stacks, run log
            cleanup.enter_context(contextlib.closing(runlog))
            stop = cleanup.enter_context(stop_between_steps(self.d.world == 1))
            cleanup.enter_context(deterministic_kernels(self.d.device, self.cfg.deterministic))
            if place_stacks(self.dataset, self.d.device, self.cfg.stacks_on_device):
                cleanup.callback(self.dataset.place, None)  # the caller's dataset crops on the host again
            pool = cleanup.enter_context(ThreadPoolExecutor(1, thread_name_prefix="sss-batches")) if self.prefetch else None
            if report is not None:
                report(self.kind, self.global_step, self.total_steps, "")
            while self.epoch < self.cfg.epochs:
                self.sampler.set_epoch(self.epoch)
                order = np.fromiter(iter(self.sampler), dtype=np.int64)
                batch_at = order[: self.steps_per_epoch * self.cfg.batch_size].reshape(self.steps_per_epoch, -1)
                pending: Future | None = None
                t0, data_wait = time.perf_counter(), 0.0
                while self.step_in_epoch < self.steps_per_epoch:
                    t_data = time.perf_counter()
                    batch = pending.result() if pending is not None else self._load(batch_at[self.step_in_epoch])
                    pending = None
                    if pool is not None and self.step_in_epoch + 1 < self.steps_per_epoch:
                        pending = pool.submit(self._load, batch_at[self.step_in_epoch + 1])
                    data_wait += time.perf_counter() - t_data
                    torch.manual_seed(self.cfg.seed * 1_000_003 + self.global_step)
                    values = step(batch, self.global_step)
                    if not math.isfinite(values["loss"]):
                        self._diverged(batch, values["loss"])
                    for k, v in values.items():
                        self.sums[k] = self.sums.get(k, 0.0) + v
                    self.step_in_epoch += 1
                    steps_run += 1
                    runlog.step(self.global_step, values)
                    if report is not None:
                        report(self.kind, self.global_step, self.total_steps,
                               f"epoch {self.epoch + 1}/{self.cfg.epochs} loss {self.sums['loss'] / self.step_in_epoch:.4f}")
                    if stop.is_set() and self.step_in_epoch < self.steps_per_epoch:  # (an epoch's end saves below)
                        self.wall_s += time.perf_counter() - t0
                        save()
                        raise TrainingStopped(self.global_step, self.total_steps, self.out_dir / CHECKPOINT)
                    if self.cfg.ckpt_every and steps_run % self.cfg.ckpt_every == 0 and self.step_in_epoch < self.steps_per_epoch:
                        self.wall_s += time.perf_counter() - t0
                        t0 = time.perf_counter()
                        save()
                self.wall_s += time.perf_counter() - t0
                means = all_mean({k: v / self.steps_per_epoch for k, v in self.sums.items()}, self.d)
                row = {"epoch": self.epoch + 1, "step": self.global_step, **means, **end_epoch(self.epoch)}
                row["wall_s"] = round(self.wall_s, 3)
                row["data_wait_s"] = round(data_wait, 3)
                self.epoch, self.step_in_epoch, self.sums = self.epoch + 1, 0, {}
                if self.best_metric is not None and self.d.main:
                    self._stage_best(row)
                runlog.epoch(row)  # before the checkpoint: an interrupt between the two loses no row (it is rewritten)
                save()
                self.keep_if_best()
                epochs_run += 1
                collapse = row.get("collapsed", 0.0)
                if collapse:
                    raise TrainingCollapsed(
                        f"representation collapsed at epoch {row['epoch']}: std of normalised projections "
                        f"{row['proj_std']:.4g} (healthy ~ {row['proj_std_healthy']:.4g}), effective rank "
                        f"{row['eff_rank']:.1f}; lower the learning rate or lengthen the warmup "
                        f"(checkpoint kept in {self.out_dir / CHECKPOINT})"
                    )
                if stop.is_set() and self.epoch < self.cfg.epochs:  # asked at the epoch's last step: saved above
                    raise TrainingStopped(self.global_step, self.total_steps, self.out_dir / CHECKPOINT)
                if self._out_of_time(time.perf_counter() - started, epochs_run):
                    break
        if self.d.world > 1:
            dist.barrier()  # every rank returns once rank 0 has written the final checkpoint


def autocast_for(d: Dist, enabled: bool):
    return torch.autocast(d.device.type, dtype=torch.bfloat16, enabled=enabled and d.device.type == "cuda")


def config_dict(cfg: object) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()}


def check_run_folder(out_dir: Path, kind: str) -> dict | None:
    """Refuse an output folder that is a session, or that holds a run of another kind (a new run, resumed
    or not, would overwrite it); returns the folder's checkpoint of this kind, or None."""
    if (out_dir / "manifest.json").exists():
        raise DataError(f"{out_dir} is a session folder: choose another output folder for the run")
    path = out_dir / CHECKPOINT
    if not path.exists():
        _refuse_files_of_another(out_dir, kind)
        return None
    ckpt = load_checkpoint(path, mmap=True)  # mapped: only the kind is looked at, no tensor is read
    if ckpt.get("kind") != kind:
        raise DataError(f"{path} holds a {ckpt.get('kind')} run, not {kind}; choose another output folder")
    return ckpt


#: What a run writes beside its checkpoint, and a new run in the same folder replaces (:func:`start_fresh`).
RUN_FILES = (METRICS, METRICS_CSV, BEST, TB_DIR, "knn_vs_time.png", "error_vs_time.png")


def _refuse_files_of_another(out_dir: Path, kind: str) -> None:
    """Refuse a folder without this kind's checkpoint that holds files a run replaces (:data:`RUN_FILES`),
    unless it is a run of this kind that stopped before its first checkpoint (its ``config.toml`` says so,
    or its best.pt is of this kind): ``--out ~/notes`` deleted a tb/ folder and a best.pt of the user's."""
    found = [name for name in RUN_FILES if (out_dir / name).exists() or (out_dir / name).is_symlink()]
    if not found or _run_of_kind(out_dir, kind):
        return
    raise DataError(f"{out_dir} holds {', '.join(found)} but no {kind} run of sssphase (no {CHECKPOINT}, no "
                    f"config.toml of `sss train {kind}`): a new run would replace them; give a new or empty folder")


def _run_of_kind(out_dir: Path, kind: str) -> bool:
    from sssphase_core.store.files import read_toml_input

    try:
        if read_toml_input(out_dir / "config.toml", "the run's options").get("command") == f"train {kind}":
            return True
    except (OSError, SssError, ValueError):
        pass
    try:
        return (out_dir / BEST).is_file() and load_checkpoint(out_dir / BEST, mmap=True).get("kind") == kind
    except (OSError, SssError):
        return False


def resume_state(out_dir: Path, resume: bool, kind: str, preset: ModelPreset | None = None) -> dict | None:
    path = out_dir / CHECKPOINT
    if check_run_folder(out_dir, kind) is None or not resume:
        return None
    ckpt = load_checkpoint(path)  # read whole: the check's mapping only looked
    if preset is not None and get_preset(ckpt["preset"]) != preset:
        raise DataError(f"{path} was trained with preset {ckpt['preset']['name']}, not {preset.name}: "
                        "resume with the same preset or pass --no-resume")
    return ckpt


def start_fresh(out_dir: Path) -> None:
    """A new run in a used folder: the old run's metrics and best checkpoint must not mix with it."""
    for name in RUN_FILES:  # the old run's figures too (check_run_folder refused a folder of the user's files)
        if name == TB_DIR and (out_dir / name).is_dir() and not (out_dir / name).is_symlink():
            shutil.rmtree(out_dir / TB_DIR, ignore_errors=True)
        else:
            (out_dir / name).unlink(missing_ok=True)
