"""Radiative transfer by Monte Carlo: the radial exit profiles of a pencil beam normally incident on a
semi-infinite homogeneous medium (Henyey-Greenstein phase function, smooth dielectric boundary), the
simulator's third light-transport model (``radiative``) beside the two diffusion models.

Both other models are diffusion approximations, and the analytic relighting baseline is one of them
(Burley): a decoder trained on them alone learns their shape and nothing a real medium adds to it.
The random walk solves the radiative transfer equation itself, so its profiles carry what diffusion
misses -- single and low-order scattering near the entry point, the forward lean of an anisotropic
phase function (g > 0 moves the first exits away from the entry point), the boundary's internal
reflection -- and depend on the phase function's mean cosine ``g`` beyond the reduced coefficients.

Units: lengths in reduced mean free paths l' = 1 / sigma_t' (sigma_t' = sigma_s' + sigma_a); a medium
is its reduced albedo alpha' = sigma_s' / sigma_t', its ``g`` (sigma_s = sigma_s' / (1 - g)) and its
relative index ``eta``. The walk is exact up to :data:`WALK_RADIUS` l' from the entry point and depth;
a photon that wanders beyond is dropped, and the profile beyond :data:`MC_RADIUS` is the classical
dipole's (Jensen et al. 2001), scaled to meet the walk's there (diffusion is exact far from the source).

:func:`simulate` is the walk; :func:`build_table` makes the table :class:`ProfileTable` reads, shipped as
``radiative_profiles.npz`` beside this module (``python -m sssphase_core.sim.radiative --jobs 2`` remakes it).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from sssphase_core.sim.dipole import fresnel_reflectance
from sssphase_core.sim.materials import dipole_boundary

#: The walk is followed exactly within this many reduced mean free paths of the entry point (radius
#: and depth); the profile is tabulated from it out to :data:`MC_RADIUS`.
WALK_RADIUS = 24.0
MC_RADIUS = 12.0
#: Russian roulette: below this weight a photon survives with probability :data:`ROULETTE_SURVIVAL`.
ROULETTE_WEIGHT, ROULETTE_SURVIVAL = 1e-3, 0.1
TABLE_FILE = Path(__file__).with_name("radiative_profiles.npz")
#: The table's grid: phase-function mean cosines, 1 - alpha' (log-spaced) and radii (l') of the CDF.
TABLE_G = (0.0, 0.3, 0.6, 0.85)
TABLE_ABSORPTION = tuple(float(v) for v in np.geomspace(1e-4, 0.7, 14))
TABLE_ETA = 1.3
TABLE_PHOTONS = 200_000


def _hg_cosine(g: float, u: np.ndarray) -> np.ndarray:
    """Henyey-Greenstein scattering cosines from uniform ``u`` (inverse CDF)."""
    if abs(g) < 1e-6:
        return 2 * u - 1
    s = (1 - g * g) / (1 - g + 2 * g * u)
    return np.clip((1 + g * g - s * s) / (2 * g), -1.0, 1.0)


def _scatter(d: np.ndarray, cos_t: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions (n, 3) turned by polar cosine ``cos_t`` and azimuth ``phi`` about themselves."""
    sin_t = np.sqrt(np.maximum(1 - cos_t * cos_t, 0))
    cp, sp = np.cos(phi), np.sin(phi)
    ux, uy, uz = d[:, 0], d[:, 1], d[:, 2]
    den = np.sqrt(np.maximum(1 - uz * uz, 1e-24))
    a, b = sin_t * cp / den, sin_t * sp / den
    out = np.empty_like(d)
    out[:, 0] = a * ux * uz - b * uy + ux * cos_t
    out[:, 1] = a * uy * uz + b * ux + uy * cos_t
    out[:, 2] = -sin_t * cp * den + uz * cos_t
    steep = np.flatnonzero(np.abs(uz) > 0.99999)  # along the normal: turn about the z axis itself
    if len(steep):
        out[steep, 0] = sin_t[steep] * cp[steep]
        out[steep, 1] = sin_t[steep] * sp[steep]
        out[steep, 2] = np.sign(uz[steep]) * cos_t[steep]
    out /= np.sqrt(np.einsum("ij,ij->i", out, out))[:, None]
    return out


def simulate(alpha: float, g: float, eta: float, radii: np.ndarray, photons: int = TABLE_PHOTONS,
             seed: int = 0) -> tuple[np.ndarray, float]:
    """The exit profile of the medium (reduced albedo ``alpha``, mean cosine ``g``, index ``eta``) by random walk:
    ``(cdf (R,), lost)``, the share of the power that entered leaving the surface within each of ``radii`` (R,) l'
    of the entry point (increasing, at most :data:`WALK_RADIUS`), and the share that wandered beyond the walk's
    bounds. Each exit is split, not sampled: a photon meeting the boundary from inside leaves with its weight times
    the Fresnel transmittance and is reflected with the rest (mirrored: the boundary is a plane)."""
    rng = np.random.default_rng(seed)
    sigma_s = alpha / (1.0 - g)
    sigma_t = sigma_s + (1.0 - alpha)
    single = sigma_s / sigma_t
    pos = np.zeros((photons, 3))
    d = np.tile([0.0, 0.0, 1.0], (photons, 1))  # +z into the medium
    w = np.ones(photons)
    exits = np.zeros(len(radii))
    lost = 0.0
    edges = np.asarray(radii, np.float64)
    while len(w):
        step = -np.log1p(-rng.random(len(w))) / sigma_t
        pos += d * step[:, None]
        out = pos[:, 2] < 0
        while out.any():  # meets the surface: leave in part, reflect the rest
            i = np.flatnonzero(out)
            back = pos[i, 2] / d[i, 2]  # distance travelled beyond z = 0 (>= 0)
            hit = pos[i] - d[i] * back[:, None]
            reflect = fresnel_reflectance(-d[i, 2], eta, 1.0) if eta != 1.0 else np.zeros(len(i))
            r = np.hypot(hit[:, 0], hit[:, 1])
            k = np.searchsorted(edges, r)  # first radius >= r: that CDF entry and every later one count it
            np.add.at(exits, k[k < len(edges)], (w[i] * (1 - reflect))[k < len(edges)])
            w[i] *= reflect
            d[i, 2] = -d[i, 2]
            pos[i, 2] = -pos[i, 2]
            out = pos[:, 2] < 0
        far = (np.hypot(pos[:, 0], pos[:, 1]) > WALK_RADIUS) | (pos[:, 2] > WALK_RADIUS)
        lost += float(w[far].sum())
        w *= single
        low = w < ROULETTE_WEIGHT
        if low.any():
            survive = rng.random(int(low.sum())) < ROULETTE_SURVIVAL
            w[np.flatnonzero(low)] = np.where(survive, w[low] / ROULETTE_SURVIVAL, 0.0)
        keep = ~far & (w > 0)
        pos, d, w = pos[keep], d[keep], w[keep]
        n = len(w)
        d = _scatter(d, _hg_cosine(g, rng.random(n)), 2 * np.pi * rng.random(n))
    return np.cumsum(exits) / photons, lost / photons


def dipole_profile(r: np.ndarray, alpha: float, eta: float) -> np.ndarray:
    """The classical dipole's diffuse reflectance per unit area R_d(r) (Jensen et al. 2001, eq. 4) at ``r`` l'."""
    sigma_tr = np.sqrt(3 * (1 - alpha))
    zr, zv = 1.0, 1.0 + 4 / 3 * dipole_boundary(eta)
    dr, dv = np.sqrt(r * r + zr * zr), np.sqrt(r * r + zv * zv)
    return alpha / (4 * np.pi) * (zr * (sigma_tr * dr + 1) * np.exp(-sigma_tr * dr) / dr**3
                                  + zv * (sigma_tr * dv + 1) * np.exp(-sigma_tr * dv) / dv**3)


#: Radii (l') of the tabulated CDF: dense near the entry point, where pixels resolve the walk's detail, then the
#: dipole's tail out to :data:`TABLE_REACH` (hundreds of l' for the least absorbing media: l_d = l' / sqrt(3 (1 - alpha'))).
TABLE_REACH = 3000.0
TABLE_RADII = np.concatenate([[0.0], np.geomspace(0.01, MC_RADIUS, 121), np.geomspace(MC_RADIUS, TABLE_REACH, 61)[1:]])
#: The walk's last rings (radii TABLE_RADII[-61 - TAIL_MATCH] to MC_RADIUS) scale the dipole's tail to meet it.
TAIL_MATCH = 12


def full_cdf(alpha: float, g: float, eta: float, photons: int = TABLE_PHOTONS, seed: int = 0) -> np.ndarray:
    """(R,) the share of the entered power leaving within each of :data:`TABLE_RADII` l': :func:`simulate`'s
    walk up to :data:`MC_RADIUS`, then the classical dipole's profile, scaled so that its power over the walk's
    last :data:`TAIL_MATCH` rings equals the walk's; the last entry is the total diffuse reflectance."""
    inner = int(np.searchsorted(TABLE_RADII, MC_RADIUS)) + 1  # radii up to and including MC_RADIUS
    near = np.concatenate([[0.0], simulate(alpha, g, eta, TABLE_RADII[1:inner], photons, seed)[0]])
    fine = lambda lo, hi: np.linspace(lo, hi, 256)  # noqa: E731
    ring = fine(TABLE_RADII[inner - 1 - TAIL_MATCH], MC_RADIUS)
    dip = np.trapezoid(dipole_profile(ring, alpha, eta) * 2 * np.pi * ring, ring)
    scale = (near[-1] - near[-1 - TAIL_MATCH]) / dip if dip > 0 else 0.0
    tail = [0.0]
    for lo, hi in zip(TABLE_RADII[inner - 1:-1], TABLE_RADII[inner:], strict=True):
        x = fine(lo, hi)
        tail.append(tail[-1] + np.trapezoid(dipole_profile(x, alpha, eta) * 2 * np.pi * x, x))
    return np.concatenate([near, near[-1] + scale * np.asarray(tail[1:])])


def build_table(photons: int = TABLE_PHOTONS, seed: int = 0, path: Path = TABLE_FILE, jobs: int = 1,
                log=print) -> Path:  # noqa: ANN001
    """Walk every medium of the grid (:data:`TABLE_G` x :data:`TABLE_ABSORPTION`, index :data:`TABLE_ETA`), ``jobs``
    at a time (each its own seed: the same table for any ``jobs``), and write the table :class:`ProfileTable` reads
    (``cdf`` (G, A, R) over ``radii`` (R,) l')."""
    from concurrent.futures import ProcessPoolExecutor

    grid = [(i, j) for i in range(len(TABLE_G)) for j in range(len(TABLE_ABSORPTION))]
    cdf = np.zeros((len(TABLE_G), len(TABLE_ABSORPTION), len(TABLE_RADII)))
    with ProcessPoolExecutor(max_workers=max(1, jobs)) as pool:
        runs = {pool.submit(full_cdf, 1.0 - TABLE_ABSORPTION[j], TABLE_G[i], TABLE_ETA, photons, seed + 1000 * i + j): (i, j)
                for i, j in grid}
        for n, (run, (i, j)) in enumerate(runs.items(), 1):
            cdf[i, j] = run.result()
            log(f"[{n}/{len(grid)}] g {TABLE_G[i]:.2f}, 1 - alpha' {TABLE_ABSORPTION[j]:.2e}: total diffuse reflectance "
                f"{cdf[i, j, -1]:.4f}")
    np.savez_compressed(path, g=np.asarray(TABLE_G), absorption=np.asarray(TABLE_ABSORPTION), radii=TABLE_RADII,
                        cdf=cdf.astype(np.float32), eta=TABLE_ETA, photons=photons, seed=seed)
    return path


#: Points of the CDF lookup per transport (uniform in log(r + LOOKUP_EPS) from 0 to TABLE_REACH l').
LOOKUP_POINTS, LOOKUP_EPS = 1024, 0.01


@dataclass(frozen=True)
class ProfileTable:
    """The tabulated exit profiles at one mean cosine ``g``, normalised to a total of 1 (a transport gives each
    footprint its material's energy), resampled for fast lookup: :meth:`cdf` at any reduced albedo and radius."""

    g: float
    table: np.ndarray  # (A, LOOKUP_POINTS) normalised CDF, rows over log(1 - alpha') uniform
    log_absorption: tuple[float, float]  # (first, step) of the rows' log(1 - alpha')
    total: np.ndarray  # (A,) total diffuse reflectance of the rows (the walk's, before normalising)

    @classmethod
    def at(cls, g: float, path: Path = TABLE_FILE) -> ProfileTable:
        """The table at mean cosine ``g`` (linear between the tabulated ones; clamped to their range)."""
        return _table_at(round(float(g), 4), str(path))

    def cdf(self, absorption_index: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Normalised CDF at radius ``r`` (N, ...) l' for rows ``absorption_index`` (N,) (fractional, from
        :meth:`index`) -> (N, ...) float32."""
        return self.lookup(self.rows(absorption_index), r)

    def rows(self, absorption_index: np.ndarray) -> np.ndarray:
        """(N, LOOKUP_POINTS) float32: each medium's CDF over the lookup grid, blended between the table's rows
        (made once per pixel and colour; :meth:`lookup` reads it at any radius)."""
        a = np.asarray(absorption_index, np.float32).ravel()
        j0 = np.minimum(a.astype(np.int32), len(self.table) - 2)
        u = (a - j0)[:, None]
        lo = self.table[j0]
        return lo + u * (self.table[j0 + 1] - lo)

    @staticmethod
    def lookup(rows: np.ndarray, r: np.ndarray) -> np.ndarray:
        """``rows`` (N, LOOKUP_POINTS) from :meth:`rows` at radius ``r`` (N, ...) l' -> (N, ...) float32 (linear in
        log(r + LOOKUP_EPS); 1 beyond the table's reach)."""
        q = np.log(np.asarray(r, np.float32) + np.float32(LOOKUP_EPS))
        q -= np.float32(LOOKUP_START)
        q *= np.float32(1 / LOOKUP_STEP)
        np.clip(q, 0, LOOKUP_POINTS - 1.001, out=q)
        i0 = q.astype(np.int32)
        q -= i0  # the fraction between grid points
        i0 += (np.arange(len(rows), dtype=np.int32) * LOOKUP_POINTS).reshape(-1, *([1] * (np.ndim(r) - 1)))
        flat = rows.ravel()
        lo = flat[i0]
        lo += q * (flat[i0 + 1] - lo)
        return lo

    def index(self, alpha: np.ndarray) -> np.ndarray:
        """Fractional row of reduced albedos ``alpha`` (...,), clamped to the table's range."""
        first, step = self.log_absorption
        x = (np.log(np.clip(1.0 - np.asarray(alpha, np.float64), 1e-12, None)) - first) / step
        return np.clip(x, 0, len(self.table) - 1).astype(np.float32)


#: The lookup grid: log(r + LOOKUP_EPS) from LOOKUP_START in steps of LOOKUP_STEP (LOOKUP_POINTS of them).
LOOKUP_START = float(np.log(LOOKUP_EPS))
LOOKUP_STEP = float((np.log(TABLE_REACH + LOOKUP_EPS) - LOOKUP_START) / (LOOKUP_POINTS - 1))


@lru_cache(maxsize=8)
def _table_at(g: float, path: str) -> ProfileTable:
    data = np.load(path)
    gs, cdf, radii = data["g"], data["cdf"].astype(np.float64), data["radii"]
    g = float(np.clip(g, gs[0], gs[-1]))
    i = min(int(np.searchsorted(gs, g, side="right")) - 1, len(gs) - 2)
    w = (g - gs[i]) / (gs[i + 1] - gs[i])
    rows = (1 - w) * cdf[i] + w * cdf[i + 1]  # (A, R)
    total = rows[:, -1].copy()
    grid = np.exp(LOOKUP_START + LOOKUP_STEP * np.arange(LOOKUP_POINTS)) - LOOKUP_EPS
    table = np.stack([np.interp(grid, radii, row / row[-1]) for row in rows]).astype(np.float32)
    log_a = np.log(data["absorption"])
    return ProfileTable(g, table, (float(log_a[0]), float(log_a[1] - log_a[0])), total)


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description="Remake the radiative transport's profile table by random walks.")
    ap.add_argument("--photons", type=int, default=TABLE_PHOTONS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=TABLE_FILE)
    ap.add_argument("--jobs", type=int, default=1, help="media walked at once (processes)")
    args = ap.parse_args()
    print(f"wrote {build_table(args.photons, args.seed, args.out, args.jobs)}")


if __name__ == "__main__":
    main()
