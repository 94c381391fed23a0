"""The projector's light model, shared by the simulator and relighting (numpy only, no torch).

A pattern value v in [0, 1] makes the projector emit ``black + (1 - black) * v**gamma``; a camera
pixel receives the emitted light of the projector point it sees, looked up bilinearly in the
emitted (linear) domain, and nothing outside the projector image; relighting averages it over a camera
pixel's footprint where that spans several projector pixels (:func:`area_sample_projector`). Keeping this in one
place is what makes relighting with exact footprints reproduce the simulator's renders.
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


def area_sample_projector(light: np.ndarray, xp: np.ndarray, yp: np.ndarray, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
    """Mean emitted light (P, Hp, Wp, C) over boxes ``wx`` x ``wy`` projector px (N,) centred at projector points
    (N,) -> (N, P, C), 0 outside the projector: what a camera pixel records whose footprint on the projector is that
    box (a camera coarser than the projector integrates several projector pixels). Exact for the projector's square
    pixels: their summed-area table is bilinear within each pixel, so it is read bilinearly at the box's corners.
    With widths of 1 it is :func:`sample_projector`."""
    n_pat, hp, wp, channels = light.shape
    ok = np.isfinite(xp) & np.isfinite(yp)
    xp, yp = np.where(ok, xp, -1e6), np.where(ok, yp, -1e6)  # undecoded points: far outside, no light
    half_x, half_y = np.asarray(wx, np.float64) / 2, np.asarray(wy, np.float64) / 2

    def corner(coord: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray]:  # pixel edge k lies at k - 0.5
        u = np.clip(coord + 0.5, 0.0, float(side))
        i = np.minimum(np.floor(u).astype(np.int64), side - 1)
        return i, (u - i)[:, None]

    xs = [corner(xp - half_x, wp), corner(xp + half_x, wp)]
    ys = [corner(yp - half_y, hp), corner(yp + half_y, hp)]
    area = (4 * half_x * half_y)[:, None]
    out = np.empty((len(xp), n_pat, channels), np.float32)
    table = np.zeros((hp + 1, wp + 1, channels))
    for k in range(n_pat):  # one float64 table at a time: 1080p patterns would take GBs at once
        table[1:, 1:] = np.asarray(light[k], np.float64).cumsum(0).cumsum(1)
        total = np.zeros((len(xp), channels))
        for (iy, fy), sy in zip(ys, (-1, 1), strict=True):
            for (ix, fx), sx in zip(xs, (-1, 1), strict=True):
                at = ((1 - fy) * ((1 - fx) * table[iy, ix] + fx * table[iy, ix + 1])
                      + fy * ((1 - fx) * table[iy + 1, ix] + fx * table[iy + 1, ix + 1]))
                total += sx * sy * at
        out[:, k] = total / area
    return out


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
