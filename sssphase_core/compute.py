"""Where torch computes: one check of a user's ``--device`` for every command."""

from __future__ import annotations

import torch

from sssphase_core.errors import InputError


def compute_device(name: str | torch.device) -> torch.device:
    """``auto`` (CUDA when torch sees one, else the CPU), ``cpu``, ``cuda`` or ``cuda:N`` -> a torch device
    this process can use; anything else is an :class:`InputError` naming what is available."""
    if isinstance(name, torch.device):
        return name
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise InputError(f"unknown device {name!r}: use auto, cpu, cuda or cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise InputError(f"device {name!r} is not supported: use auto, cpu, cuda or cuda:N")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"device {name!r}: this torch build sees no CUDA device (torch.cuda.is_available() is False)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InputError(f"device {name!r}: torch sees {torch.cuda.device_count()} CUDA device(s)")
    return dev
