"""Where torch computes: one check of a user's ``--device`` for every command.

:func:`check_device` refuses a bad name without importing torch for ``auto`` and ``cpu`` (a front end's
checks stay fast); :func:`compute_device` gives the torch device.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from sssphase_core.errors import InputError

if TYPE_CHECKING:
    import torch

DEVICE_NAMES = "use auto, cpu, cuda or cuda:N"
#: Device types torch knows that sssphase does not compute on.
OTHER_TORCH_DEVICES = ("mps", "xpu", "meta", "hip", "xla", "ipu", "mtia", "hpu", "vulkan", "mkldnn", "opengl", "opencl",
                       "ideep", "fpga", "maia", "lazy", "ve", "privateuseone")


def check_device(name: str) -> None:
    """Refuse a ``--device`` this process cannot use (an :class:`InputError` naming what is available).
    ``auto`` and ``cpu`` are checked without importing torch; ``cuda[:N]`` asks torch what it sees."""
    if name == "auto" or re.fullmatch(r"cpu(:\d+)?", name):
        return
    if not re.fullmatch(r"cuda(:\d+)?", name):
        if name.partition(":")[0] in OTHER_TORCH_DEVICES:
            raise InputError(f"device {name!r} is not supported: {DEVICE_NAMES}")
        raise InputError(f"unknown device {name!r}: {DEVICE_NAMES}")
    import torch

    if not torch.cuda.is_available():
        raise InputError(f"device {name!r}: this torch build sees no CUDA device (torch.cuda.is_available() is False)")
    index = int(name.partition(":")[2] or 0)
    if ":" in name and index >= torch.cuda.device_count():
        raise InputError(f"device {name!r}: torch sees {torch.cuda.device_count()} CUDA device(s)")


def compute_device(name: str | torch.device) -> torch.device:
    """``auto`` (CUDA when torch sees one, else the CPU), ``cpu``, ``cuda`` or ``cuda:N`` -> a torch device
    this process can use; anything else is an :class:`InputError` naming what is available."""
    import torch

    if isinstance(name, torch.device):
        return name
    check_device(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


#: ``--precision`` of a decoder's inference: ``auto`` is bf16 where the device computes it natively, else fp32.
PRECISIONS = ("auto", "fp32", "bf16")


def check_precision(name: str) -> None:
    """Refuse a ``--precision`` that is none of :data:`PRECISIONS` (an :class:`InputError`), without importing torch."""
    if name not in PRECISIONS:
        raise InputError(f"unknown precision {str(name)[:40]!r}: use {', '.join(PRECISIONS)}")


def inference_precision(device: str | torch.device, name: str = "auto") -> str:
    """The precision a decoder infers in on ``device``: ``fp32`` or ``bf16`` as asked, and for ``auto`` bf16 where
    the device computes it natively (a CUDA GPU with bf16, Ampere or later; a CPU with AVX512-BF16 or AMX: on one, a
    trained decoder's footprints within 0.005 dB PSNR of float32's, 1.5 to 2 times as fast), else fp32 (emulated
    bf16 is slower than float32)."""
    import torch

    check_precision(name)
    if name != "auto":
        return name
    dev = compute_device(device)
    if dev.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported(including_emulation=False) else "fp32"
    native = (getattr(torch.cpu, "_is_avx512_bf16_supported", None), getattr(torch.cpu, "_is_amx_tile_supported", None))
    return "bf16" if any(f is not None and f() for f in native) else "fp32"


def renders_on_torch(name: str) -> bool:
    """Whether the simulator's ``device`` option puts its light transport on torch: ``cuda[:N]`` yes, ``cpu`` no
    (numpy), ``auto`` only where torch sees a GPU: on a CPU the numpy path is faster (it caches footprints; torch
    recomputes them per batch: a sand-rake view 2.2x slower with 6x the memory) and imports no torch."""
    check_device(name)
    if name == "auto":
        import torch

        return torch.cuda.is_available()
    return not name.startswith("cpu")


def available_memory() -> int | None:
    """Bytes this process can still allocate: the kernel's ``MemAvailable``, or less under an address-space
    limit (``ulimit -v``); None where neither is known."""
    import resource

    found = []
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError):
        pass
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft != resource.RLIM_INFINITY:
        found.append(max(0, soft - _address_space_used()))
    return min(found) if found else None


def _address_space_used() -> int:
    import os

    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0
