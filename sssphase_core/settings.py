"""Numbers read from environment variables, checked where they are read: a bad value is one line naming the
variable (``SSS_OPEN_TIMEOUT_S=abc`` was an internal ValueError at import; ``nan`` or ``inf`` timed out at once
or overflowed a timer)."""

from __future__ import annotations

import math
import os

from sssphase_core.errors import InputError

MAX_SECONDS = 86400.0  # a day: longer is no timeout anyone means (and ``threading`` overflows near 9.2e9 s)


def env_seconds(name: str, default: float) -> float:
    """``$name`` as a number of seconds, 0 < s <= a day; ``default`` when it is unset or empty."""
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value <= MAX_SECONDS):
        raise InputError(f"{name}={raw!r}: give a number of seconds above 0 and at most {MAX_SECONDS:g} "
                         f"(or unset it for the default, {default:g})")
    return value


def env_count(name: str, default: int, minimum: int = 0) -> int:
    """``$name`` as a whole number >= ``minimum`` (torchrun's WORLD_SIZE, RANK); ``default`` when unset or empty."""
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        value = int(raw)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise InputError(f"{name}={raw!r}: give a whole number >= {minimum} (torchrun sets it; unset it to run alone)"
                         if name in ("WORLD_SIZE", "RANK", "LOCAL_RANK") else f"{name}={raw!r}: give a whole number >= {minimum}")
    return value
