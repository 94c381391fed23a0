"""Training loops: SimSiam pretraining and decoder fitting, with exact resume, metrics and DDP.

Both loops share :class:`Loop`: a deterministic schedule (the epoch's sample order comes from
``DistributedSampler(seed, epoch)``, and torch's global RNG, which drives augmentations and dropout,
is re-seeded from (seed, global step) before every step), so a run resumed from a checkpoint
reproduces exactly the steps of an uninterrupted one (bit for bit on the CPU; decoder training on CUDA
is not bit-reproducible even without a resume). Checkpoints (``last.pt``) hold plain tensors
and dicts only and are read with ``torch.load(weights_only=True)``; they are written atomically at
the end of every epoch and every ``ckpt_every`` steps, so a run killed mid-epoch loses at most that
many steps. Metrics go to ``metrics.jsonl`` (one row per epoch with the cumulative run time
``wall_s`` and the epoch's time spent waiting for batches, ``data_wait_s``). Off the CPU the next batch
is built on a worker thread during each step, and on CUDA patches are cropped from copies of the view
stacks on the device when they fit (``prefetch``, ``stacks_on_device``). Under ``torchrun`` (WORLD_SIZE > 1) the model is wrapped in DDP (gloo on CPU, NCCL on
GPU, SyncBatchNorm on GPU only: PyTorch's SyncBN has no CPU kernel) and rank 0 writes files.

One job per module: :mod:`~sssphase_core.learning.training.checkpoints` (atomic, safe checkpoints and the
models they hold), :mod:`~sssphase_core.learning.training.loop` (the shared loop, DDP),
:mod:`~sssphase_core.learning.training.pretrain` (SimSiam) and :mod:`~sssphase_core.learning.training.decoder` (SBH).
"""


from sssphase_core.learning.runlog import METRICS, METRICS_CSV, TB_DIR
from sssphase_core.learning.training.checkpoints import (
    BEST,
    CHECKPOINT,
    decoder_modules,
    decoder_patch,
    load_checkpoint,
    load_decoder,
    load_encoder,
    resolve_checkpoint,
    save_checkpoint,
)
from sssphase_core.learning.training.decoder import (
    PRIOR_SAMPLES,
    DecoderConfig,
    FootprintNet,
    train_decoder,
    validate_decoder,
)
from sssphase_core.learning.training.loop import (
    Dist,
    Loop,
    LoopConfig,
    StepProgress,
    TrainingCollapsed,
    TrainingDiverged,
    TrainingStopped,
    check_run_folder,
    init_distributed,
)
from sssphase_core.learning.training.pretrain import (
    PretrainConfig,
    effective_rank,
    initial_encoder,
    knn_monitor,
    knn_monitor_indices,
    pretrain,
    projection_std,
    warmup_cosine,
)

__all__ = [
    "BEST", "CHECKPOINT", "METRICS", "METRICS_CSV", "PRIOR_SAMPLES", "TB_DIR", "DecoderConfig", "Dist", "FootprintNet",
    "Loop", "LoopConfig", "PretrainConfig", "StepProgress", "TrainingCollapsed", "TrainingDiverged", "TrainingStopped",
    "check_run_folder", "decoder_modules", "decoder_patch", "effective_rank", "init_distributed", "initial_encoder", "knn_monitor", "knn_monitor_indices", "load_checkpoint", "load_decoder",
    "load_encoder", "pretrain", "projection_std", "resolve_checkpoint", "save_checkpoint", "train_decoder",
    "validate_decoder", "warmup_cosine",
]
