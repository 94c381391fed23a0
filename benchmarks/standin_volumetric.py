"""Frames of a second stand-in for an independent renderer: light transport by Monte Carlo random walks
in a homogeneous medium (measured coefficients, Jensen et al. 2001), written without the simulator
(``sssphase_core.sim``) and without any diffusion profile.

Footprints come from photons, not from a formula: each enters the half-space below a smooth
dielectric boundary (relative index ETA) at the pixel's incidence angle, refracts, and walks
(exponential free flights, Henyey-Greenstein phase function, Fresnel reflection at the boundary)
until it is absorbed or leaves. Every scattering vertex sends its light to the camera, which looks
along the normal (next-event estimation: the phase function toward the refracted camera direction,
the attenuation to the surface, the boundary's transmission), binned at the vertex's position in
camera pixels of MM_PER_PX millimetres. So the footprints hold single scattering, the diffusion tail,
and the forward skew of oblique incidence (toward where the light travels; the fringes a pixel sees are
shifted), with nothing of the kernels our simulator or its stand-in use.

The scene is an ellipsoidal cap of mild colour texture, seen from above by an orthographic camera and lit
by an orthographic projector TILT degrees off the camera's axis along x (the baseline), so the geometry
is consistent: a pixel's incidence angle, the direction its light travels along the surface (which way
its footprint leans) and its fringe spacing all follow from the surface normal, and self-shadowed
pixels get no light. Kernels are laid flat in the image (no foreshortening) and the camera is taken to
look along each normal. Shot and read noise as the first stand-in (``standin_render.py``), float EXR
named by plan key. Kernels are cached per material, scale and phase function in OUT/kernels_*.npz; the
noise-free reference images and the exact projector coordinates of every lit pixel
(``NAME_geometry.npz``: xp, yp, theta, azimuth, and the colour texture the entering light is multiplied by) are
written beside the folder.

    python benchmarks/standin_volumetric.py OUT NAME MATERIAL MM_PER_PX SEED [G [TILT]]
    sss import OUT/NAME --object NAME --projector 256x192 --out SESSIONS

MATERIAL is one of Jensen et al. 2001's (apple, marble, skin1, ...); G the phase function's mean
cosine (default 0: the reduced coefficients as isotropic scattering; otherwise sigma_s = sigma_s' /
(1 - G)); TILT the projector's angle from the camera's axis (default 35 degrees).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from sssphase_core.processing.patterns import capture_plan
from sssphase_core.processing.projector import emitted_light

sys.path.insert(0, str(Path(__file__).resolve().parent))
from standin_render import write_frames  # noqa: E402  (the first stand-in's noise and file naming)

WP, HP, W, H = 256, 192, 200, 150
ETA = 1.3
RADIUS = 15  # kernels are (2 * RADIUS + 1) px square: the CPU preset's 32 px patch
ANGLES = np.arange(0.0, 81.0, 10.0)  # tabulated incidence angles (degrees); pixels interpolate between them

#: Jensen, Marschner, Levoy, Hanrahan 2001, Table 1: sigma_s' and sigma_a in 1/mm (R, G, B)
MEASURED = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}


def fresnel(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance for light arriving at cosine ``cos_i`` from the side of index 1 / ``eta``
    relative (``eta`` = n_other / n_here); 1 beyond the critical angle."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (1.0 - cos_i**2) / eta**2
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(tir, 1.0, 0.5 * (rs**2 + rp**2))


def hg_sample(d: np.ndarray, g: float, rng: np.random.Generator) -> np.ndarray:
    """New unit directions (N, 3) scattered from ``d`` (N, 3) by the Henyey-Greenstein phase function."""
    n = len(d)
    u = rng.random(n)
    if abs(g) < 1e-4:
        cos_t = 1.0 - 2.0 * u
    else:
        cos_t = (1.0 + g * g - ((1.0 - g * g) / (1.0 - g + 2.0 * g * u)) ** 2) / (2.0 * g)
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, 1.0))
    phi = 2.0 * np.pi * rng.random(n)
    # an orthonormal frame around d
    a = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    t1 = np.cross(a, d)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(d, t1)
    return (sin_t * np.cos(phi))[:, None] * t1 + (sin_t * np.sin(phi))[:, None] * t2 + cos_t[:, None] * d


def hg(cos_t: np.ndarray, g: float) -> np.ndarray:
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * cos_t) ** 1.5)


def mc_kernel(sigma_s_prime: float, sigma_a: float, g: float, theta_deg: float, mm_per_px: float,
              photons: int, rng: np.random.Generator, max_events: int = 20000) -> np.ndarray:
    """Camera-pixel footprint (2R+1, 2R+1) of unit irradiance entering at the centre pixel at ``theta_deg``
    (travelling toward +x); the camera looks along the normal. Radiance x pi, so a Lambertian surface of
    albedo a gives a kernel summing to a."""
    sigma_s = sigma_s_prime / (1.0 - g)
    sigma_t = sigma_s + sigma_a
    albedo = sigma_s / sigma_t
    th = np.radians(theta_deg)
    k = 2 * RADIUS + 1
    hist = np.zeros(k * k)
    sin_t = np.sin(th) / ETA
    d = np.tile([sin_t, 0.0, -np.sqrt(1.0 - sin_t**2)], (photons, 1))  # refracted, into z < 0
    pos = np.zeros((photons, 3))
    w = np.full(photons, float((1.0 - fresnel(np.cos(th), ETA)) * np.cos(th)))
    t_cam = 1.0 - float(fresnel(np.array(1.0), ETA))  # leaving along the normal
    for _ in range(max_events):
        if not len(w):
            break
        step = -np.log(1.0 - rng.random(len(w))) / sigma_t
        new = pos + step[:, None] * d
        out = np.flatnonzero(new[:, 2] > 0.0)  # reaches the boundary within this flight: reflect or leave
        if len(out):
            to_surface = -pos[out, 2] / d[out, 2]
            reflect = rng.random(len(out)) < fresnel(d[out, 2], 1.0 / ETA)  # from inside: relative index 1 / ETA
            bounced = out[reflect]
            d[bounced, 2] *= -1.0  # the rest of the flight, mirrored (a second crossing within it is rare)
            new[bounced, 2] = (step[bounced] - to_surface[reflect]) * d[bounced, 2]  # from the surface, downward
            keep = np.ones(len(w), bool)
            keep[out[~reflect]] = False  # left the medium (seen by the camera through the estimates below)
            new, d, w = new[keep], d[keep], w[keep]
        pos = new
        # a scattering event at pos: its light toward the camera (next-event estimate), then the walk goes on
        contrib = w * albedo * hg(d[:, 2], g) * np.exp(sigma_t * pos[:, 2]) * t_cam * np.pi / ETA**2
        ix = np.round(pos[:, 0] / mm_per_px).astype(int) + RADIUS
        iy = np.round(pos[:, 1] / mm_per_px).astype(int) + RADIUS
        ok = (ix >= 0) & (ix < k) & (iy >= 0) & (iy < k)
        np.add.at(hist, iy[ok] * k + ix[ok], contrib[ok])
        w = w * albedo
        d = hg_sample(d, g, rng)
        low = w < 1e-3
        survive = ~low | (rng.random(len(w)) < 0.1)  # Russian roulette keeps the estimate unbiased
        w = np.where(low, w / 0.1, w)
        pos, d, w = pos[survive], d[survive], w[survive]
    return (hist / photons).reshape(k, k)


def kernels(out: Path, material: str, mm_per_px: float, g: float, photons: int = 20000) -> np.ndarray:
    """(angles, 3, K, K) footprints, cached in OUT."""
    cache = out / f"kernels_{material}_{mm_per_px:g}_{g:g}_{photons}_{len(ANGLES)}.npz"
    if cache.exists():
        return np.load(cache)["k"]
    sp, sa = MEASURED[material]
    rng = np.random.default_rng(12345)
    table = np.stack([np.stack([mc_kernel(sp[c], sa[c], g, a, mm_per_px, photons, rng) for c in range(3)])
                      for a in ANGLES])
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(cache, k=table)
    return table


def per_pixel_kernels(table: np.ndarray, theta: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """(P, 3, K, K): the tabulated footprints interpolated to each pixel's incidence angle ``theta`` (degrees, (P,)),
    turned so that it leans along ``azimuth`` (radians in the image, (P,)); each keeps its energy."""
    import torch

    k = 2 * RADIUS + 1
    pos = np.clip(np.interp(theta, ANGLES, np.arange(len(ANGLES))), 0, len(ANGLES) - 1)
    lo = np.minimum(pos.astype(int), len(ANGLES) - 2)
    t = (pos - lo).astype(np.float32)[:, None, None, None]
    base = torch.from_numpy((1 - t) * table[lo].astype(np.float32) + t * table[lo + 1].astype(np.float32))  # leaning along +x
    off = torch.linspace(-1.0, 1.0, k)
    gy, gx = torch.meshgrid(off, off, indexing="ij")
    c = torch.from_numpy(np.cos(azimuth).astype(np.float32))[:, None, None]
    s = torch.from_numpy(np.sin(azimuth).astype(np.float32))[:, None, None]
    grid = torch.stack([gx * c + gy * s, -gx * s + gy * c], -1)  # where each output offset comes from
    turned = torch.nn.functional.grid_sample(base, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    turned *= base.sum((2, 3), keepdim=True) / turned.sum((2, 3), keepdim=True).clamp_min(1e-12)
    return turned.numpy()


def main(out: Path, name: str, material: str, mm_per_px: float, seed: int, g: float = 0.0, tilt: float = 35.0) -> None:
    import torch

    table = kernels(out, material, mm_per_px, g)
    plan = capture_plan(WP, HP, footprints=True, dot_spacing=20, references=("white", "black", "checkerboard", "stripes_x"))
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    cx, cy, ax, ay = 100 + rng.uniform(-10, 10), 75 + rng.uniform(-5, 5), rng.uniform(60, 85), rng.uniform(45, 60)
    height = 0.8 * ax  # an ellipsoidal cap seen from above (orthographic camera along -z), lengths in camera px
    q = 1.0 - ((xx - cx) / ax) ** 2 - ((yy - cy) / ay) ** 2
    inside = q > 0.03  # (the rim's grazing sliver left out)
    root = np.sqrt(np.clip(q, 0.03, None))
    z = height * root
    normal = np.stack([height * (xx - cx) / ax**2 / root, height * (yy - cy) / ay**2 / root, np.ones_like(q)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    a = np.radians(tilt)
    to_projector = np.array([np.sin(a), 0.0, np.cos(a)])  # the projector sits along +x of the camera: the baseline
    cos_i = normal @ to_projector
    lit = inside & (cos_i > 0.02)
    # the projector is orthographic too, along -to_projector: its x axis is u = (cos a, 0, -sin a)
    mapx = (1.1 * ((xx - cx) * np.cos(a) - z * np.sin(a)) + 128.0 + 0.0005 * (xx - 100) ** 2).astype(np.float32)
    mapy = (1.1 * (yy - cy) + 96.0 + 0.03 * (xx - cx)).astype(np.float32)
    travel = -to_projector + cos_i[..., None] * normal  # the light's direction along the surface after entering
    theta = np.degrees(np.arccos(np.clip(cos_i, 0.0, 1.0)))
    azimuth = np.arctan2(travel[..., 1], travel[..., 0])
    texture = np.stack([0.85 + 0.15 * np.sin(xx / rng.uniform(5, 15) + c) for c in range(3)], -1).astype(np.float32)
    k = 2 * RADIUS + 1
    weights = np.zeros((H * W, 3, k, k), np.float32)
    weights[lit.ravel()] = per_pixel_kernels(table, theta[lit], azimuth[lit])
    wt = torch.from_numpy(np.ascontiguousarray(weights.transpose(1, 2, 3, 0).reshape(3, k * k, -1)))
    del weights
    np.savez_compressed(out / f"{name}_geometry.npz", xp=np.where(lit, mapx, np.nan), yp=np.where(lit, mapy, np.nan),
                        theta=np.where(lit, theta, np.nan), azimuth=np.where(lit, azimuth, np.nan), texture=texture)

    def render(pattern: np.ndarray) -> np.ndarray:
        light = emitted_light(pattern[None], 2.2)[0]
        seen = np.stack([cv2.remap(light[..., c], mapx, mapy, cv2.INTER_LINEAR, borderValue=0) for c in range(3)], -1)
        src = torch.from_numpy(np.ascontiguousarray((seen * texture * lit[..., None]).transpose(2, 0, 1).reshape(3, 1, -1)))
        spread = torch.nn.functional.fold((wt * src).reshape(1, 3 * k * k, -1), (H, W), k, padding=RADIUS)[0]
        return (spread.numpy().transpose(1, 2, 0) * inside[..., None]).astype(np.float32)

    write_frames(out, name, plan, render, rng)


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) not in (5, 6, 7):
        sys.exit(__doc__)
    main(Path(a[0]), a[1], a[2], float(a[3]), int(a[4]), *(float(v) for v in a[5:]))
