"""Scattering materials: Jensen et al. 2001 measured coefficients -> Christensen-Burley parameters.

A material is described by what the light-transport model needs:

* ``albedo`` (RGB): Burley's surface albedo A, the total diffuse reflectance of the subsurface term;
* ``mfp`` (RGB, mm): the diffuse mean free path l_d = 1 / sigma_tr;
* ``rho_s``: the surface (direct, single-bounce) reflectance, added at the entry pixel only.

The normalized-diffusion profile is R(r) = s (e^{-s r} + e^{-s r / 3}) / (8 pi r) with
s = S(A) / l_d and Burley's fit for the diffuse mean free path S(A) = 3.5 + 100 (A - 0.33)^4
(Christensen & Burley 2015). Its radial CDF is 1 - e^{-s r} / 4 - 3 e^{-s r / 3} / 4.

**Measured** (Jensen, Marschner, Levoy, Hanrahan 2001, Table 2, sigma_s' and sigma_a in mm^-1,
eta = 1.3): apple, chicken1, chicken2, skin1, skin2, marble, wholemilk, skimmilk, ketchup, potato,
cream. Their albedo is the dipole's total diffuse reflectance R_d and l_d = 1 / sigma_tr. Chicken,
potato and skim milk are the materials of the objects outside the paper's splits (``extra``): their
footprints are measured physics no catalogue object was tuned to, and chicken's reach well beyond
the patch (red l_d = 11.6 mm).

**Invented** (plausible values chosen by eye, marked ``measured=False``): the red apple skin
pigment, pear, orange and tangerine peel, plastics (star, lego, shovel, sand rake), crab shell, leaf
and its veins, soap veins, stems and nails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ETA = 1.3  # relative index of refraction used by Jensen et al. for all their measurements

#: Jensen et al. 2001, Table 2: (sigma_s' RGB, sigma_a RGB) in mm^-1.
JENSEN_2001: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19)),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20)),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}


def dipole_boundary(eta: float = ETA) -> float:
    """The classical dipole's boundary term A = (1 + F_dr) / (1 - F_dr), F_dr the diffuse Fresnel reflectance of
    relative index ``eta`` (Jensen et al. 2001's fit)."""
    f_dr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    return (1 + f_dr) / (1 - f_dr)


def jensen_diffuse_reflectance(sigma_s_prime: np.ndarray, sigma_a: np.ndarray, eta: float = ETA) -> np.ndarray:
    """Total diffuse reflectance R_d of the dipole model (Jensen et al. 2001, eq. 5 integrated)."""
    sp, sa = np.asarray(sigma_s_prime, np.float64), np.asarray(sigma_a, np.float64)
    alpha = sp / (sp + sa)
    a = dipole_boundary(eta)
    root = np.sqrt(3 * (1 - alpha))
    return alpha / 2 * (1 + np.exp(-4 / 3 * a * root)) * np.exp(-root)


def diffuse_mean_free_path(sigma_s_prime: np.ndarray, sigma_a: np.ndarray) -> np.ndarray:
    """l_d = 1 / sigma_tr with sigma_tr = sqrt(3 sigma_a (sigma_a + sigma_s')) (mm)."""
    sp, sa = np.asarray(sigma_s_prime, np.float64), np.asarray(sigma_a, np.float64)
    return 1.0 / np.sqrt(3 * sa * (sa + sp))


def burley_scale(albedo: np.ndarray) -> np.ndarray:
    """Burley's S(A) for the diffuse mean free path parameterisation: s = S(A) / l_d."""
    return 3.5 + 100.0 * (np.asarray(albedo, np.float64) - 0.33) ** 4


def burley_cdf(r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Fraction of the normalized-diffusion energy within radius r (r, s broadcast)."""
    u = np.exp(-s * r / 3)
    return 1 - u**3 / 4 - 3 * u / 4


def dropped_fraction(rate: np.ndarray, pitch: float, patch: int) -> np.ndarray:
    """Share of a footprint's subsurface energy that falls outside the K x K patch, for Burley rates
    ``rate`` (RGB, mm^-1) on a flat fronto-parallel grid of ``pitch`` mm cells, with the transport's
    quadrature (ring shares, see :mod:`sssphase_core.sim.transport`), relative to an unbounded grid."""
    rate = np.asarray(rate, np.float64)
    reach = int(np.ceil(60.0 / (rate.min() * pitch)))  # e^{-s r / 3} < 1e-9 beyond
    big = max(reach, patch)
    yy, xx = np.mgrid[-big : big + 1, -big : big + 1]
    r = np.hypot(yy, xx) * pitch
    r0, hh = pitch / np.sqrt(np.pi), pitch / 2
    rr = np.where(r > 0, r, 1.0)[..., None]
    share = (burley_cdf(np.maximum(rr + hh, r0), rate) - burley_cdf(np.maximum(rr - hh, r0), rate)) * pitch / (2 * np.pi * rr)
    share[big, big] = burley_cdf(r0, rate)
    half = patch // 2
    window = share[big - half : big - half + patch, big - half : big - half + patch]
    return 1.0 - window.sum(axis=(0, 1)) / share.sum(axis=(0, 1))


@dataclass(frozen=True)
class Material:
    """One homogeneous material; ``label`` is its index in :data:`MATERIAL_NAMES`."""

    name: str
    albedo: tuple[float, float, float]
    mfp: tuple[float, float, float]  # diffuse mean free path l_d per RGB, mm
    rho_s: float
    measured: bool

    @property
    def label(self) -> int:
        return MATERIAL_NAMES.index(self.name)

    def rate(self, sss_scale: float = 1.0) -> np.ndarray:
        """Burley's s per RGB (mm^-1) once distances are scaled by ``sss_scale``."""
        return burley_scale(self.albedo) / (np.asarray(self.mfp) * sss_scale)


def from_jensen(name: str, jensen: str, *, tint: tuple[float, float, float] = (1.0, 1.0, 1.0), rho_s: float = 0.02) -> Material:
    """Material from Jensen's table.

    A ``tint`` other than 1 is an invented pigment: it multiplies the albedo and, since absorption
    also shortens the light paths, the mean free path by ``sqrt(tint)``.
    """
    sp, sa = JENSEN_2001[jensen]
    albedo = jensen_diffuse_reflectance(sp, sa) * np.asarray(tint)
    mfp = diffuse_mean_free_path(sp, sa) * np.sqrt(tint)
    measured = tint == (1.0, 1.0, 1.0)
    return Material(name, tuple(float(v) for v in albedo), tuple(float(v) for v in mfp), rho_s, measured)


def invented(name: str, albedo: tuple[float, float, float], mfp: tuple[float, float, float], rho_s: float) -> Material:
    return Material(name, albedo, mfp, rho_s, measured=False)


_ALL = (
    from_jensen("apple_flesh", "apple"),
    from_jensen("apple_red", "apple", tint=(0.95, 0.22, 0.30)),
    from_jensen("skin", "skin1", rho_s=0.03),
    from_jensen("skin_palm", "skin2", rho_s=0.03),
    from_jensen("marble", "marble", rho_s=0.03),
    from_jensen("wholemilk", "wholemilk"),
    invented("stem", (0.25, 0.17, 0.08), (0.15, 0.15, 0.15), 0.03),
    invented("pear", (0.62, 0.70, 0.22), (1.6, 1.4, 0.7), 0.03),
    invented("orange_peel", (0.85, 0.40, 0.06), (3.2, 2.2, 1.0), 0.03),
    invented("tangerine_peel", (0.88, 0.32, 0.04), (2.6, 1.6, 0.8), 0.03),
    invented("plastic_star", (0.85, 0.62, 0.05), (0.10, 0.08, 0.06), 0.05),
    invented("plastic_lego", (0.72, 0.05, 0.04), (0.20, 0.08, 0.08), 0.05),
    invented("plastic_shovel", (0.10, 0.35, 0.80), (0.9, 1.1, 1.6), 0.04),
    invented("plastic_rake", (0.20, 0.70, 0.15), (0.8, 1.3, 0.7), 0.04),
    invented("crab_shell", (0.80, 0.28, 0.12), (1.2, 0.6, 0.5), 0.04),
    invented("crab_belly", (0.85, 0.78, 0.65), (2.0, 1.8, 1.5), 0.03),
    invented("leaf", (0.18, 0.45, 0.10), (0.9, 1.4, 0.7), 0.03),
    invented("leaf_vein", (0.45, 0.70, 0.30), (1.6, 2.0, 1.2), 0.03),
    invented("soap_vein", (0.45, 0.25, 0.35), (1.0, 0.7, 0.8), 0.03),
    invented("nail", (0.85, 0.70, 0.65), (0.5, 0.4, 0.4), 0.05),
    # appended, so the labels stored in earlier sessions keep their meaning
    from_jensen("chicken", "chicken1"),
    from_jensen("chicken_fat", "chicken2"),
    from_jensen("potato", "potato"),
    from_jensen("skimmilk", "skimmilk"),
    # a matte grey wall behind the turntable (``RigConfig.backdrop``): opaque, its light leaves where it enters
    invented("backdrop", (0.35, 0.35, 0.33), (0.01, 0.01, 0.01), 0.0),
)

#: Global material label names; a material map stores indices into this tuple.
MATERIAL_NAMES: tuple[str, ...] = tuple(m.name for m in _ALL)
MATERIALS: dict[str, Material] = {m.name: m for m in _ALL}
