"""Model FLOPs per training patch (counted by torch's ``FlopCounterMode`` on one step on the meta device) and
the share of an accelerator's peak a measured throughput reaches (MFU)."""

from __future__ import annotations

import time

import torch
from torch.utils.flop_counter import FlopCounterMode

#: Dense bf16 matrix-multiply peaks from the vendors' datasheets (FLOP/s), by a substring of the device name.
DATASHEET_BF16_PEAK = {"H200": 989e12, "H100": 989e12, "A100": 312e12, "L40S": 362e12, "L4": 121e12}


def training_flops_per_patch(preset: str, stage: str, batch: int = 2) -> float:
    """FLOPs of one training step per patch for ``stage`` ``pretrain`` (SimSiam: both views through encoder,
    projector and predictor, forward and backward) or ``decoder`` (the frozen encoder's forward, the decoder's
    forward and backward), counted on a batch of ``batch`` patches on torch's meta device (shapes only, no
    arithmetic: the paper preset's count in 0.3 s instead of 2 s of CPU)."""
    from sssphase_core.learning.models import Decoder, Encoder, SimSiam, get_preset
    from sssphase_core.learning.training import FootprintNet

    if stage not in ("pretrain", "decoder"):
        raise ValueError(f"stage must be pretrain or decoder, got {stage!r}")
    p = get_preset(preset)
    x = torch.empty(batch, 24, p.patch, p.patch, device="meta")
    if stage == "pretrain":
        simsiam = SimSiam(p).to("meta").train()
        loss = lambda: simsiam(x, x.flip(-1))["loss"]  # noqa: E731
    else:
        net = FootprintNet(Encoder(p).eval().requires_grad_(False), Decoder(p).train()).to("meta")
        loss = lambda: net(x)[0].float().sum()  # noqa: E731
    with FlopCounterMode(display=False) as counter:
        loss().backward()
    return counter.get_total_flops() / batch


def datasheet_peak(device_name: str) -> float | None:
    """The bf16 dense peak (FLOP/s) of a device named ``device_name``, when :data:`DATASHEET_BF16_PEAK` knows it."""
    return next((v for k, v in DATASHEET_BF16_PEAK.items() if k in device_name), None)


def measured_matmul_peak(device: torch.device, n: int = 8192, repeats: int = 20) -> float:
    """bf16 (CUDA) or float32 (CPU) dense matrix-multiply FLOP/s measured here: the same run's baseline."""
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    n = n if device.type == "cuda" else 1024
    a, b = (torch.randn(n, n, device=device, dtype=dtype) for _ in range(2))
    a @ b  # warm-up (kernel selection)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        a @ b
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return 2.0 * n**3 * repeats / (time.perf_counter() - t0)
