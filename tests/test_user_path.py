"""The user's path end to end through the CLI, at tiny size: capture sessions through the daemon (sim
rig), pretrain and fit the decoder from those sessions only, relight and evaluate an unseen object.

Ground truth (the simulator's noise-free renders) is used for scoring only; training reads captured
dot-grid crops, as a lab would.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path

import pytest
from sss_process import run_sss


def _sss(*args: str, env: dict[str, str]) -> str:
    res = run_sss([*args], timeout=600, env=env)
    assert res.returncode == 0, f"sss {' '.join(args)}:\n{res.stdout}\n{res.stderr}"
    return res.stdout


@pytest.mark.slow
def test_capture_train_from_sessions_relight_and_beat_no_scattering(tmp_path):
    runtime = Path(tempfile.mkdtemp(prefix="sssu", dir="/tmp"))  # ipc paths must stay short
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "200"}
    train, test = tmp_path / "sessions", tmp_path / "test_sessions"
    for obj in ("apple", "star"):  # every fourth dot shift: crops for a sixteenth of the pixels, as a lab trains
        _sss("capture", "--object", obj, "--views", "2", "--footprints", "--dot-stride", "4", "--out", str(train), env=env)
    _sss("capture", "--object", "sand_rake", "--views", "1", "--reference", "checkerboard", "--out", str(test), env=env)
    pre, dec = tmp_path / "runs" / "pre", tmp_path / "runs" / "dec"
    # No --views: what was captured is used (2 views each), the decoder holding each session's last view out.
    out = _sss("train", "pretrain", "--sessions", str(train), "--out", str(pre), "--pixels-per-view", "150",
               "--epochs", "2", "--warmup-epochs", "1", "--batch-size", "32", "--knn-monitor", "200", env=env)
    assert "best knn_acc at epoch" in out and (pre / "best.pt").exists()
    assert f"data: captured sessions under {train}: apple view 0,1; star view 0,1" in out, out
    out = _sss("train", "decoder", "--encoder", str(pre), "--sessions", str(train),
               "--out", str(dec), "--pixels-per-view", "300", "--epochs", "2", "--check-sessions", str(test), env=env)
    assert f"data: captured sessions under {train}: apple view 0; star view 0" in out, out
    assert f"validation (held out): captured sessions under {train}: apple view 1; star view 1" in out, out
    assert "final (epoch 2): val_loss" in out and "relit PSNR on sand_rake view 0" in out
    assert "worse than the none baseline" not in out, out
    checked = float(re.search(r"relit PSNR on sand_rake view 0: torch ([0-9.]+) dB", out).group(1))
    _sss("eval", "relight", str(test), "--backend", "none,torch", "--checkpoint", str(dec), "--out", str(tmp_path / "ev"),
         env=env)
    rows = json.loads((tmp_path / "ev" / "relight_eval.json").read_text())["aggregate"]
    psnr = {r["backend"]: r["psnr"] for r in rows}
    assert psnr["torch"] > psnr["none"] + 2, psnr
    # The evaluation read the footprints the training's check cached for this view and checkpoint: its cache is
    # that very file (linked; a footprint computed again would have replaced it) and its PSNR the check's.
    (kept,) = (dec / "check" / "cache").glob("sand_rake_v0_*_torch_*.npz")
    assert (tmp_path / "ev" / "cache" / kept.name).stat().st_ino == kept.stat().st_ino
    assert round(psnr["torch"], 2) == checked, (psnr, checked)


@pytest.mark.slow
def test_the_compact_footprint_store_is_a_quarter_of_float32_and_relights_the_same(sim_daemon, tmp_path):
    """`sss bench store` on a capture with kept dot frames: the stored transport (float16, noise floor
    zeroed, zstd) against float32 with every value, both relit by the measured backend."""
    from sssphase_core.bench import store_bench
    from sssphase_core.capture import CaptureRequest, run_capture

    s = run_capture(sim_daemon, CaptureRequest("sand_rake", views=1, footprints=True, keep_dots=True,
                                                references=("checkerboard",), out=tmp_path / "s"))
    assert s.manifest["views"]["0"]["transport"]["noise_dropped"]
    row = store_bench.run([s], tmp_path / "store.json")["rows"][0]
    assert row["store"]["bytes"] < 0.25 * row["raw_float32_bytes"]
    # no worse than every value in float32 (the store's zeros also tighten the noise mask read from it)
    assert row["store"]["psnr"] > row["float32"]["psnr"] - 0.1
    assert (tmp_path / "store.md").read_text().count("| sand_rake |") == 1
