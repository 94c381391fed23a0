"""torchrun with two CPU processes (gloo): DDP pretraining and decoder training stay in sync."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

SCRIPT = textwrap.dedent(
    """
    import os, sys
    from pathlib import Path
    import torch
    torch.set_num_threads(1)
    sys.path.insert(0, os.environ["LEARN_TESTS"])
    from conftest import TINY
    from sssphase_core.bench.synthetic import synthetic_views
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.training import DecoderConfig, PretrainConfig, pretrain, train_decoder

    out = Path(sys.argv[1])
    views, _ = synthetic_views(("a", "b"), (0, 1), size=(48, 48), patch=16, pixels_per_view=64)
    ds = PatchDataset(views, 16, ["a", "b"], with_targets=True)
    pre = pretrain(PretrainConfig(epochs=1, batch_size=16, ckpt_every=0), ds, out / "pre", preset=TINY, progress=False)
    dec = train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pre, ds, out / "dec", progress=False)
    rank = int(os.environ["RANK"])
    torch.save({"world": torch.distributed.get_world_size()}, out / f"rank{rank}.pt")
    """
)


@pytest.mark.slow
def test_torchrun_two_cpu_processes(tmp_path):
    script = tmp_path / "ddp_run.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "LEARN_TESTS": os.path.dirname(__file__), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", str(script), str(tmp_path)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    first = [line for line in proc.stderr.splitlines() if line.startswith("[rank1]")]  # (rank 0's tail alone hid the
    assert proc.returncode == 0, "\n".join(first[-40:]) + "\n...\n" + proc.stderr[-2000:]  # cause: a rank-1 exit)
    for r in (0, 1):
        assert torch.load(tmp_path / f"rank{r}.pt", weights_only=True)["world"] == 2
    pre = torch.load(tmp_path / "pre" / "last.pt", weights_only=True)
    # 256 patches, 2 processes, batch 16 -> 8 steps per process per epoch
    assert pre["loop"]["epoch"] == 1
    rows = [json.loads(line) for line in (tmp_path / "pre" / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["step"] == 8
    assert (tmp_path / "dec" / "last.pt").exists()
