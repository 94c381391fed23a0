"""Shared benchmark plumbing: timing with a median over repeats, JSON and Markdown output."""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.tables import Table  # noqa: F401  (benchmarks build their tables with it)


def median_seconds(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def interleaved_seconds(fns: dict[str, Callable[[], object]], repeats: int = 5, warmup: int = 1) -> dict[str, list[float]]:
    """Wall times of several functions measured alternately (round-robin), so that a change in machine
    load between measurements affects all of them alike. Returns every repeat's time per name."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(max(1, repeats)):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def machine_info() -> dict[str, Any]:
    """What the numbers were measured on (CPU count, threads, library versions)."""
    info: dict[str, Any] = {"python": platform.python_version(), "cpus": os.cpu_count(), "machine": platform.machine()}
    if hasattr(os, "getloadavg"):
        info["load_average_1min"] = os.getloadavg()[0]  # other processes sharing the cores
    try:
        import torch

        info |= {"torch": torch.__version__, "torch_threads": torch.get_num_threads()}
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    try:
        import cv2

        info["opencv"] = cv2.__version__
    except ImportError:  # pragma: no cover
        pass
    info["numpy"] = np.__version__
    return info


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def check_result_paths(out: Path | str, md: Path | str | None = None) -> None:
    """Refuse result files that would land inside a session (``--out S/apple/manifest.json`` replaced a
    session's manifest), on an existing folder, or a JSON and its Markdown on one path."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import refuse_inside_session

    for path in (Path(out), *([Path(md)] if md is not None else [])):
        refuse_inside_session(path.parent, what=f"--out {path}: its folder")
        if path.is_dir():
            raise InputError(f"--out {path} is a folder: give a file name (e.g. {path / 'result.json'})")
        above = next((a for a in path.parents if a.exists()), None)  # "afile: File exists" came after all the work
        if above is not None and not above.is_dir():
            raise InputError(f"--out {path}: {above} is a file, so no folder can be made there")
    if md is not None and Path(md).resolve() == Path(out).resolve():
        raise InputError(f"--out {out}: the JSON record and its Markdown table would be the same file; give a .json name")


def write_bench_report(result: dict[str, Any], tables: Sequence[Table], out: Path, md: Path | None = None, title: str = "") -> None:
    """Write ``result`` as JSON to ``out`` and, if ``md`` is given, the tables as Markdown."""
    out = Path(out)
    check_result_paths(out, md)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_jsonable(result), indent=1) + "\n")
    if md is not None:
        md = Path(md)
        md.parent.mkdir(parents=True, exist_ok=True)
        head = f"## {title}\n\n" if title else ""
        md.write_text(head + "\n".join(t.markdown() for t in tables))
