"""``sss bench gpu``'s plumbing on the CPU: every stage runs and reports what it measured."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sssphase_core.bench import gpu_bench
from sssphase_core.errors import InputError


@pytest.mark.slow
def test_the_gpu_bench_runs_every_stage_on_the_cpu(tmp_path):
    r = gpu_bench.run(tmp_path / "gpu.json", device="cpu", preset="lite", steps=4, batch=8, epochs=2, relight_size=48)
    for stage in ("pretrain", "decoder", "pretrain_host", "decoder_host", "pretrain_kernels", "decoder_kernels"):
        s = r["training"][stage]
        assert s["steps"] == 4 and s["patches_s"] > 0 and len(s["loss_per_epoch"]) == 2 and s["finite"]
        assert s["steady_patches_s"] > 0 and 0 <= s["data_wait_share"] <= 1
        assert s["peak_memory_mb"] is None  # no device memory on the CPU
    for stage in ("pretrain", "decoder"):  # neither loader nor kernel option applies on the CPU: the same training
        assert r["training"][stage]["loss_per_epoch"] == r["training"][stage + "_host"]["loss_per_epoch"]
        assert r["training"][stage]["loss_per_epoch"] == r["training"][stage + "_kernels"]["loss_per_epoch"]
    for label in ("float32", "bf16 autocast"):
        assert r["agreement"][label]["footprint"] == 0.0  # CPU against itself: the same numbers
    for method in ("index", "fold"):
        assert r["relight"][method]["max_rel_diff"] < 1e-5 and r["relight"][method]["seconds"] > 0
    assert "skipped" in r["ddp"] and "GPU" in r["ddp"]["skipped"]
    text = gpu_bench.markdown(r)
    assert "| pretrain | default | 4 |" in text and "| decoder | host loader (baseline) | 4 |" in text
    assert "| decoder | other kernels | 4 |" in text and "identical with the host loader" in text
    assert r["training"]["deterministic_default"] == {"pretrain": False, "decoder": True}
    assert r["training"]["deterministic_kernels"] == {"pretrain": True, "decoder": False}
    assert "same run: pretrain" in text and "fold" in text and "CPU" in text
    assert all(math.isfinite(v) for v in r["training"]["decoder"]["loss_per_epoch"])
    f = r["flops"]  # model FLOPs of one training step per patch, and the same run's peak
    assert 1e8 < f["pretrain"] < 1e9 and 1e8 < f["decoder"] < 1e9 and f["matmul_peak"] > 1e8
    assert f["datasheet_peak"] is None  # a CPU has no entry
    assert "GFLOP per patch" in text and "unknown device" in text and "of a bf16 matrix product" in text


def test_training_flops_count_what_a_step_runs():
    """SimSiam runs the encoder on two views forward and backward; the frozen-encoder decoder step runs the
    encoder forward only: FLOPs grow with the preset and the count is per patch (not per batch)."""
    from sssphase_core.learning.flops import datasheet_peak, training_flops_per_patch

    lite = training_flops_per_patch("lite", "pretrain")
    assert training_flops_per_patch("lite", "pretrain", batch=4) == pytest.approx(lite, rel=1e-6)
    assert training_flops_per_patch("paper", "pretrain") > 100 * lite
    assert datasheet_peak("NVIDIA H200") == 989e12 and datasheet_peak("Quadro") is None
    with pytest.raises(ValueError):
        training_flops_per_patch("lite", "finetune")


def test_an_absent_cuda_device_is_one_clear_error(monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    with pytest.raises(InputError, match="no CUDA device"):
        gpu_bench.run(Path("unused.json"), device="cuda")  # refused before anything is written
    from sssphase_core.compute import compute_device

    assert compute_device("auto").type == "cpu"
