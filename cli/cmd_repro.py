"""`sss repro paper`: the paper's Tables 1-2 at its scale within a time budget (``reporting.repro``)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)


def capture_args(req: Any) -> list[str]:
    """``sss capture`` options for a ``CaptureRequest`` (what a lab would type)."""
    args = ["capture", "--object", req.object, "--views", str(req.views), "--out", str(req.out), "--seed", str(req.seed),
            "--preset", req.preset, "--dot-stride", str(req.dot_stride), "--resume"]
    args += ["--footprints"] if req.footprints else []
    for ref in req.references:
        args += ["--reference", ref]
    if req.sim_options.get("device"):
        args += ["--device", str(req.sim_options["device"])]
    return args


def parallel_capture(workers: int, run_dir: Path, timeout: float):
    """``capture(requests)``: each request through ``sss capture`` in a process of its own with a daemon of its
    own (``SSS_RUNTIME_DIR`` per worker), ``workers`` at once, each with its share of the cores (its torch and
    BLAS threads: 7 captures of 16 threads each on 16 cores ran 4x slower); one worker: this process and the
    local daemon."""
    share = str(max(1, (os.cpu_count() or 1) // max(workers, 1)))
    threads = {v: share for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}

    def one(index_req: tuple[int, Any]) -> str:
        index, req = index_req
        env = {**os.environ, "SSS_RUNTIME_DIR": str(run_dir / f"worker{index % workers}"), **threads}
        cmd = [sys.executable, "-m", "sssphase_cli", *capture_args(req), "--timeout", str(timeout)]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, stdin=subprocess.DEVNULL)
        if done.returncode != 0:
            from sssphase_core.errors import SssError

            last = (done.stderr.strip() or done.stdout.strip()).splitlines()[-1:] or ["no output"]
            raise SssError(f"capturing {req.object} failed: {last[0]}")
        console.print(f"  captured {req.object}: {req.views} view(s)", highlight=False)
        return str(Path(req.out) / req.object)

    def capture(requests: Sequence[Any]) -> list[str]:
        for req in requests:
            req.validate()
        if workers <= 1:
            from sssphase_core.capture import run_capture
            from sssphase_daemon.client import local_client

            with local_client(timeout) as client:
                return [str(run_capture(client, req).path) for req in requests]
        run_dir.mkdir(parents=True, exist_ok=True)
        with ThreadPoolExecutor(workers) as pool:
            return list(pool.map(one, enumerate(requests)))

    return capture


def repro_paper(
    out: Annotated[Path, typer.Option("--out", help="Run folder (resumable: finished steps are skipped).")] = Path("repro"),
    device: Annotated[str, typer.Option(help="Where the simulator renders and the models train: auto, cpu, cuda, cuda:N.")] = "auto",
    budget: Annotated[float, typer.Option(help="Seconds for this run (a rerun skips finished steps and has a budget of its own): training epochs are sized to the time the captures leave; a step that would start after it is not run.")] = 480.0,
    preset: Annotated[str, typer.Option(help="paper (1080p, K = 90, the paper model: a GPU) or tiny (the CPU rig and lite model: tests).")] = "paper",
    workers: Annotated[int, typer.Option(help="Captures at once, each through its own daemon (0: half the CPU cores, at most the number of sessions).")] = 0,
    train_views: Annotated[int | None, typer.Option(help="Views per training object (default: the preset's; at least 2 for kNN's leave-one-view-out).")] = None,
    fresh: Annotated[bool, typer.Option("--fresh", help="Redo every step.")] = False,
    timeout: Annotated[float, typer.Option(help="Seconds without an answer from a capture's daemon before it counts as gone.")] = 60.0,
) -> None:
    """The paper's Tables 1-2 at its scale: capture training and unseen sessions, pretrain (PSP and ImageNet
    augmentations), fit the decoder, evaluate, and report beside the paper's numbers, within --budget seconds."""
    from sssphase_cli.progress import step_bar
    from sssphase_core.errors import InputError
    from sssphase_core.reporting.repro import PRESETS, check_repro_options, run_repro

    check_repro_options(out, preset, device, budget)  # before the progress display (it left a blank line)
    if workers < 0:
        raise InputError(f"--workers must be 0 (automatic) or more, got {workers}")
    if not 0 < timeout <= 86400:  # 0 failed every capture, and the run still said it had finished; inf overflowed
        raise InputError(f"--timeout must be a number of seconds in (0, 86400], got {timeout:g}")
    if train_views is not None and train_views < 2:
        raise InputError(f"--train-views must be at least 2 (kNN leaves one view out), got {train_views}")
    cfg = PRESETS[preset]
    sessions = len(cfg.train_objects) + len(cfg.test_objects)
    n = workers or max(1, min(sessions, (os.cpu_count() or 2) // 2))
    overrides = {"train_views": train_views} if train_views is not None else {}

    def log(message: str) -> None:
        console.print(message, markup=False, highlight=False)

    # each worker's daemon has a runtime folder of its own; ipc socket paths must stay short (~100 bytes)
    with tempfile.TemporaryDirectory(prefix="sssr") as runtime, step_bar(console) as progress:
        report = run_repro(out, parallel_capture(n, Path(runtime), timeout), preset=preset, device=device,
                           budget_s=budget, fresh=fresh, log=log, progress=progress, **overrides)
    console.print(report.read_text(), markup=False, highlight=False)
    console.print(f"[green]report[/]: {report}")


def register(groups: dict[str, typer.Typer]) -> None:
    groups["repro"].command("paper")(repro_paper)
