"""The simulator's light transport and camera sensor on a torch device (a GPU): the same footprints and
splatting as :class:`sssphase_core.sim.transport.Transport`, for rendering 1080p captures in seconds.

The Burley transport's two costs are per-pixel footprints (K x K x 3 exponentials for every lit pixel:
5 G values for a 1080p view at K = 90) and their splatting under each pattern. Here both run on the
device: footprints of the lit pixels are computed chunk by chunk with the CPU path's formulas (the same
float32 field, the same float64 per-pixel constants and clamped near rings) for every batch of patterns
(not kept: a 1080p view's take 19 GB; recomputing them took 0.28 s per fringe frame on an H200, all counted),
each chunk splatted with one ``index_put_(accumulate=True)`` into a (H + K) x (W + K) x 3P canvas.

The sensor (:class:`DeviceSensor`: photon and read noise, the ISP's median and Malvar demosaicing) runs there
too for the presets' cameras: 0.43 s per 1080p frame on the CPU was the cost of every dot frame.

``sssphase_core.sim`` itself never imports torch (a daemon serving the CPU sim stays free of it): the sim
device plugin hands :func:`transport_factory` to :class:`~sssphase_core.sim.scene.SimScene` when its rig
option ``device`` names one; the radiative transport's table lookup runs there too
(:class:`TorchRadiativeTransport`). The directional dipole stays on the CPU (its near-field quadrature is not
ported): a scene with that transport renders as before whatever the device.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from sssphase_core.compute import compute_device
from sssphase_core.processing.isp import MALVAR_KERNELS
from sssphase_core.sim.radiative import LOOKUP_EPS, LOOKUP_POINTS, LOOKUP_START, LOOKUP_STEP
from sssphase_core.sim.sensor import SensorConfig
from sssphase_core.sim.transport import FAR, NEAR, RATE_CAP, SurfaceMaps, Transport, radiative_media

#: Footprint entries per chunk on the device (its temporaries: ~16 bytes each).
DEVICE_CHUNK_ENTRIES = 32_000_000
#: Splat products (entries x patterns x 3) per ``index_put_`` call.
SPLAT_ENTRIES = 256_000_000
#: A source's footprint costs about this many times its splat under one pattern (the CPU: 2). A batch whose sources
#: are lit by m of its P patterns on average is splatted pattern by pattern (each source recomputed m times, each
#: splatted under its own) when ``m (R + 1) < R + P``: a batch of dot grids, each source lit by one of them.
COMPUTE_OVER_SPLAT = 2.0


def _burley_cdf(r: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Fraction of the normalized-diffusion energy within radius r (``sim.materials.burley_cdf``)."""
    u = torch.exp(-s * r / 3)
    return 1 - u**3 / 4 - 3 * u / 4


class TorchTransport(Transport):
    """:class:`Transport` (Burley) with footprints and splatting on ``device`` (results as numpy arrays)."""

    def __init__(self, maps: SurfaceMaps, patch: int, device: str | torch.device = "cuda"):
        super().__init__(maps, patch)
        self.device = compute_device(device)
        self._windows = []  # the CPU path's sliding windows are not used here
        dev, half, k = self.device, self.half, patch
        pts = np.where(maps.mask[..., None], np.nan_to_num(maps.points), FAR).astype(np.float32)
        pad = ((half, k - half), (half, k - half), (0, 0))
        self._padded = torch.as_tensor(np.pad(pts, pad, constant_values=FAR).reshape(-1, 3), device=dev)
        self._points = torch.as_tensor(np.nan_to_num(maps.points).reshape(-1, 3).astype(np.float32), device=dev)
        self._toffsets = torch.as_tensor(self._offsets.astype(np.int64), device=dev)
        self.cache_bytes = 0  # nothing kept (Transport.cache): several sim daemons may share one GPU

    def chunk_size(self) -> int:
        return max(1, DEVICE_CHUNK_ENTRIES // (self.k * self.k))

    def _compute(self, index: np.ndarray) -> np.ndarray:
        return self._device_compute(index).reshape(3, len(index), self.k, self.k).cpu().numpy()

    def _distances(self, index: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, int]:
        """``(idx (N,), r (N, K*K), centre)``: the pixels' flat indices on the device, the 3D distance from each to
        every cell of its window (the pixel itself set to 1: it gets the disc term), and the window's centre cell."""
        y, x = np.divmod(index, self.w)
        idx = torch.as_tensor(index, device=self.device)
        corner = torch.as_tensor(y * self.wpad + x, device=self.device)
        window = self._padded[corner[:, None] + self._toffsets[None, :]]  # (N, K*K, 3)
        r = torch.linalg.vector_norm(window - self._points[idx][:, None, :], dim=-1)
        centre = self.half * self.k + self.half
        r[:, centre] = 1.0
        return idx, r, centre

    def _device_compute(self, index: np.ndarray) -> torch.Tensor:
        """The CPU path's ``Transport._compute`` on the device -> (3, N, K*K) float32."""
        m, k, half, dev = self.maps, self.k, self.half, self.device
        n = len(index)
        _, r, centre = self._distances(index)
        inv_r = 1.0 / r

        f64 = torch.float64
        e = torch.as_tensor(m.irradiance.reshape(-1)[index], device=dev).to(f64)
        ap = torch.as_tensor(m.area.reshape(-1)[index], device=dev).to(f64)
        albedo = torch.as_tensor(m.albedo.reshape(-1, 3)[index], device=dev).to(f64)
        rho = torch.as_tensor(m.rho_s.reshape(-1)[index], device=dev).to(f64)
        hh = torch.sqrt(ap) / 2
        rate = torch.minimum(torch.as_tensor(m.rate.reshape(-1, 3)[index], device=dev).to(f64), RATE_CAP / (2 * hh[:, None]))
        scale = (e * 2 * hh / (2 * np.pi))[:, None] * albedo
        s3 = rate / 3
        a_, b_ = torch.exp(s3 * hh[:, None]), torch.exp(-s3 * hh[:, None])
        alpha = (0.75 * (a_ - b_) * scale).to(torch.float32)
        beta = ((a_ - b_) * (a_**2 + 1 + b_**2) / 4 * scale).to(torch.float32)
        r0 = torch.sqrt(ap / np.pi)
        # rings reaching into the pixel's own disc (within NEAR pixels): clamped at r0 in float64
        near = torch.zeros((k, k), dtype=torch.bool, device=dev)
        near[max(half - NEAR, 0) : half + NEAR + 1, max(half - NEAR, 0) : half + NEAR + 1] = True
        close = near.reshape(1, -1) & (r < (r0 + hh).to(torch.float32)[:, None])
        n_close, j_close = torch.nonzero(close, as_tuple=True)
        out = torch.empty((3, n, k * k), dtype=torch.float32, device=dev)
        for c in range(3):
            t = torch.exp(r * -s3[:, c].to(torch.float32)[:, None])
            field = t * t
            field *= beta[:, c, None]
            field += alpha[:, c, None]
            field *= t
            field *= inv_r
            if n_close.numel():
                rc = r[n_close, j_close].to(f64)
                sc = 3 * s3[n_close, c]
                ring = (_burley_cdf(torch.maximum(rc + hh[n_close], r0[n_close]), sc)
                        - _burley_cdf(torch.maximum(rc - hh[n_close], r0[n_close]), sc))
                field[n_close, j_close] = (ring * scale[n_close, c] / rc).to(torch.float32)
            field[:, centre] = (_burley_cdf(r0, rate[:, c]) * e * albedo[:, c]).to(torch.float32)
            out[c] = field
        out[:, :, centre] += (e * rho).to(torch.float32)[None]
        return out

    def splat(
        self,
        sources: np.ndarray,
        light: np.ndarray,
        progress: Callable[[int, int], None] | None = None,
    ) -> np.ndarray:
        """sum_p F_p(q - p) * light_p for sources (N,) flat index and light (N, P, 3) -> (P, H, W, 3). Where each
        source is lit by few of the patterns (dot grids: one of a batch's), each pattern splats only its own."""
        n_pat, dev = light.shape[1], self.device
        lit = (light > 0).any(axis=2)  # (N, P)
        per_source = float(lit.sum(axis=1).mean()) if len(lit) else 0.0
        if per_source * (COMPUTE_OVER_SPLAT + 1) < COMPUTE_OVER_SPLAT + n_pat:
            planes = torch.zeros((n_pat, self.hpad * self.wpad, 3), dtype=torch.float32, device=dev)
            done, total = 0, int(lit.sum())
            for p in range(n_pat):
                mine = np.flatnonzero(lit[:, p])
                self._splat_into(planes[p], sources[mine], light[mine, p : p + 1],
                                 None if progress is None else lambda n, _t, d=done: progress(d + n, total))
                done += len(mine)
            img = planes.reshape(n_pat, self.hpad, self.wpad, 3)[:, self.half : self.half + self.h,
                                                                   self.half : self.half + self.w]
            return img.contiguous().cpu().numpy()
        canvas = torch.zeros((self.hpad * self.wpad, n_pat * 3), dtype=torch.float32, device=dev)
        self._splat_into(canvas, sources, light, progress)
        img = canvas.reshape(self.hpad, self.wpad, n_pat, 3)[self.half : self.half + self.h, self.half : self.half + self.w]
        return img.permute(2, 0, 1, 3).contiguous().cpu().numpy()


    def _splat_into(self, canvas: torch.Tensor, sources: np.ndarray, light: np.ndarray,
                    progress: Callable[[int, int], None] | None) -> None:
        """Accumulate sources (N,) under light (N, P, 3) into ``canvas`` (padded H * W, P * 3), in chunks."""
        n_pat, kk, dev = light.shape[1], self.k * self.k, self.device
        step = max(1, min(self.chunk_size(), SPLAT_ENTRIES // (kk * n_pat * 3)))
        for start in range(0, len(sources), step):
            src = sources[start : start + step]
            w = self._device_compute(src)  # (3, n, K*K)
            y, x = np.divmod(src, self.w)
            corner = torch.as_tensor(y * self.wpad + x, device=dev)
            rows = (corner[:, None] + self._toffsets[None, :]).reshape(-1)
            lt = torch.as_tensor(np.ascontiguousarray(light[start : start + step]), dtype=torch.float32, device=dev)
            vals = w.permute(1, 2, 0)[:, :, None, :] * lt[:, None, :, :]  # (n, K*K, P, 3)
            canvas.index_put_((rows,), vals.reshape(-1, n_pat * 3), accumulate=True)
            if progress is not None:
                progress(min(start + step, len(sources)), len(sources))


class TorchRadiativeTransport(TorchTransport):
    """:class:`~sssphase_core.sim.transport.RadiativeTransport` on ``device``: the same media, table and rings (its
    lookup linear in log radius between the blended rows), the splatting :class:`TorchTransport`'s."""

    name = "radiative"

    def __init__(self, maps: SurfaceMaps, patch: int, mfp: np.ndarray, anisotropy: float = 0.0,
                 device: str | torch.device = "cuda"):
        super().__init__(maps, patch, device)
        self.profiles, inv_path, row = radiative_media(maps, mfp, anisotropy)
        dev = self.device
        self._table = torch.as_tensor(self.profiles.table, device=dev)  # (A, LOOKUP_POINTS)
        self._inv_path = torch.as_tensor(inv_path.reshape(-1, 3), device=dev)
        self._row = torch.as_tensor(row.reshape(-1, 3), device=dev)

    def _rows(self, index: torch.Tensor) -> torch.Tensor:
        j0 = torch.clamp(index.to(torch.int64), max=len(self._table) - 2)
        u = (index - j0)[:, None]
        lo = self._table[j0]
        return lo + u * (self._table[j0 + 1] - lo)

    @staticmethod
    def _lookup(rows: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        q = torch.clamp((torch.log(r + LOOKUP_EPS) - LOOKUP_START) * (1 / LOOKUP_STEP), 0, LOOKUP_POINTS - 1.001)
        i0 = q.to(torch.int64)
        frac = q - i0
        lo = torch.gather(rows, 1, i0)
        return lo + frac * (torch.gather(rows, 1, i0 + 1) - lo)

    def _device_compute(self, index: np.ndarray) -> torch.Tensor:
        """The CPU path's ``RadiativeTransport._compute`` on the device -> (3, N, K*K) float32."""
        m, k, dev = self.maps, self.k, self.device
        idx, r, centre = self._distances(index)
        e = torch.as_tensor(m.irradiance.reshape(-1)[index].astype(np.float32), device=dev)
        ap = torch.as_tensor(m.area.reshape(-1)[index].astype(np.float32), device=dev)
        hh, r0 = (torch.sqrt(ap) / 2)[:, None], torch.sqrt(ap / np.pi)[:, None]
        lo_r, hi_r = torch.maximum(r - hh, r0), torch.maximum(r + hh, r0)
        energy = e[:, None] * torch.as_tensor(m.albedo.reshape(-1, 3)[index].astype(np.float32), device=dev)
        out = torch.empty((3, len(index), k * k), dtype=torch.float32, device=dev)
        for c in range(3):
            inv, rows = self._inv_path[idx, c][:, None], self._rows(self._row[idx, c])
            ring = self._lookup(rows, hi_r * inv) - self._lookup(rows, lo_r * inv)
            out[c] = ring * (energy[:, c, None] * 2 * hh / (2 * np.pi * r))
            out[c, :, centre] = self._lookup(rows, r0 * inv)[:, 0] * energy[:, c]
        rho = torch.as_tensor(m.rho_s.reshape(-1)[index].astype(np.float32), device=dev)
        out[:, :, centre] += (e * rho)[None]
        return out


def transport_factory(device: str | torch.device) -> Callable[[SurfaceMaps, int], Transport]:
    """What :class:`~sssphase_core.sim.scene.SimScene` builds its Burley transport with on ``device``; its
    ``radiative`` attribute builds the radiative one there (``(maps, patch, mfp, anisotropy)``)."""
    dev = compute_device(device)

    def make(maps: SurfaceMaps, patch: int) -> Transport:
        return TorchTransport(maps, patch, dev)

    def make_radiative(maps: SurfaceMaps, patch: int, mfp: np.ndarray, anisotropy: float = 0.0) -> Transport:
        return TorchRadiativeTransport(maps, patch, mfp, anisotropy, dev)

    make.radiative = make_radiative  # type: ignore[attr-defined]
    return make


# --- the camera's sensor on the device ------------------------------------------------------------------

def _symmetric_pad(x: torch.Tensor, n: int) -> torch.Tensor:
    """(P, H, W) padded by ``n`` mirrored samples that repeat the edge (scipy.ndimage's ``reflect``: d c b a | a b c d)."""
    x = torch.cat([x[:, :n].flip(1), x, x[:, -n:].flip(1)], dim=1)
    return torch.cat([x[:, :, :n].flip(2), x, x[:, :, -n:].flip(2)], dim=2)


def malvar_rggb(mosaic: torch.Tensor) -> torch.Tensor:
    """RGGB mosaics (P, H, W) -> RGB (P, H, W, 3), Malvar-He-Cutler 2004 with mirrored borders: what
    ``processing.isp.demosaic(method="malvar")`` gives, on the device."""
    kernels = torch.tensor([MALVAR_KERNELS[k] for k in ("green", "row", "col", "cross")],
                           dtype=mosaic.dtype, device=mosaic.device)[:, None] / 8
    filtered = torch.nn.functional.conv2d(_symmetric_pad(mosaic, 2)[:, None], kernels)  # (P, 4, H, W); kernels symmetric
    g_rb, c_g_row, c_g_col, c_opposite = filtered.unbind(1)
    h, w = mosaic.shape[-2:]
    even_y = (torch.arange(h, device=mosaic.device) % 2 == 0)[:, None]
    even_x = (torch.arange(w, device=mosaic.device) % 2 == 0)[None, :]
    r_site, b_site = even_y & even_x, ~even_y & ~even_x
    g_in_r_row, g_in_b_row = even_y & ~even_x, ~even_y & even_x
    green = torch.where(r_site | b_site, g_rb, mosaic)
    red = torch.where(r_site, mosaic, torch.where(g_in_r_row, c_g_row, torch.where(g_in_b_row, c_g_col, c_opposite)))
    blue = torch.where(b_site, mosaic, torch.where(g_in_b_row, c_g_row, torch.where(g_in_r_row, c_g_col, c_opposite)))
    return torch.stack([red, green, blue], dim=-1)


def median3_rggb(mosaic: torch.Tensor) -> torch.Tensor:
    """(P, H, W) -> the 3 x 3 median of each of the four RGGB planes, borders repeated (OpenCV's ``medianBlur``,
    ``processing.isp.median3_bayer``)."""
    out = torch.empty_like(mosaic)
    for dy in (0, 1):
        for dx in (0, 1):
            plane = mosaic[:, dy::2, dx::2]
            padded = torch.nn.functional.pad(plane[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
            windows = padded.unfold(1, 3, 1).unfold(2, 3, 1)  # (P, h, w, 3, 3)
            out[:, dy::2, dx::2] = windows.reshape(*plane.shape, 9).median(dim=-1).values
    return out


class DeviceSensor:
    """The sim camera's sensor (:func:`sssphase_core.sim.sensor.expose` and ``develop``) on a torch device for a
    Bayer camera demosaicing with Malvar and a perfect lens (the presets'): photon and read noise drawn there
    (a torch generator seeded from the frame's numpy generator: the same frame re-captured is the same, but not
    the numpy path's draw), rounding and clipping as the numpy path, the ISP's median and demosaicing equal to
    it within float tolerance. Other cameras (three-chip, OpenCV demosaicing, lens blur) are sensed by the
    numpy path."""

    def __init__(self, device: str | torch.device):
        self.device = compute_device(device)

    @staticmethod
    def handles(config: SensorConfig) -> bool:
        return (not config.three_chip) and config.demosaic == "malvar" \
            and config.lens_blur <= 0

    def expose(self, linear: np.ndarray, config: SensorConfig, rng: np.random.Generator, exposure: float = 1.0) -> torch.Tensor:
        """(P, H, W, 3) linear images -> (P, H, W) raw RGGB DN (float32 holding integers) on the device."""
        gen = torch.Generator(device=self.device).manual_seed(int(rng.integers(2**62)))
        img = torch.as_tensor(np.ascontiguousarray(linear, np.float32), device=self.device)
        h, w = img.shape[1:3]
        channel = torch.ones((h, w), dtype=torch.long, device=self.device)
        channel[0::2, 0::2], channel[1::2, 1::2] = 0, 2
        mosaic = torch.gather(img, 3, channel[None, :, :, None].expand(img.shape[0], h, w, 1))[..., 0]
        mean_e = mosaic.clamp(min=0) * float(config.electrons_per_unit * exposure)
        electrons = torch.poisson(mean_e, generator=gen)
        electrons += torch.randn(mean_e.shape, generator=gen, device=self.device) * float(config.read_noise)
        electrons = electrons.clamp(max=float(config.full_well))
        dn = torch.round(float(config.black_level) + electrons * float(config.dn_per_electron))
        return dn.clamp(0, float(config.max_dn))

    def develop(self, raw: torch.Tensor, config: SensorConfig, dn_per_unit: float) -> torch.Tensor:
        """(P, H, W) raw DN -> (P, H, W, 3) linear RGB on the device (median, Malvar, black level and scale)."""
        mosaic = median3_rggb(raw) if config.isp_median else raw
        rgb = malvar_rggb(mosaic.to(torch.float64))
        return ((rgb - float(config.black_level)) / float(dn_per_unit)).to(torch.float32)

    def sense(self, images: np.ndarray, config: SensorConfig, rng: np.random.Generator, exposure: float = 1.0,
              raw: bool = False) -> np.ndarray:
        """``SimScene.sense`` on the device: raw uint16 Bayer frames, or developed RGB float32 (P, H, W, 3)."""
        frames = self.expose(images, config, rng, exposure)
        if raw:
            return frames.to(torch.int32).cpu().numpy().astype(np.uint16)
        return self.develop(frames, config, config.dn_per_unit(exposure)).cpu().numpy()
