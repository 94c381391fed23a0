"""The directional dipole (Frisvad, Hachisuka, Kjeldsen, ACM TOG 33(1) 2014): subsurface transport
that depends on the direction the light enters, the simulator's second transport model.

Light refracted into the medium along ``w12`` (from the projector direction by Snell's law) is
modelled as a ray source; its diffusion exitance at ``x_o`` skews toward the direction the light
travels, so a footprint lit obliquely is no longer radially symmetric (the Christensen-Burley
profile of :mod:`sssphase_core.sim.transport` is). With x = x_o - x_i, D = 1 / (3 sigma_t'),
sigma_tr = sqrt(sigma_a / D) and the extrapolation distance d_e = 2.131 D / sqrt(alpha'):

    S'(x, w, r) = e^{-sigma_tr r} / (4 pi^2 r^3) [ C_phi (r^2 / D + 3 (1 + sigma_tr r) x.w)
                  - C_E (3 D (1 + sigma_tr r) w.n_o - (1 + sigma_tr r + 3 D (3 (1 + sigma_tr r)
                  + sigma_tr^2 r^2) x.w / r^2) x.n_o) ]

    S_d = [S'(x, w12, d_r) - S'(x - 2 A d_e n*, w_v, d_v)] / (4 C_phi(1 / eta))

where the real source sits at the corrected distance d_r^2 = r^2 + D mu0 (D mu0 - 2 d_e cos(beta))
(mu0 = -w12.n_o > 0; else r^2 + 1 / (3 sigma_t')^2), the virtual source is mirrored in the modified
tangent plane with normal n* (n_i made perpendicular to x) and w_v = w12 - 2 (w12.n*) n*.
C_phi(eta), C_E(eta) are the first two moments of the internal Fresnel reflectance, C_phi(1/eta)
that of the external one, A = (1 - C_E) / (2 C_phi). Only the diffusion term is modelled (the
surface's direct reflection is the transport's ``rho_s`` term, as for Burley).

:func:`exitance` returns pi (S'_r - S'_v): the diffuse exitance at x_o per unit power that has
entered at x_i, so that an image value (our units: a white Lambertian surface reads its
irradiance) is ``E a_i T_i exitance T_o / (4 C_phi(1/eta))`` with T the Fresnel transmittances at
entry (projector angle) and exit (camera angle).

**Energy.** As published, the model's total diffuse reflectance at normal incidence exceeds the
classical dipole's and reaches 1.10 at alpha' = 0.999 (measured here by quadrature; the classical
dipole gives 0.86): more light out than in. :func:`normal_energy` tabulates it against alpha' (it
depends on alpha' alone) and :func:`exitance` divides by it and multiplies by the classical
R_d(alpha'), so at normal incidence the total equals the material's albedo, as for the Burley
model, while the profile's shape, its skew and the energy's dependence on the incidence angle
stay the model's.

Materials keep the catalogue's parameters (Burley albedo A and diffuse mean free path l_d):
:func:`coefficients` returns the sigma_s', sigma_a whose classical dipole has total diffuse
reflectance A and 1 / sigma_tr = l_d (exact for the Jensen 2001 materials, which were converted
the other way).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from sssphase_core.sim.materials import ETA, jensen_diffuse_reflectance

#: Extrapolation-distance constant of the directional dipole (d_e = 2.131 D / sqrt(alpha')).
EXTRAPOLATION = 2.131
#: Largest reduced scattering albedo given to a material (alpha' -> 1 means no absorption at all).
ALPHA_MAX = 1.0 - 1e-6


def fresnel_reflectance(cos_i: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a smooth dielectric boundary for light going from index n1
    into n2 at incidence cosine ``cos_i`` in [0, 1]; 1 beyond the critical angle."""
    ci = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)
    sin_t2 = (n1 / n2) ** 2 * (1.0 - ci * ci)
    ct = np.sqrt(np.clip(1.0 - sin_t2, 0.0, None))
    rs = (n1 * ci - n2 * ct) / np.maximum(n1 * ci + n2 * ct, 1e-300)
    rp = (n1 * ct - n2 * ci) / np.maximum(n1 * ct + n2 * ci, 1e-300)
    return np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs * rs + rp * rp))


@lru_cache(maxsize=8)
def _moments(n1: float, n2: float) -> tuple[float, float]:
    """(2 C1, 3 C2) = (2 int F mu dmu, 3 int F mu^2 dmu) over mu in [0, 1] (Gauss-Legendre)."""
    t, w = np.polynomial.legendre.leggauss(400)
    # two panels, split at the critical angle where F has a kink (internal reflection)
    mu_c = float(np.sqrt(max(0.0, 1.0 - (n2 / n1) ** 2))) if n1 > n2 else 0.0
    total = np.zeros(2)
    for lo, hi in ((0.0, mu_c), (mu_c, 1.0)):
        if hi <= lo:
            continue
        mu = lo + (hi - lo) * (t + 1) / 2
        f = fresnel_reflectance(mu, n1, n2) * w * (hi - lo) / 2
        total += (2 * np.sum(f * mu), 3 * np.sum(f * mu * mu))
    return float(total[0]), float(total[1])


@dataclass(frozen=True)
class Boundary:
    """Constants of a boundary with relative index ``eta`` (inside / outside)."""

    eta: float
    c_phi: float  # C_phi(eta) = (1 - 2 C1) / 4, internal reflection
    c_e: float  # C_E(eta) = (1 - 3 C2) / 2, internal reflection
    c_phi_out: float  # C_phi(1 / eta), external reflection: 4 c_phi_out is the diffuse transmittance out

    @classmethod
    def of(cls, eta: float = ETA) -> Boundary:
        if not eta > 1.0:
            raise ValueError(f"relative index of refraction must be > 1, got {eta}")
        c1_in, c2_in = _moments(eta, 1.0)
        c1_out, _ = _moments(1.0, eta)
        return cls(float(eta), (1 - c1_in) / 4, (1 - c2_in) / 2, (1 - c1_out) / 4)

    @property
    def reflection(self) -> float:
        """A = (1 - C_E) / (2 C_phi), the boundary's reflection parameter."""
        return (1 - self.c_e) / (2 * self.c_phi)

    def transmittance(self, cos_outside: np.ndarray) -> np.ndarray:
        """Fresnel transmittance for light crossing the boundary at ``cos_outside`` (the angle on the
        air side), either way (reciprocity)."""
        return 1.0 - fresnel_reflectance(cos_outside, 1.0, self.eta)


def coefficients(albedo: np.ndarray, mfp: np.ndarray, eta: float = ETA) -> tuple[np.ndarray, np.ndarray]:
    """(sigma_s', sigma_a) in 1 / (unit of ``mfp``) whose classical dipole (Jensen et al. 2001) has
    total diffuse reflectance ``albedo`` and diffuse mean free path 1 / sigma_tr = ``mfp``.

    ``albedo`` is clipped to the dipole's range; R_d(alpha') is increasing, so alpha' is found by
    bisection (60 halvings: machine precision)."""
    a = np.clip(np.asarray(albedo, np.float64), 1e-6, float(jensen_diffuse_reflectance(ALPHA_MAX, 1.0 - ALPHA_MAX, eta)))
    lo, hi = np.zeros_like(a), np.full_like(a, ALPHA_MAX)
    for _ in range(60):
        mid = (lo + hi) / 2
        low = jensen_diffuse_reflectance(mid, 1.0 - mid, eta) < a  # R_d depends on alpha' only
        lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
    alpha = (lo + hi) / 2
    sigma_t = 1.0 / (np.asarray(mfp, np.float64) * np.sqrt(3 * (1 - alpha)))
    return alpha * sigma_t, (1 - alpha) * sigma_t


def refract_in(incident: np.ndarray, normal: np.ndarray, eta: float = ETA) -> np.ndarray:
    """Direction (..., 3) of light travelling along unit ``incident`` (toward the surface) after it
    enters through a surface with outward unit ``normal`` (Snell, relative index ``eta``)."""
    cos_i = np.clip(-np.sum(incident * normal, axis=-1, keepdims=True), 0.0, 1.0)
    cos_t = np.sqrt(1.0 - (1.0 - cos_i * cos_i) / eta**2)
    out = incident / eta + (cos_i / eta - cos_t) * normal
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _ray_source(xw: np.ndarray, xn: np.ndarray, wn: np.ndarray, r: np.ndarray, d: np.ndarray,
                s_tr: np.ndarray, bd: Boundary) -> np.ndarray:
    """S'(x, w, r) of the module docstring (without 1 / (4 C_phi(1/eta))) from x.w, x.n_o, w.n_o."""
    r2 = r * r
    sr = s_tr * r
    one = 1.0 + sr
    t1 = r2 / d + 3.0 * one * xw
    t2 = 3.0 * d * one * wn
    t3 = (one + 3.0 * d * (3.0 * one + sr * sr) / r2 * xw) * xn
    return np.exp(-sr) / (4 * np.pi**2 * r2 * r) * (bd.c_phi * t1 - bd.c_e * (t2 - t3))


def exitance(x: np.ndarray, w12: np.ndarray, n_i: np.ndarray, n_o: np.ndarray,
             sigma_s: np.ndarray, sigma_a: np.ndarray, boundary: Boundary,
             normalise: bool = True) -> np.ndarray:
    """Diffuse exitance pi (S'_r - S'_v) at x_o = x_i + ``x`` per unit power entered at x_i along
    ``w12`` (refracted, unit), per colour; never negative.

    Shapes: ``x`` (..., 3) offsets, ``w12`` / ``n_i`` / ``n_o`` (..., 3) unit vectors (broadcast),
    ``sigma_s`` (reduced) and ``sigma_a`` (..., C) -> (..., C). The geometry is computed once for
    all colours. ``normalise``: scaled so that the total at normal incidence is the classical
    dipole's R_d(alpha') (module docstring)."""
    sig_s, sig_a = np.asarray(sigma_s), np.asarray(sigma_a)
    sig_t = sig_s + sig_a
    alpha = sig_s / sig_t
    d = 1.0 / (3.0 * sig_t)
    s_tr = np.sqrt(sig_a / d)
    d_e = EXTRAPOLATION * d / np.sqrt(alpha)
    lift = 2.0 * boundary.reflection * d_e  # distance of the virtual source from x_i
    # geometry, shared by the colours (trailing axis of length 1 to broadcast against them)
    r2 = _dot(x, x)[..., None]
    xw = _dot(x, w12)[..., None]
    xn = _dot(x, n_o)[..., None]
    wn = _dot(w12, n_o)[..., None]
    # modified tangent plane: n_i made perpendicular to x (n_i itself where x = 0)
    n_star = n_i * r2 - x * _dot(x, n_i)[..., None]
    norm = np.linalg.norm(n_star, axis=-1, keepdims=True)
    tiny = np.finfo(np.result_type(norm, np.float32)).tiny
    n_star = np.where(norm > 1e-6 * np.maximum(r2, tiny), n_star / np.maximum(norm, tiny), n_i)
    wv_n = _dot(w12, n_star)[..., None]  # w_v = w12 - 2 (w12.n*) n*
    x_ns = _dot(x, n_star)[..., None]
    ns_no = _dot(n_star, n_o)[..., None]
    x_wv = xw - 2 * wv_n * x_ns  # x.w_v
    wv_no = wn - 2 * wv_n * ns_no  # w_v.n_o
    # real source at the corrected distance
    cos_beta = -np.sqrt(np.clip(r2 - xw * xw, 0.0, None) / (r2 + d_e * d_e))
    mu0 = -wn
    z2 = np.where(mu0 > 0, d * mu0 * (d * mu0 - 2.0 * d_e * cos_beta), 1.0 / (3.0 * sig_t) ** 2)
    real = _ray_source(xw, xn, wn, np.sqrt(r2 + z2), d, s_tr, boundary)
    # virtual source at x_v = x_i + lift n*: x_o - x_v = x - lift n*, with n*.w_v = -(w12.n*)
    xvw = x_wv + lift * wv_n  # (x - lift n*).w_v = x.w_v - lift (n*.w_v)
    xvn = xn - lift * ns_no
    d_v = np.sqrt(np.clip(r2 - 2 * lift * x_ns + lift * lift, 0.0, None))
    virtual = _ray_source(xvw, xvn, wv_no, d_v, d, s_tr, boundary)
    out = np.maximum(np.pi * (real - virtual), 0.0)
    if normalise:
        out = out * (jensen_diffuse_reflectance(alpha, 1.0 - alpha, boundary.eta) / normal_energy(alpha, boundary.eta))
    return out


_ALPHA_GRID = 1.0 - np.geomspace(1.0 - ALPHA_MAX, 0.999, 96)[::-1]  # dense toward alpha' = 1


@lru_cache(maxsize=4)
def _energy_table(eta: float) -> np.ndarray:
    """Total of the unnormalised exitance over a flat plane at normal incidence, at ``_ALPHA_GRID``."""
    bd = Boundary.of(eta)
    t, w = np.polynomial.legendre.leggauss(400)
    u = (t + 1) / 2
    n = np.array([0.0, 0.0, 1.0])
    w12 = np.array([0.0, 0.0, -1.0])
    out = np.empty(len(_ALPHA_GRID))
    for i, alpha in enumerate(_ALPHA_GRID):  # sigma_t' = 1: the total is scale free
        reach = 60.0 / np.sqrt(3 * (1 - alpha))  # e^{-sigma_tr r} < 1e-26 beyond
        r = reach * u**4
        x = np.stack([r, np.zeros_like(r), np.zeros_like(r)], -1)
        f = exitance(x, w12, n, n, np.array([alpha]), np.array([1.0 - alpha]), bd, normalise=False)[:, 0]
        out[i] = 2 * np.pi * np.sum(f * r * reach * 2 * u**3 * w)
    return out


def normal_energy(alpha: np.ndarray | float, eta: float = ETA) -> np.ndarray:
    """Total diffuse exitance of the unnormalised model (per unit entered power) on a flat plane lit
    at normal incidence, for reduced albedo ``alpha`` (interpolated in a 96-point table)."""
    return np.interp(np.asarray(alpha, np.float64), _ALPHA_GRID, _energy_table(float(eta)))
