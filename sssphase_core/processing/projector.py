"""The projector's light model, shared by the simulator and relighting (numpy only, no torch).

A pattern value v in [0, 1] makes the projector emit ``black + (1 - black) * v**gamma``; a camera
pixel receives the emitted light of the projector point it sees, looked up bilinearly in the
emitted (linear) domain, and nothing outside the projector image. Keeping this in one place is
what makes relighting with exact footprints reproduce the simulator's renders.
"""

from __future__ import annotations

import numpy as np

from sssphase_core.errors import InputError


def emitted_light(patterns: np.ndarray, gamma: float) -> np.ndarray:
    """Pattern values in [0, 1] -> relative emitted radiance above black, (P, Hp, Wp, 3) float32."""
    pats = np.asarray(patterns, dtype=np.float32)
    if pats.ndim == 3:
        pats = np.repeat(pats[..., None], 3, axis=-1)
    if pats.ndim != 4 or pats.shape[-1] != 3:
        raise InputError(f"patterns must be (P, Hp, Wp) or (P, Hp, Wp, 3), got shape {pats.shape}")
    if not np.isfinite(pats).all():
        raise InputError("patterns contain NaN or inf values")
    return np.clip(pats, 0.0, 1.0) ** np.float32(gamma)


def sample_projector(light: np.ndarray, xp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Bilinear lookup of emitted light (P, Hp, Wp, C) at projector points -> (N, P, C); 0 outside."""
    _, hp, wp, channels = light.shape
    xp = np.where(np.isfinite(xp), xp, -2.0)  # undecoded points (NaN): outside, without an invalid integer cast
    yp = np.where(np.isfinite(yp), yp, -2.0)
    x0 = np.floor(xp).astype(np.int64)
    y0 = np.floor(yp).astype(np.int64)
    fx = (xp - x0).astype(np.float32)[:, None, None]
    fy = (yp - y0).astype(np.float32)[:, None, None]
    out = np.zeros((xp.shape[0], light.shape[0], channels), np.float32)
    for dy, dx, w in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx), (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi < wp) & (yi >= 0) & (yi < hp)
        out[inside] += w[inside] * light[:, yi[inside], xi[inside], :].transpose(1, 0, 2)
    return out
