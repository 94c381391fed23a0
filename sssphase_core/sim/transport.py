"""Light transport: per-pixel footprints and rendering of any projector pattern with one linear operator.

Light entering the surface at camera pixel p (irradiance factor E_p, relative to the reference
white) leaves it at pixel q with

    F_p(q) = E_p * [ rho_s,p [q == p] + A_p * frac_p(q) * a_p / a_q ]

where ``frac_p(q)`` is the share of the Christensen-Burley normalized-diffusion energy of p's
material (entry-point albedo A_p and rate s_p, per RGB: scattering uses the entry point's
material) that lands in surface cell q, and a is a pixel's surface cell area (power enters over
a_p, radiance leaves per a_q). r = |X_q - X_p| is the 3D distance, so footprints stretch with
foreshortening. Discretisation, chosen so the profile's 1/r pole is integrated, never sampled:

* the pixel itself receives ``CDF(r0)``, the energy within the disc of its own area,
  r0 = sqrt(a_p / pi);
* a neighbour at distance r receives the profile averaged over the ring [r - h/2, r + h/2] of
  width h = sqrt(a_p) (the entry cell's size), outside the pixel's own disc, times its own area:
  ``frac = a_q * (CDF(max(r + h/2, r0)) - CDF(max(r - h/2, r0))) / (2 pi r h)``, hence
  ``F_p(q) = E_p A_p sqrt(a_p) (CDF(max(r + h/2, r0)) - CDF(max(r - h/2, r0))) / (2 pi r)``.
  Checked on flat lattices: the shares sum to the exact CDF within 5 % on square cells and within
  8 % on cells foreshortened 10:1 (without the r0 clamp, overlapping rings double count there).
  For r - h/2 >= r0 the ring is ``t (alpha + beta t^2)`` with t = exp(-s r / 3) and per-pixel
  constants: one exp per entry and colour.

Targets are the K x K window around p restricted to the surface mask (off-surface cells are placed
far away, so their weight underflows to exactly 0): footprints are cut at silhouettes and energy
beyond the window is dropped. Rendering computes footprints chunk by chunk, only for pixels lit by
some pattern, and applies each chunk to all patterns at once as one sparse (targets x sources)
matrix product per colour channel (scipy's compiled CSC kernel: measured faster than
``np.bincount`` per pattern and channel, see ``sssphase_core.bench.sim_bench``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from numpy.lib.stride_tricks import sliding_window_view

from sssphase_core.sim import dipole
from sssphase_core.sim.materials import burley_cdf
from sssphase_core.sim.radiative import ProfileTable

#: Footprint entries evaluated per chunk (bounds the temporary memory to ~100 MB).
CHUNK_ENTRIES = 1_000_000
#: Footprints of all lit pixels are kept after the first render when they fit in this many bytes
#: (the CPU preset: ~40-160 MB per view), so later renders only pay for the splat.
CACHE_BYTES = 256 * 2**20
FAR = 1e6  # mm, position given to off-surface cells
#: Neighbours with r < r0 + h/2 (clamped ring) lie within this many pixels: h <= sqrt(10) pixel
#: pitches at the grazing clamp, and depths across an object differ by less than 4:3.
NEAR = 5
#: Burley s is capped at RATE_CAP / h (h = sqrt(a_p)): scattering over less than 1/120 of a pixel
#: is a delta anyway (CDF(r0) > 1 - 1e-9), and the cap keeps exp() in the closed form finite.
RATE_CAP = 120.0


@dataclass
class SurfaceMaps:
    """Per camera pixel geometry and material of one view; float maps are NaN off the surface."""

    mask: np.ndarray  # (H, W) bool
    points: np.ndarray  # (H, W, 3) camera-space mm
    area: np.ndarray  # (H, W) surface cell area, mm^2
    irradiance: np.ndarray  # (H, W) E_p, 0 where not lit by the projector
    albedo: np.ndarray  # (H, W, 3)
    rate: np.ndarray  # (H, W, 3) Burley s, mm^-1 (after sss_scale)
    rho_s: np.ndarray  # (H, W)


@dataclass
class DirectionalMaps:
    """What the directional dipole adds to :class:`SurfaceMaps` (NaN / 0 off the surface)."""

    normals: np.ndarray  # (H, W, 3) outward unit normals, camera space
    light_dir: np.ndarray  # (H, W, 3) unit direction the projector light travels, camera space
    cos_in: np.ndarray  # (H, W) cosine between the normal and the direction to the projector
    cos_view: np.ndarray  # (H, W) |cosine| between the normal and the camera ray
    mfp: np.ndarray  # (H, W, 3) diffuse mean free path l_d, mm (after sss_scale)
    eta: float = dipole.ETA


class Transport:
    """Footprints of surface pixels and their splatting, for a fixed patch size K (Christensen-Burley
    normalized diffusion; :class:`DirectionalTransport` for the directional dipole)."""

    name = "burley"

    def __init__(self, maps: SurfaceMaps, patch: int):
        self.maps, self.k = maps, patch
        h, w = maps.mask.shape
        self.h, self.w = h, w
        self.half = half = patch // 2
        self.hpad, self.wpad = h + patch, w + patch
        pad = ((half, patch - half), (half, patch - half))
        # Off-surface cells sit "infinitely" far away, so their weights underflow to exactly 0.
        planes = np.where(maps.mask[None], np.moveaxis(np.nan_to_num(maps.points), -1, 0), FAR).astype(np.float32)
        self._windows = [sliding_window_view(np.pad(p, pad, constant_values=FAR), (patch, patch)) for p in planes]
        oy, ox = np.mgrid[0:patch, 0:patch]
        self._offsets = (oy * self.wpad + ox).ravel().astype(np.int32)
        lit = maps.mask & (maps.irradiance > 0)
        self.lit_index = np.flatnonzero(lit)  # sources that can emit anything
        self.cache_bytes = CACHE_BYTES
        self._cache: np.ndarray | None = None  # (3, n_lit, K, K) footprints of lit_index
        self._position = np.full(h * w, -1, np.int64)
        self._position[self.lit_index] = np.arange(len(self.lit_index))

    def chunk_size(self) -> int:
        return max(1, CHUNK_ENTRIES // (self.k * self.k))

    def cache(self) -> bool:
        """Compute and keep the footprints of every lit pixel if they fit in ``cache_bytes``."""
        if self._cache is None and 3 * len(self.lit_index) * self.k**2 * 4 <= self.cache_bytes:
            cache = np.empty((3, len(self.lit_index), self.k, self.k), np.float32)
            step = self.chunk_size()
            for start in range(0, len(self.lit_index), step):
                cache[:, start : start + step] = self._compute(self.lit_index[start : start + step])
            self._cache = cache
        return self._cache is not None

    def weights(self, index: np.ndarray) -> np.ndarray:
        """Footprints of pixels with flat image ``index`` (N,) -> (3, N, K, K) float32."""
        if self._cache is not None:
            pos = self._position[index]
            out = np.take(self._cache, np.maximum(pos, 0), axis=1)
            if (pos < 0).any():
                out[:, pos < 0] = 0.0  # not lit: no footprint
            return out
        return self._compute(index)

    def _distances(self, index: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
        """``((y, x), r)``: the pixels' rows and columns and the 3D distance (N, K, K) float32 from each to every
        cell of its window (the pixel itself set to 1: it gets the disc term)."""
        y, x = np.divmod(index, self.w)
        r2 = np.zeros((len(index), self.k, self.k), np.float32)
        for plane, win in zip(self.maps.points.transpose(2, 0, 1), self._windows, strict=True):
            d = win[y, x] - plane[y, x][:, None, None]
            r2 += d * d
        r = np.sqrt(r2)
        r[:, self.half, self.half] = 1.0
        return (y, x), r

    def _compute(self, index: np.ndarray) -> np.ndarray:
        m, k = self.maps, self.k
        yx, r = self._distances(index)
        inv_r = 1.0 / r

        e = m.irradiance[yx].astype(np.float64)
        ap = m.area[yx].astype(np.float64)
        hh = np.sqrt(ap) / 2  # half ring width
        rate = np.minimum(m.rate[yx].astype(np.float64), RATE_CAP / (2 * hh[:, None]))
        scale = (e * 2 * hh / (2 * np.pi))[:, None] * m.albedo[yx]  # E A sqrt(a_p) / (2 pi), (N, 3)
        s3 = rate / 3
        a_, b_ = np.exp(s3 * hh[:, None]), np.exp(-s3 * hh[:, None])
        # ring = (u_lo^3 - u_hi^3)/4 + 3 (u_lo - u_hi)/4, u = t * (A or B), t = exp(-s r / 3), if r - h/2 >= r0
        alpha = (0.75 * (a_ - b_) * scale).astype(np.float32)
        beta = ((a_ - b_) * (a_**2 + 1 + b_**2) / 4 * scale).astype(np.float32)
        r0 = np.sqrt(ap / np.pi)
        near = slice(max(self.half - NEAR, 0), self.half + NEAR + 1)
        n_close, y_close, x_close = np.nonzero(r[:, near, near] < (r0 + hh).astype(np.float32)[:, None, None])
        close = (n_close, y_close + near.start, x_close + near.start)
        out = np.empty((3, len(index), k, k), np.float32)
        for c in range(3):
            t = np.exp(r * -s3[:, c].astype(np.float32)[:, None, None])
            t2 = t * t
            t2 *= beta[:, c, None, None]
            t2 += alpha[:, c, None, None]
            t2 *= t
            t2 *= inv_r
            out[c] = t2
            if close[0].size:  # rings reaching into the pixel's own disc: clamp them at r0
                n, rc = close[0], r[close].astype(np.float64)
                sc = s3[n, c]
                ring = burley_cdf(np.maximum(rc + hh[n], r0[n]), 3 * sc) - burley_cdf(np.maximum(rc - hh[n], r0[n]), 3 * sc)
                out[c][close] = ring * scale[n, c] / rc
            out[c, :, self.half, self.half] = burley_cdf(r0, rate[:, c]) * e * m.albedo[yx][:, c]
        out[:, :, self.half, self.half] += (e * m.rho_s[yx])[None]
        return out

    def footprints(self, index: np.ndarray) -> np.ndarray:
        """(N, K, K, 3) footprints of pixels with flat image ``index``; zero for unlit pixels."""
        index = np.asarray(index, np.int64)
        out = np.zeros((len(index), self.k, self.k, 3), np.float32)
        lit = np.flatnonzero(self._position[index] >= 0)
        step = self.chunk_size()
        for start in range(0, len(lit), step):
            sel = lit[start : start + step]
            out[sel] = np.moveaxis(self.weights(index[sel]), 0, -1)
        return out

    def splat(
        self,
        sources: np.ndarray,
        light: np.ndarray,
        progress: Callable[[int, int], None] | None = None,
    ) -> np.ndarray:
        """sum_p F_p(q - p) * light_p for sources (N,) flat index and light (N, P, 3) -> (P, H, W, 3)."""
        n_pat, kk = light.shape[1], self.k * self.k
        self.cache()
        out = np.zeros((3, self.hpad * self.wpad, n_pat), np.float32)
        step = self.chunk_size()
        for start in range(0, len(sources), step):
            src = sources[start : start + step]
            w = self.weights(src)
            y, x = np.divmod(src, self.w)
            corner = y * self.wpad + x  # window top-left = (y, x) in padded coordinates
            lo, hi = int(corner.min()), int(corner.max() + self._offsets[-1]) + 1
            rows = ((corner - lo).astype(np.int32)[:, None] + self._offsets[None, :]).ravel()
            indptr = np.arange(0, len(src) * kk + 1, kk, dtype=np.int32)
            for c in range(3):
                t = scipy.sparse.csc_array((w[c].ravel(), rows, indptr), shape=(hi - lo, len(src)))
                out[c, lo:hi] += t @ light[start : start + step, :, c]
            if progress is not None:
                progress(min(start + step, len(sources)), len(sources))
        img = out.reshape(3, self.hpad, self.wpad, n_pat)[:, self.half : self.half + self.h, self.half : self.half + self.w]
        return np.ascontiguousarray(img.transpose(3, 1, 2, 0))


#: Neighbours within this many pixels of the entry pixel are integrated over their cell with
#: SUBSAMPLES x SUBSAMPLES points (the directional profile varies within a cell there); the entry
#: pixel's own disc with DISC_NODES radial x DISC_NODES angular Gauss / uniform nodes.
NEAR_CELLS = 2
SUBSAMPLES = 4
DISC_NODES = 16


class DirectionalTransport(Transport):
    """Footprints from the directional dipole (:mod:`sssphase_core.sim.dipole`): they skew toward
    the direction the projector light travels once refracted, and their energy depends on the
    incidence angle; the splatting, caching and the direct ``rho_s`` term are the Burley
    transport's.

    Discretisation: ``F_p(q) = E_p a_p T_in,p R(p -> q) T_out,q / (4 C_phi(1/eta))`` (R: the
    exitance per unit entered power; T: Fresnel transmittances at the projector and camera angles)
    with R averaged over q's cell for the (2 NEAR_CELLS + 1)^2 nearest cells (points spread along
    the surface's image-space derivatives) and sampled at the cell centre beyond; the entry pixel
    gets R integrated over the disc of its own area, r0 = sqrt(a_p / pi), and the sub-samples of
    the neighbours that fall inside that disc are dropped (counted once). Entry-point material, as
    for Burley; scattering coefficients from the material's albedo and mean free path
    (:func:`sssphase_core.sim.dipole.coefficients`). Cost: ~15x the Burley transport's (a soap
    view on the CPU preset: 8.3 s against 0.5 s for the first render; later renders reuse the
    cached footprints). Checked against a fine polar quadrature on a slab: within 0.5 %.
    """

    name = "directional_dipole"

    def __init__(self, maps: SurfaceMaps, patch: int, directional: DirectionalMaps):
        super().__init__(maps, patch)
        self.directional = d = directional
        self.boundary = dipole.Boundary.of(d.eta)
        half, k = self.half, patch
        pad = ((half, k - half), (half, k - half))
        on = maps.mask[..., None]
        self.sigma_s, self.sigma_a = dipole.coefficients(np.where(on, np.nan_to_num(maps.albedo), 0.5),
                                                         np.where(on, np.nan_to_num(d.mfp), 1.0), d.eta)
        t_out = np.where(maps.mask, self.boundary.transmittance(np.nan_to_num(d.cos_view)) / (4 * self.boundary.c_phi_out), 0.0)
        self.t_in = np.where(maps.mask, self.boundary.transmittance(np.nan_to_num(d.cos_in)), 0.0)
        normals = np.where(maps.mask[..., None], np.nan_to_num(d.normals), 0.0).astype(np.float32)
        self._normal_windows = [sliding_window_view(np.pad(c, pad), (k, k)) for c in np.moveaxis(normals, -1, 0)]
        self._t_out_window = sliding_window_view(np.pad(t_out.astype(np.float32), pad), (k, k))
        gy, gx = _surface_derivatives(maps.points, maps.mask)
        self._gx, self._gy = gx, gy

    def chunk_size(self) -> int:
        return max(1, CHUNK_ENTRIES // (4 * self.k * self.k))

    def _compute(self, index: np.ndarray) -> np.ndarray:
        m, half, bd = self.maps, self.half, self.boundary
        y, x = np.divmod(index, self.w)
        xp = m.points[y, x].astype(np.float64)  # (N, 3)
        n_i = np.nan_to_num(self.directional.normals[y, x]).astype(np.float64)
        w12 = dipole.refract_in(self.directional.light_dir[y, x].astype(np.float64), n_i, self.directional.eta)
        e, ap = m.irradiance[y, x].astype(np.float64), m.area[y, x].astype(np.float64)
        power = e * ap * self.t_in[y, x]  # power entering the cell (N,)
        r0 = np.sqrt(ap / np.pi)
        offsets = np.stack([win[y, x] for win in self._windows], -1).astype(np.float64) - xp[:, None, None]  # (N, K, K, 3)
        n_o = np.stack([win[y, x] for win in self._normal_windows], -1).astype(np.float64)
        t_out = self._t_out_window[y, x].astype(np.float64)  # (N, K, K), 0 off the surface

        # near cells: sub-samples spread along the exit cell's image-space derivatives
        near = np.arange(-NEAR_CELLS, NEAR_CELLS + 1)
        cy, cx = np.meshgrid(near, near, indexing="ij")
        keep = (cy != 0) | (cx != 0)
        cy, cx = cy[keep], cx[keep]  # (C,)
        qy, qx = np.clip(y[:, None] + cy, 0, self.h - 1), np.clip(x[:, None] + cx, 0, self.w - 1)  # (N, C)
        sub = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5
        su, sv = np.meshgrid(sub, sub, indexing="ij")
        su, sv = su.ravel(), sv.ravel()  # (S,)
        near_off = offsets[:, half + cy, half + cx]  # (N, C, 3)
        spread = (sv[None, None, :, None] * self._gy[qy, qx][:, :, None] + su[None, None, :, None] * self._gx[qy, qx][:, :, None])
        near_off = near_off[:, :, None] + spread  # (N, C, S, 3)
        outside = np.sqrt(np.sum(near_off**2, axis=-1)) >= r0[:, None, None]
        near_n = n_o[:, half + cy, half + cx][:, :, None]

        # the entry pixel's own disc, in its tangent plane
        t1 = np.cross(n_i, np.where(np.abs(n_i[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(n_i, t1)
        g, gw = np.polynomial.legendre.leggauss(DISC_NODES)
        u = (g + 1) / 2  # r = r0 u^2 resolves the profile's peak at the entry point
        phi = 2 * np.pi * (np.arange(DISC_NODES) + 0.5) / DISC_NODES
        rad = r0[:, None] * u[None] ** 2  # (N, R)
        disc_off = rad[:, :, None, None] * (np.cos(phi)[None, None, :, None] * t1[:, None, None] + np.sin(phi)[None, None, :, None] * t2[:, None, None])
        weight = rad * (r0[:, None] * 2 * u[None] * gw[None] / 2) * (2 * np.pi / DISC_NODES)  # r dr dphi, (N, R)

        sp, sa = self.sigma_s[y, x], self.sigma_a[y, x]  # (N, 3)
        w, ni, sp4, sa4 = w12[:, None, None], n_i[:, None, None], sp[:, None, None], sa[:, None, None]
        f32 = np.float32  # the K x K field in single precision (twice as fast; the near field stays double)
        far = dipole.exitance(offsets.astype(f32), w.astype(f32), ni.astype(f32), n_o.astype(f32), sp4.astype(f32), sa4.astype(f32), bd)
        close = dipole.exitance(near_off, w, ni, near_n, sp4, sa4, bd)  # (N, C, S, 3)
        far[:, half + cy, half + cx] = np.mean(np.where(outside[..., None], close, 0.0), axis=2)  # (N, K, K, 3)
        disc = dipole.exitance(disc_off, w, ni, ni, sp4, sa4, bd)  # (N, R, A, 3)
        own = np.einsum("nrac,nr->nc", disc, weight)  # share of the entered power leaving through the disc
        img = far * (power[:, None, None] * t_out)[..., None]
        img[:, half, half] = own * (e * self.t_in[y, x] * t_out[:, half, half])[:, None]
        out = np.ascontiguousarray(np.moveaxis(img, -1, 0), dtype=np.float32)
        out[:, :, half, half] += (e * m.rho_s[y, x])[None]
        return out


def _surface_derivatives(points: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dX/dy, dX/dx (H, W, 3) of the surface points per image pixel: central differences, one-sided
    at silhouettes, 0 where neither neighbour is on the surface (that cell is then point-sampled)."""
    pts = np.where(mask[..., None], np.nan_to_num(points), 0.0).astype(np.float64)
    out = []
    for axis in (0, 1):
        fwd, bwd = np.roll(pts, -1, axis), np.roll(pts, 1, axis)
        m_f, m_b = np.roll(mask, -1, axis), np.roll(mask, 1, axis)
        edge = [slice(None)] * 2
        edge[axis] = -1
        m_f[tuple(edge)] = False
        edge[axis] = 0
        m_b[tuple(edge)] = False
        both = (fwd - bwd) / 2
        grad = np.where((m_f & m_b)[..., None], both, np.where(m_f[..., None], fwd - pts, np.where(m_b[..., None], pts - bwd, 0.0)))
        out.append(np.where(mask[..., None], grad, 0.0))
    return out[0], out[1]


def radiative_media(maps: SurfaceMaps, mfp: np.ndarray, anisotropy: float) -> tuple[ProfileTable, np.ndarray, np.ndarray]:
    """``(profiles, inv_path, row)``: the radiative transport's :class:`~sssphase_core.sim.radiative.ProfileTable` at
    mean cosine ``anisotropy``, and per pixel and colour (H, W, 3) 1 / l' (mm^-1) and the table's fractional row, from
    the maps' albedo and the diffuse mean free path ``mfp`` (H, W, 3) mm (NaN off the surface)."""
    profiles = ProfileTable.at(anisotropy)
    on = maps.mask[..., None]
    reduced_s, sigma_a = dipole.coefficients(np.where(on, np.nan_to_num(maps.albedo), 0.5),
                                             np.where(on, np.nan_to_num(mfp), 1.0), dipole.ETA)
    reduced_t = reduced_s + sigma_a
    return profiles, reduced_t.astype(np.float32), profiles.index(reduced_s / reduced_t)


class RadiativeTransport(Transport):
    """Footprints from radiative transfer (:mod:`sssphase_core.sim.radiative`): the exit profile of a random walk
    in a semi-infinite medium of the entry pixel's material, with a Henyey-Greenstein phase function of mean
    cosine ``g`` (the rig's ``anisotropy``) behind a boundary of index 1.3, instead of a diffusion model's. The
    material's albedo A and diffuse mean free path l_d give its reduced coefficients as for the directional dipole
    (:func:`sssphase_core.sim.dipole.coefficients`: exact for the Jensen 2001 materials); the footprint carries
    the energy A, spread as the walk spreads it (its tabulated CDF, normalised), over the same rings as the Burley
    transport's (the CDF's difference across each ring, the pixel's own disc its CDF at r0). Radially symmetric,
    like Burley's; the splatting, caching and ``rho_s`` term are the Burley transport's."""

    name = "radiative"

    def __init__(self, maps: SurfaceMaps, patch: int, mfp: np.ndarray, anisotropy: float = 0.0):
        super().__init__(maps, patch)
        self.profiles, self.inv_path, self.row = radiative_media(maps, mfp, anisotropy)

    def _compute(self, index: np.ndarray) -> np.ndarray:
        m, k, half = self.maps, self.k, self.half
        (y, x), r = self._distances(index)
        e = m.irradiance[y, x].astype(np.float32)
        ap = m.area[y, x].astype(np.float32)
        hh = (np.sqrt(ap) / 2)[:, None, None]  # half ring width
        r0 = np.sqrt(ap / np.pi)[:, None, None]
        lo_r, hi_r = np.maximum(r - hh, r0), np.maximum(r + hh, r0)
        energy = e[:, None] * m.albedo[y, x].astype(np.float32)  # (N, 3)
        out = np.empty((3, len(index), k, k), np.float32)
        for c in range(3):
            inv, rows = self.inv_path[y, x, c][:, None, None], self.profiles.rows(self.row[y, x, c])
            ring = self.profiles.lookup(rows, hi_r * inv)
            ring -= self.profiles.lookup(rows, lo_r * inv)
            out[c] = ring * (energy[:, c, None, None] * 2 * hh / (2 * np.pi * r))
            out[c, :, half, half] = self.profiles.lookup(rows, r0[:, 0, 0] * inv[:, 0, 0]) * energy[:, c]
        out[:, :, half, half] += (e * m.rho_s[y, x])[None]
        return out
