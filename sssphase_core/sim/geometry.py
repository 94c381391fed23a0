"""Signed-distance primitives and vectorised sphere tracing (numpy, all rays at once).

Every SDF takes points ``p`` of shape (N, 3) in object space (mm, y down like the camera) and
returns (N,) distances, negative inside. Some shapes (smooth unions, displacements, ellipsoids)
are only approximately distances; the tracer steps a fraction of the distance to stay safe.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

SDF = Callable[[np.ndarray], np.ndarray]


def length(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def sphere(p: np.ndarray, centre, radius: float) -> np.ndarray:
    return length(p - np.asarray(centre, np.float64)) - radius


def ellipsoid(p: np.ndarray, centre, radii) -> np.ndarray:
    """Approximate ellipsoid distance (bounded gradient, exact on the surface)."""
    q = p - np.asarray(centre, np.float64)
    r = np.asarray(radii, np.float64)
    k0 = length(q / r)
    k1 = np.maximum(length(q / r**2), 1e-12)
    return k0 * (k0 - 1.0) / k1


def round_box(p: np.ndarray, centre, half, radius: float) -> np.ndarray:
    q = np.abs(p - np.asarray(centre, np.float64)) - (np.asarray(half, np.float64) - radius)
    outside = length(np.maximum(q, 0.0))
    return outside + np.minimum(q.max(axis=-1), 0.0) - radius


def capsule(p: np.ndarray, a, b, radius: float) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    pa, ba = p - a, b - a
    h = np.clip(pa @ ba / (ba @ ba), 0.0, 1.0)
    return length(pa - h[:, None] * ba) - radius


def cylinder_y(p: np.ndarray, centre, radius: float, half_height: float) -> np.ndarray:
    """Capped cylinder along the y axis."""
    q = p - np.asarray(centre, np.float64)
    d = np.stack([np.hypot(q[:, 0], q[:, 2]) - radius, np.abs(q[:, 1]) - half_height], axis=-1)
    return np.minimum(d.max(axis=-1), 0.0) + length(np.maximum(d, 0.0))


def star2d(x: np.ndarray, y: np.ndarray, r_outer: float, r_inner: float, n: int = 5) -> np.ndarray:
    """Distance to an n-pointed star polygon in the plane (exact for the polygon's edges)."""
    ang = np.arctan2(x, -y)  # first point straight up (-y)
    sector = 2 * np.pi / n
    a = np.mod(ang + sector / 2, sector) - sector / 2  # fold into one sector around a point
    a = np.abs(a)
    rad = np.hypot(x, y)
    px, py = rad * np.sin(a), rad * np.cos(a)  # point in the folded frame, the tip on +py
    tip = np.array([0.0, r_outer])
    valley = np.array([r_inner * np.sin(sector / 2), r_inner * np.cos(sector / 2)])
    e = valley - tip
    wx, wy = px - tip[0], py - tip[1]
    h = np.clip((wx * e[0] + wy * e[1]) / (e @ e), 0.0, 1.0)
    dist = np.hypot(wx - h * e[0], wy - h * e[1])
    inside = (wx * e[1] - wy * e[0]) > 0  # same side of the edge as the centre
    return np.where(inside, -dist, dist)


def extrude(d2: np.ndarray, z: np.ndarray, half_depth: float) -> np.ndarray:
    w = np.stack([d2, np.abs(z) - half_depth], axis=-1)
    return np.minimum(w.max(axis=-1), 0.0) + length(np.maximum(w, 0.0))


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union) with blend radius k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def union(*ds: np.ndarray) -> np.ndarray:
    return np.minimum.reduce(ds)


def rotation_y(angle_rad: float) -> np.ndarray:
    """Rotation about the y axis (the turntable axis)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_x(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def value_noise(p: np.ndarray, scale: float, seed: int = 0) -> np.ndarray:
    """Smooth pseudo-random field in [-1, 1]: a few incommensurate sine waves (cheap, deterministic)."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phases = rng.uniform(0, 2 * np.pi, 6)
    freqs = 2 * np.pi / scale * np.array([1.0, 1.3, 1.7, 2.3, 2.9, 3.7])
    waves = np.sin((p @ dirs.T) * freqs + phases) / np.array([1.0, 1.2, 1.5, 2.0, 2.5, 3.0])
    return waves.sum(axis=-1) / 3.0


def ray_sphere(origins: np.ndarray, dirs: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry and exit distances of unit rays through a sphere at the origin; ``hit`` where it meets it."""
    b = np.einsum("ij,ij->i", origins, dirs)
    c = np.einsum("ij,ij->i", origins, origins) - radius**2
    disc = b * b - c
    hit = disc > 0
    root = np.sqrt(np.where(hit, disc, 0.0))
    return np.maximum(-b - root, 0.0), -b + root, hit


def sphere_trace(
    sdf: SDF,
    origins: np.ndarray,
    dirs: np.ndarray,
    t_near: np.ndarray,
    t_far: np.ndarray,
    *,
    eps: float = 0.01,
    step: float = 0.8,
    max_steps: int = 400,
) -> tuple[np.ndarray, np.ndarray]:
    """March all rays at once, keeping only the unfinished ones active -> (t, hit)."""
    t = t_near.astype(np.float64).copy()
    hit = np.zeros(len(t), bool)
    active = np.nonzero(t < t_far)[0]
    for _ in range(max_steps):
        if active.size == 0:
            break
        d = sdf(origins[active] + t[active, None] * dirs[active])
        done = d < eps
        hit[active[done]] = True
        t[active] += np.where(done, 0.0, np.maximum(d, eps) * step)
        active = active[~done & (t[active] < t_far[active])]
    return t, hit


def sdf_normals(sdf: SDF, p: np.ndarray, h: float = 0.02) -> np.ndarray:
    """Unit normals from the SDF gradient by central differences."""
    grad = np.empty_like(p)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        grad[:, i] = sdf(p + e) - sdf(p - e)
    return grad / np.maximum(length(grad), 1e-12)[:, None]
