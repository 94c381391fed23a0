"""The simulator's light transport on a torch device (a GPU): the same footprints and splatting as
:class:`sssphase_core.sim.transport.Transport`, for rendering 1080p captures in seconds.

The Burley transport's two costs are per-pixel footprints (K x K x 3 exponentials for every lit pixel:
5 G values for a 1080p view at K = 90) and their splatting under each pattern. Here both run on the
device: footprints of the lit pixels are computed chunk by chunk with the CPU path's formulas (the same
float32 field, the same float64 per-pixel constants and clamped near rings) for every batch of patterns
(not kept: a 1080p view's take 19 GB, and recomputing them costs less than a frame's sensor on the CPU),
each chunk splatted with one ``index_put_(accumulate=True)`` into a (H + K) x (W + K) x 3P canvas.

``sssphase_core.sim`` itself never imports torch (a daemon serving the CPU sim stays free of it): the sim
device plugin hands :func:`transport_factory` to :class:`~sssphase_core.sim.scene.SimScene` when its rig
option ``device`` names one. The directional dipole stays on the CPU (its near-field quadrature is not
ported): a scene with that transport renders as before whatever the device.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from sssphase_core.compute import compute_device
from sssphase_core.sim.transport import FAR, NEAR, RATE_CAP, SurfaceMaps, Transport

#: Footprint entries per chunk on the device (its temporaries: ~16 bytes each).
DEVICE_CHUNK_ENTRIES = 32_000_000
#: Splat products (entries x patterns x 3) per ``index_put_`` call.
SPLAT_ENTRIES = 256_000_000


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
        self.cache_bytes = 0  # nothing kept: several sim daemons may share one GPU

    def chunk_size(self) -> int:
        return max(1, DEVICE_CHUNK_ENTRIES // (self.k * self.k))

    def cache(self) -> bool:
        return False

    def weights(self, index: np.ndarray) -> np.ndarray:
        return self._compute(index)

    def _compute(self, index: np.ndarray) -> np.ndarray:
        return self._device_compute(index).reshape(3, len(index), self.k, self.k).cpu().numpy()

    def _device_compute(self, index: np.ndarray) -> torch.Tensor:
        """The CPU path's ``Transport._compute`` on the device -> (3, N, K*K) float32."""
        m, k, half, dev = self.maps, self.k, self.half, self.device
        n = len(index)
        y, x = np.divmod(index, self.w)
        idx = torch.as_tensor(index, device=dev)
        corner = torch.as_tensor(y * self.wpad + x, device=dev)
        window = self._padded[corner[:, None] + self._toffsets[None, :]]  # (N, K*K, 3)
        r = torch.linalg.vector_norm(window - self._points[idx][:, None, :], dim=-1)
        centre = half * k + half
        r[:, centre] = 1.0  # the pixel itself gets the disc term below
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
        """sum_p F_p(q - p) * light_p for sources (N,) flat index and light (N, P, 3) -> (P, H, W, 3)."""
        n_pat, kk, dev = light.shape[1], self.k * self.k, self.device
        canvas = torch.zeros((self.hpad * self.wpad, n_pat * 3), dtype=torch.float32, device=dev)
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
        img = canvas.reshape(self.hpad, self.wpad, n_pat, 3)[self.half : self.half + self.h, self.half : self.half + self.w]
        return img.permute(2, 0, 1, 3).contiguous().cpu().numpy()


def transport_factory(device: str | torch.device) -> Callable[[SurfaceMaps, int], Transport]:
    """What :class:`~sssphase_core.sim.scene.SimScene` builds its Burley transport with on ``device``."""
    dev = compute_device(device)

    def make(maps: SurfaceMaps, patch: int) -> Transport:
        return TorchTransport(maps, patch, dev)

    return make
