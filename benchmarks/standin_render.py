"""Frames of a stand-in for an independent renderer, written without the simulator (``sssphase_core.sim``):
an ellipse of colour-textured albedo seen through a slightly curved camera->projector map, light spread
by a normalised exponential kernel per colour (lengths in camera px), Poisson shot noise (6000 photons
per unit) and Gaussian read noise (7e-4), as float EXR named by plan key for `sss import`. The noise-free
reference images are written beside the folder (``<name>_clean_ref__*.exr``).

With FORWARD = g > 0 the kernels are directional instead, as for light entering obliquely: each lit
pixel spreads its light by exp(-(r - g_p d.e_p) / L) (d: offset, r = |d|, e_p: the incidence direction
projected on the surface, mostly along the projector baseline, g_p from 0.3 g to g across the object),
so footprints are skewed forward and the fringes a pixel sees are shifted; no kernel family of ours.

With FLOOR = a > 0 a diffuse, non-scattering surface of albedo a fills the frame behind the object (a
table or a wall, as most renders have; the object's light stays inside its silhouette).

    python benchmarks/standin_render.py OUT NAME L_R L_G L_B SEED [FORWARD [FLOOR]]
    sss import OUT/NAME --object NAME --projector 256x192 --out SESSIONS
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from sssphase_core.processing.patterns import capture_plan
from sssphase_core.processing.projector import emitted_light
from sssphase_core.store.exr import write_exr

WP, HP, W, H = 256, 192, 200, 150


def directional_spread(lengths: tuple[float, float, float], forward: np.ndarray, angle: np.ndarray, radius: int = 12):
    """Per-pixel forward-skewed exponential kernels -> spread(seen (H, W, 3)) -> (H, W, 3), light kept inside."""
    import torch

    k = 2 * radius + 1
    dy, dx = (t.reshape(-1, 1) for t in np.mgrid[-radius : radius + 1, -radius : radius + 1].astype(np.float32))
    r = np.hypot(dx, dy)
    along = dx * np.cos(angle).reshape(1, -1) + dy * np.sin(angle).reshape(1, -1)  # (K*K, H*W)
    weights = []
    for lam in lengths:
        w = np.exp(-(r - forward.reshape(1, -1) * along) / lam)
        weights.append(w / w.sum(0, keepdims=True))
    wt = torch.from_numpy(np.concatenate(weights, 0).astype(np.float32))  # (3*K*K, H*W), channel-major

    def spread(seen: np.ndarray) -> np.ndarray:
        src = torch.from_numpy(np.ascontiguousarray(seen.transpose(2, 0, 1).reshape(3, 1, -1)))
        cols = (wt.view(3, k * k, -1) * src).reshape(1, 3 * k * k, -1)
        out = torch.nn.functional.fold(cols, (H, W), k, padding=radius)[0]
        return out.numpy().transpose(1, 2, 0)

    return spread


def write_frames(out: Path, name: str, plan, render, rng: np.random.Generator) -> None:  # noqa: ANN001
    """Every frame of ``plan`` rendered (``render(pattern) -> (H, W, 3)``), with Poisson shot noise (6000
    photons per unit) and Gaussian read noise (7e-4), as float EXR named by its key in OUT/NAME; the
    reference patterns also noise-free beside the folder (``NAME_clean_ref__*.exr``)."""
    folder = out / name
    folder.mkdir(parents=True, exist_ok=False)
    for f in plan:
        img = render(f.pattern())
        noisy = rng.poisson(np.maximum(img, 0) * 6000) / 6000 + rng.normal(0, 0.0007, img.shape)
        write_exr(folder / (f.key.replace("/", "__") + ".exr"), noisy.astype(np.float32))
        if f.key.startswith("ref/"):
            write_exr(out / f"{name}_clean_{f.key.replace('/', '__')}.exr", img)


def main(out: Path, name: str, lengths: tuple[float, float, float], seed: int, forward: float = 0.0,
         floor: float = 0.0) -> None:
    plan = capture_plan(WP, HP, footprints=True, dot_spacing=20, references=("white", "black", "checkerboard", "stripes_x"))
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    mapx = (xx * 1.1 + 15 + 0.0005 * (xx - 100) ** 2).astype(np.float32)
    mapy = (yy * 1.1 + 12 + 0.03 * xx).astype(np.float32)
    cx, cy, ax, ay = 100 + rng.uniform(-10, 10), 75 + rng.uniform(-5, 5), rng.uniform(60, 85), rng.uniform(45, 60)
    inside = ((xx - cx) ** 2 / ax**2 + (yy - cy) ** 2 / ay**2) < 1
    base = rng.uniform(0.3, 0.9, 3)
    albedo = np.stack([base[c] * (0.8 + 0.2 * np.sin(xx / rng.uniform(5, 15) + c)) for c in range(3)], -1).astype(np.float32)
    r = np.hypot(*np.mgrid[-15:16, -15:16]).astype(np.float32)
    kernels = [np.exp(-r / lam) / np.exp(-r / lam).sum() for lam in lengths]
    if forward > 0:
        g = forward * np.clip(0.3 + 0.35 * ((xx - cx) / ax + 1), 0.3, 1.0)
        directional = directional_spread(lengths, g.astype(np.float32), (0.25 * (yy - cy) / ay).astype(np.float32))

    def render(pattern: np.ndarray) -> np.ndarray:
        light = emitted_light(pattern[None], 2.2)[0]
        seen = np.stack([cv2.remap(light[..., c], mapx, mapy, cv2.INTER_LINEAR, borderValue=0) for c in range(3)], -1)
        seen = seen * inside[..., None] * albedo
        if forward > 0:
            spread = directional(seen)
        else:
            spread = np.stack([cv2.filter2D(seen[..., c], -1, kernels[c], borderType=cv2.BORDER_CONSTANT) for c in range(3)], -1)
        return (spread * inside[..., None] + floor * light_on_floor(light) * ~inside[..., None]).astype(np.float32)

    def light_on_floor(light: np.ndarray) -> np.ndarray:  # the floor is farther: its own camera -> projector map
        fx, fy = (mapx * 0.97 + 4).astype(np.float32), (mapy * 0.97 + 3).astype(np.float32)
        return np.stack([cv2.remap(light[..., c], fx, fy, cv2.INTER_LINEAR, borderValue=0) for c in range(3)], -1)

    write_frames(out, name, plan, render, rng)


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) not in (6, 7, 8):
        sys.exit(__doc__)
    main(Path(a[0]), a[1], (float(a[2]), float(a[3]), float(a[4])), int(a[5]), *(float(v) for v in a[6:]))
