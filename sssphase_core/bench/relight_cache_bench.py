"""`sss bench relight-cache`: a new pattern relit from a view's cached eigen-footprints, against the full relight.

Three `sss relight` commands on one session view, each its own process (wall time and peak RSS from the
operating system's record of that process):

1. ``cold``: the first relight of the view (the model's footprints computed, the eigen-footprints kept);
2. ``cached``: another pattern, relit from the eigen-footprints alone;
3. ``full``: that pattern relit from scratch with ``--no-cache``, the baseline measured in the same run;
4. ``sequence``: a clip of ``frames`` frames (a bar sweeping across the projector, MPEG-4) relit into a fresh folder,
   its first frame computing the footprints as ``cold`` did, the others from the eigen-footprints in the same process.

The report gives the seconds and peak RSS of each, the ratio full / cached, how far the cached images are from the
full ones (PSNR at the image's peak, and the largest difference), and a sequence's cost per later frame
((sequence - cold) / (frames - 1)) against a `sss relight` process per pattern from the cache (``cached``).
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


def sweep_clip(path: Path, size: tuple[int, int], frames: int, fps: float = 25.0) -> Path:
    """A clip of ``frames`` frames of ``size`` (W, H): a white bar a fifth of the width wide sweeping across black."""
    import cv2

    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for i in range(frames):
        frame = np.zeros((h, w, 3), np.uint8)
        x = round(i * w / frames)
        frame[:, x : x + max(1, w // 5)] = 255
        writer.write(frame)
    writer.release()
    return path


def run(session: Path, out: Path, *, backend: str = "analytic", checkpoint: Path | None = None, view: int = 0,
        first: str = "checkerboard", new: str = "stripes_y", work: Path | None = None, frames: int = 100) -> dict[str, Any]:
    """The four relights of ``session``'s ``view`` (patterns ``first``, then ``new``, then a clip of ``frames``); writes
    ``out`` (JSON) and its Markdown twin. ``work``: where the relit images and caches go (default: a temporary folder,
    removed afterwards: a 100-frame clip's PNGs are tens of MB beside a benchmark's report)."""
    import tempfile

    if work is not None:
        return _run(session, out, backend=backend, checkpoint=checkpoint, view=view, first=first, new=new,
                    work=Path(work), frames=frames)
    with tempfile.TemporaryDirectory(prefix="sss-bench-relight-cache-") as scratch:
        return _run(session, out, backend=backend, checkpoint=checkpoint, view=view, first=first, new=new,
                    work=Path(scratch), frames=frames)


def _run(session: Path, out: Path, *, backend: str, checkpoint: Path | None, view: int, first: str, new: str,
         work: Path, frames: int) -> dict[str, Any]:
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import Session

    s = Session.open(session)
    obj = s.name
    cached_dir, full_dir = work / "cached", work / "full"
    common = ["--backend", backend, "--views", str(view), "--format", "exr"] + (
        ["--checkpoint", str(checkpoint)] if checkpoint is not None else [])
    env = dict(os.environ, NO_COLOR="1", COLUMNS="200")
    work.mkdir(parents=True, exist_ok=True)
    clip = sweep_clip(work / "sweep.mp4", tuple(int(v) for v in s.manifest["plan"]["projector"]), frames)  # type: ignore[arg-type]
    steps = {
        "cold": ["relight", str(session), "--pattern", first, "--out", str(cached_dir), *common],
        "cached": ["relight", str(session), "--pattern", new, "--out", str(cached_dir), *common],
        "full": ["relight", str(session), "--pattern", new, "--out", str(full_dir), "--no-cache", *common],
        "sequence": ["relight", str(session), "--pattern", str(clip), "--out", str(work / "sequence"),
                     *[a for a in common if a not in ("--format", "exr")], "--format", "png"],
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
              "shape": list(np.asarray(b).shape[:2]), "frames": frames,
              "seconds_per_frame": (by["sequence"]["seconds"] - by["cold"]["seconds"]) / max(frames - 1, 1)}
    result["frame_vs_cached_process"] = by["cached"]["seconds"] / result["seconds_per_frame"]
    table = Table(
        "A new pattern from cached eigen-footprints",
        ["step", "pattern", "seconds", "peak RSS (MiB)"],
        [[r["step"], {"cold": first, "sequence": f"sweep, {frames} frames"}.get(r["step"], new), r["seconds"],
          r["peak_rss_mib"]] for r in rows],
        note=(f"{obj} view {view}, {b.shape[1]}x{b.shape[0]}, backend {backend}. Each step is one `sss relight` process "
              f"(start-up included). full / cached: {result['speedup']:.1f}x. Cached against full: PSNR "
              f"{agreement['psnr_at_peak']:.1f} dB at the image's peak ({peak:.3g}), largest difference "
              f"{agreement['max_abs']:.2g}. The sequence's later frames: {1000 * result['seconds_per_frame']:.0f} ms each "
              f"((sequence - cold) / {frames - 1}, their PNGs written), {result['frame_vs_cached_process']:.0f}x less than "
              "a `sss relight` process per pattern from the cache."))
    write_bench_report(result, [table], Path(out), md=Path(out).with_suffix(".md"), title="Relighting from cached eigen-footprints")
    return result
