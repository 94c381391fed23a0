"""Shared benchmark plumbing: timing with a median over repeats, JSON and Markdown output."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from sssphase_core.store.results import check_result_paths  # noqa: F401  (the CLI checks result paths with it)
from sssphase_core.store.results import jsonable as _jsonable  # noqa: F401
from sssphase_core.store.results import write_report as write_bench_report  # noqa: F401
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
