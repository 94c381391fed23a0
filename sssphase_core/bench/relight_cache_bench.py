"""`sss bench relight-cache`: a new pattern relit from a view's cached eigen-footprints, against the full relight.

Three `sss relight` commands on one session view, each its own process (wall time and peak RSS from the
operating system's record of that process):

1. ``cold``: the first relight of the view (the model's footprints computed, the eigen-footprints kept);
2. ``cached``: another pattern, relit from the eigen-footprints alone;
3. ``full``: that pattern relit from scratch with ``--no-cache``, the baseline measured in the same run.

The report gives the seconds and peak RSS of each, the ratio full / cached, and how far the cached images
are from the full ones (PSNR at the image's peak, and the largest difference).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.bench.output import Table, machine_info, write_bench_report


def run_command(args: list[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``python -m sssphase_cli ARGS`` -> {"seconds", "peak_rss_mib", "returncode", "output"}; the peak
    RSS is the process's own (``wait4``), its children excluded."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=env)
    assert proc.stdout is not None
    output = proc.stdout.read().decode(errors="replace")
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"seconds": time.perf_counter() - t0, "peak_rss_mib": usage.ru_maxrss / 1024.0,
            "returncode": proc.returncode, "output": output[-2000:]}


def _image(folder: Path, obj: str, view: int, pattern: str, backend: str) -> np.ndarray:
    from sssphase_core.store.exr import read_exr

    return read_exr(folder / f"{obj}_v{view}_{pattern}_{backend}.exr")


def run(session: Path, out: Path, *, backend: str = "analytic", checkpoint: Path | None = None, view: int = 0,
        first: str = "checkerboard", new: str = "stripes_y", work: Path | None = None) -> dict[str, Any]:
    """The three relights of ``session``'s ``view`` (patterns ``first``, then ``new``); writes ``out`` (JSON) and
    its Markdown twin. ``work``: where the relit images and caches go (default: next to ``out``)."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import Session

    s = Session.open(session)
    obj = s.name
    work = Path(work) if work is not None else Path(out).with_suffix("") / "work"
    cached_dir, full_dir = work / "cached", work / "full"
    common = ["--backend", backend, "--views", str(view), "--format", "exr"] + (
        ["--checkpoint", str(checkpoint)] if checkpoint is not None else [])
    env = dict(os.environ, NO_COLOR="1", COLUMNS="200")
    steps = {
        "cold": ["relight", str(session), "--pattern", first, "--out", str(cached_dir), *common],
        "cached": ["relight", str(session), "--pattern", new, "--out", str(cached_dir), *common],
        "full": ["relight", str(session), "--pattern", new, "--out", str(full_dir), "--no-cache", *common],
    }
    rows = []
    for name, args in steps.items():
        r = run_command(args, env)
        if r["returncode"] != 0:
            raise InputError(f"`sss {' '.join(args)}` failed: {r['output'].strip().splitlines()[-1] if r['output'].strip() else r['returncode']}")
        rows.append({"step": name, "command": "sss " + " ".join(args), **r})
    by = {r["step"]: r for r in rows}
    if "eigen-footprints" not in by["cached"]["output"]:
        raise InputError("the second relight did not use the eigen-footprint cache (see its output in the JSON)")
    a, b = _image(cached_dir, obj, view, new, backend), _image(full_dir, obj, view, new, backend)
    diff = float(np.mean((a - b) ** 2))
    peak = float(np.abs(b).max())
    agreement = {"psnr_at_peak": 10 * np.log10(peak**2 / diff) if diff > 0 else float("inf"),
                 "max_abs": float(np.abs(a - b).max()), "peak": peak}
    result = {"machine": machine_info(), "session": str(session), "object": obj, "view": view, "backend": backend,
              "checkpoint": None if checkpoint is None else str(checkpoint), "patterns": [first, new], "rows": rows,
              "speedup": by["full"]["seconds"] / by["cached"]["seconds"], "agreement": agreement,
              "shape": list(np.asarray(b).shape[:2])}
    table = Table(
        "A new pattern from cached eigen-footprints",
        ["step", "pattern", "seconds", "peak RSS (MiB)"],
        [[r["step"], first if r["step"] == "cold" else new, r["seconds"], r["peak_rss_mib"]] for r in rows],
        note=(f"{obj} view {view}, {b.shape[1]}x{b.shape[0]}, backend {backend}. Each step is one `sss relight` process "
              f"(start-up included). full / cached: {result['speedup']:.1f}x. Cached against full: PSNR "
              f"{agreement['psnr_at_peak']:.1f} dB at the image's peak ({peak:.3g}), largest difference "
              f"{agreement['max_abs']:.2g}."))
    write_bench_report(result, [table], Path(out), md=Path(out).with_suffix(".md"), title="Relighting from cached eigen-footprints")
    return result
