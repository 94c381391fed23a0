"""Relighting by footprint splatting: I(q) = sum_p PSF_p(q - p) * c(p), with c(p) = L(pi(p)).

The footprint of every lit surface pixel is produced once per chunk (by a network, an analytic model,
measured captures or the simulator) and splatted for all requested patterns at once, so several
patterns share the footprint cost and footprints are never all held in memory.

Only pixels that are valid *and* receive light from at least one pattern are evaluated. The
projector's black level lights every pixel weakly; its contribution is ``black * white`` (the
captured white image is the sum of all footprints at unit light), so it costs nothing per pixel.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

from sssphase_core.colour import display_scale, srgb  # noqa: F401  (part of this module's API)
from sssphase_core.errors import InputError
from sssphase_core.isp import SATURATION_MARGIN
from sssphase_core.projector import emitted_light, sample_projector

#: Produces the (N, K, K, 3) footprints of camera pixels given as (N, 2) int (y, x).
FootprintSource = Callable[[np.ndarray], "np.ndarray | torch.Tensor"]


@dataclass(frozen=True)
class Projection:
    """Where each camera pixel lands in the projector, and how the projector turns values into light."""

    xp: np.ndarray  # (H, W) float32 projector x, NaN where invalid
    yp: np.ndarray  # (H, W) float32 projector y, NaN where invalid
    mask: np.ndarray  # (H, W) bool valid surface pixels
    projector_size: tuple[int, int]  # (Wp, Hp)
    gamma: float = 2.2
    black: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape


def lit_pixels(proj: Projection, light: np.ndarray, threshold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels that receive light above ``threshold`` in some pattern: (pixels (N,2), c (N,P,3))."""
    ys, xs = np.nonzero(proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp))
    c = sample_projector(light, proj.xp[ys, xs], proj.yp[ys, xs])
    keep = (c > threshold).any(axis=(1, 2))
    return np.stack([ys[keep], xs[keep]], axis=1), c[keep]


#: ``fold`` splat: bytes of the dense column tensor per band of image rows (one row at least).
FOLD_BAND_BYTES = 256 * 2**20


class Splatter:
    """Accumulates scaled K x K footprints into P canvases (padded so no bounds checks are needed).

    ``method``: ``csc`` (CPU): one sparse (canvas x sources) matrix per colour channel times the
    (sources x P) light, with scipy's compiled CSC kernel (measured ~9x faster than
    ``torch.index_add_`` and ~30x faster than torch's sparse matmul on the CPU preset, see ``sss bench
    relight``). ``index`` (other devices): torch ``index_put_(accumulate=True)``, whose CUDA kernel
    sorts indices and is deterministic. ``fold``: ``torch.nn.functional.fold`` (col2im, no atomics)
    over bands of image rows, the lit pixels' windows scattered into a dense (3P, K^2, rows x W)
    column tensor (unlit pixels of the band are zero columns, so the cost follows the band's area, and
    its memory is ``3 P K^2 W`` floats per row). ``auto``: csc on the CPU, index elsewhere.
    """

    def __init__(self, height: int, width: int, patch: int, n_patterns: int, device: str = "cpu", method: str = "auto"):
        if method not in ("auto", "csc", "index", "fold"):
            raise InputError(f"unknown splat method {method!r} (auto, csc, index or fold)")
        self.method = method
        self.h, self.w, self.k, self.p = height, width, patch, n_patterns
        self.hp, self.wp = height + patch, width + patch
        self.device = torch.device(device)
        dy, dx = np.meshgrid(np.arange(patch), np.arange(patch), indexing="ij")
        self._offsets = (dy * self.wp + dx).ravel()
        if method == "csc" or (method == "auto" and self.device.type == "cpu"):
            self.device = torch.device("cpu")
            self.canvas: np.ndarray | torch.Tensor = np.zeros((3, self.hp * self.wp, n_patterns), np.float32)
        elif method == "fold":
            self.canvas = torch.zeros(n_patterns * 3, self.hp, self.wp, dtype=torch.float32, device=self.device)
        else:
            self.canvas = torch.zeros(self.hp * self.wp, n_patterns * 3, dtype=torch.float32, device=self.device)
            self._toffsets = torch.as_tensor(self._offsets, device=self.device)

    def add(self, pixels: np.ndarray, footprints: torch.Tensor, c: torch.Tensor) -> None:
        """Splat footprints (n, K, K, 3) scaled by light c (n, P, 3) centred on pixels (n, 2)."""
        n, kk = footprints.shape[0], self.k * self.k
        if n == 0:
            return
        # Window top-left in padded coordinates: (y - K//2) + K//2 = y, likewise for x.
        corner = pixels[:, 0].astype(np.int64) * self.wp + pixels[:, 1]
        if isinstance(self.canvas, np.ndarray):
            fp = footprints.to(torch.float32).reshape(n, kk, 3).cpu().numpy()
            light = c.to(torch.float32).cpu().numpy()
            lo, hi = int(corner.min()), int(corner.max() + self._offsets[-1]) + 1
            rows = ((corner - lo)[:, None] + self._offsets[None, :]).astype(np.int32).ravel()
            indptr = np.arange(0, n * kk + 1, kk, dtype=np.int64 if n * kk >= 2**31 else np.int32)
            for ch in range(3):
                m = scipy.sparse.csc_array((np.ascontiguousarray(fp[:, :, ch]).ravel(), rows, indptr), shape=(hi - lo, n))
                self.canvas[ch, lo:hi] += m @ light[:, :, ch]
            return
        footprints, c = footprints.to(self.device), c.to(self.device)
        if self.method == "fold":
            self._fold(pixels, footprints, c)
            return
        base = torch.as_tensor(corner, device=self.device)
        index = (base[:, None] + self._toffsets[None, :]).reshape(-1)
        vals = footprints.to(torch.float32).reshape(n, kk, 1, 3) * c.to(torch.float32).reshape(n, 1, self.p, 3)
        self.canvas.index_put_((index,), vals.reshape(n * kk, self.p * 3), accumulate=True)

    def _fold(self, pixels: np.ndarray, footprints: torch.Tensor, c: torch.Tensor) -> None:
        n, k, kk, p3 = len(pixels), self.k, self.k * self.k, self.p * 3
        # (n, P*3, K*K): every footprint entry times each pattern's light, ordered as fold's columns
        vals = (footprints.to(torch.float32).reshape(n, 1, kk, 3) * c.to(torch.float32).reshape(n, self.p, 1, 3))
        vals = vals.permute(0, 1, 3, 2).reshape(n, p3, kk)
        ys = torch.as_tensor(pixels[:, 0], device=self.device)
        xs = torch.as_tensor(pixels[:, 1], device=self.device)
        band = max(1, FOLD_BAND_BYTES // (p3 * kk * self.w * 4))
        y_lo = int(pixels[:, 0].min())
        while y_lo <= int(pixels[:, 0].max()):
            sel = (ys >= y_lo) & (ys < y_lo + band)
            rows = min(band, self.h - y_lo)
            if bool(sel.any()):
                cols = torch.zeros(p3, kk, rows * self.w, dtype=torch.float32, device=self.device)
                # a camera pixel can carry several dots (measured transport): add, do not assign
                cols.index_add_(2, (ys[sel] - y_lo) * self.w + xs[sel], vals[sel].permute(1, 2, 0))
                out = torch.nn.functional.fold(cols, (rows + k - 1, self.w + k - 1), k)  # window top-left = (y, x)
                self.canvas[:, y_lo:y_lo + rows + k - 1, : self.w + k - 1] += out[:, 0]
            y_lo += band

    def result(self) -> np.ndarray:
        """Canvases cropped to the image, (P, H, W, 3) float32."""
        half = self.k // 2
        if self.method == "fold":
            img = self.canvas.reshape(self.p, 3, self.hp, self.wp)[:, :, half : half + self.h, half : half + self.w]
            return img.permute(0, 2, 3, 1).contiguous().cpu().numpy()
        if isinstance(self.canvas, np.ndarray):
            img = self.canvas.reshape(3, self.hp, self.wp, self.p)[:, half : half + self.h, half : half + self.w]
            return np.ascontiguousarray(img.transpose(3, 1, 2, 0))
        img = self.canvas.reshape(self.hp, self.wp, self.p, 3)[half : half + self.h, half : half + self.w]
        return img.permute(2, 0, 1, 3).contiguous().cpu().numpy()


def crop_footprints(fp: torch.Tensor, radius: int) -> torch.Tensor:
    """Truncate (N, K, K, 3) footprints to the central (2 radius + 1)^2 window."""
    half = fp.shape[1] // 2
    if radius < 0 or radius >= half:
        return fp
    return fp[:, half - radius : half + radius + 1, half - radius : half + radius + 1]


def relight(
    source: FootprintSource,
    proj: Projection,
    patterns: np.ndarray | Sequence[np.ndarray],
    patch: int,
    *,
    white: np.ndarray | None = None,
    chunk: int = 1024,
    dtype: torch.dtype = torch.float32,
    device: str = "cpu",
    radius: int | None = None,
    method: str = "auto",
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Relight one view under P projector patterns in one fused, chunked pass -> (P, H, W, 3) float32.

    ``white`` (the image under a full-white pattern, linear units) supplies the projector black
    level's contribution; without it the black level is ignored. ``dtype`` is the precision the
    footprints and the light are rounded to (accumulation is always float32). ``radius`` truncates
    footprints to the central (2 radius + 1)^2 window (cheaper splats). ``method`` picks the splat
    kernel (see :class:`Splatter`). Non-finite footprint values are set to 0 with a warning.
    ``progress(done, total)`` is called after each chunk.
    """
    if isinstance(patterns, np.ndarray):
        pats = patterns
    else:
        listed = [np.asarray(p, np.float32) for p in patterns]
        if any(p.ndim == 3 for p in listed):  # mono and colour patterns together: all as RGB
            listed = [np.repeat(p[..., None], 3, axis=-1) if p.ndim == 2 else p for p in listed]
        pats = np.stack(listed)
    if pats.ndim == 2:
        pats = pats[None]
    wp, hp = proj.projector_size
    if pats.shape[1:3] != (hp, wp):
        raise InputError(
            f"pattern size {pats.shape[2]}x{pats.shape[1]} does not match the projector's {wp}x{hp} "
            "(resize it explicitly first, e.g. `sss relight --resize`)"
        )
    if chunk < 1:
        raise InputError("chunk must be >= 1")
    light = emitted_light(pats, proj.gamma) * np.float32(1.0 - proj.black)
    if isinstance(source, DotTransport):  # measured columns of the light transport, one per projector dot
        pixels, c, rows = source.lit(light)
        fetch: Callable[[slice], np.ndarray | torch.Tensor] = lambda sl: source.crops_at(rows[sl])  # noqa: E731
    else:
        pixels, c = lit_pixels(proj, light)
        fetch = lambda sl: source(pixels[sl])  # noqa: E731
    h, w = proj.shape
    k = patch if radius is None or radius >= patch // 2 else 2 * radius + 1
    splat = Splatter(h, w, k, light.shape[0], device=device, method=method)
    total, n_bad = len(pixels), 0
    for start in range(0, total, chunk):
        sl = slice(start, min(start + chunk, total))
        fp = fetch(sl)
        fp = fp if torch.is_tensor(fp) else torch.from_numpy(np.ascontiguousarray(fp, dtype=np.float32))
        if fp.shape[1:] != (patch, patch, 3):
            raise InputError(f"the footprint source returned {tuple(fp.shape[1:])} footprints, expected ({patch}, {patch}, 3)")
        fp = crop_footprints(fp.to(device=device), radius if radius is not None else patch)
        bad = ~torch.isfinite(fp)
        if bad.any():  # a backend's NaN/inf must not spread over the whole canvas
            n_bad += int(bad.sum())
            fp = torch.where(bad, torch.zeros((), dtype=fp.dtype, device=fp.device), fp)
        fp = fp.to(dtype)
        splat.add(pixels[sl], fp, torch.as_tensor(c[sl], device=device).to(dtype))
        if progress is not None:
            progress(sl.stop, total)
    if n_bad:
        warnings.warn(f"{n_bad} non-finite footprint values from the footprint source were set to 0", RuntimeWarning, stacklevel=2)
    out = splat.result()
    if white is not None and proj.black > 0:
        out += np.float32(proj.black) * np.asarray(white, np.float32)[None]
    return out


# --- footprint sources -------------------------------------------------------------------------


class DotTransport:
    """The measured light transport of a captured view (``transport/`` arrays of a session): crop ``i``
    (K, K, 3) is the camera's response to projector pixel ``dots[i]`` (x, y), centred on camera pixel
    ``pixels[i]`` (y, x). :func:`relight` splats ``sum_i L(dots[i]) crop_i`` with the pattern's light at
    each dot exactly.

    With ``noise`` > 0 (the crops' noise std, ``footprints.ring_noise``) crops are denoised as they are
    read (``footprints.above_noise``); captures from this version zeroed their noise floor already and
    pass 0.
    """

    def __init__(self, pixels: np.ndarray, dots: np.ndarray, crops: object, noise: float) -> None:
        self.pixels, self.dots, self.crops, self.noise = np.asarray(pixels, np.int64), np.asarray(dots, np.int64), crops, noise

    def lit(self, light: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Dots lit by some pattern: (camera pixels (N, 2), light (N, P, C), rows into the crops (N,))."""
        c = light[:, self.dots[:, 1], self.dots[:, 0], :].transpose(1, 0, 2)
        rows = np.nonzero((c > 0).any(axis=(1, 2)))[0]
        return self.pixels[rows], c[rows], rows

    def crops_at(self, rows: np.ndarray) -> np.ndarray:
        """Denoised crops (n, K, K, 3) float32 of ``rows`` (ascending, as :meth:`lit` gives them)."""
        if len(rows) == 0:
            return np.zeros((0, *self.crops.shape[1:]), np.float32)  # type: ignore[attr-defined]
        from sssphase_core.footprints import above_noise

        lo, hi = int(rows.min()), int(rows.max()) + 1
        if hi - lo <= 4 * len(rows) or not hasattr(self.crops, "oindex"):  # one contiguous read of the chunks
            crops = np.asarray(self.crops[lo:hi])[rows - lo].astype(np.float32)  # type: ignore[index]
        else:  # a sparse pattern lights few of the rows in between: read only theirs
            crops = np.asarray(self.crops.oindex[rows]).astype(np.float32)  # type: ignore[attr-defined]
        if self.noise > 0 and len(crops):
            crops = crops * above_noise(crops, self.noise)[..., None]
        return crops



def no_scattering_source(white: np.ndarray, patch: int = 1) -> FootprintSource:
    """The no-scattering baseline: a delta footprint carrying the pixel's white-image value
    (``patch`` 1 splats it at no cost; a larger patch gives the same image)."""
    img = np.asarray(white, np.float32)
    img = np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img

    def source(pixels: np.ndarray) -> np.ndarray:
        fp = np.zeros((len(pixels), patch, patch, 3), np.float32)
        fp[:, patch // 2, patch // 2] = np.nan_to_num(img[pixels[:, 0], pixels[:, 1]])
        return fp

    return source


def backend_source(backend: object, psp: np.ndarray, chunk: int = 256) -> FootprintSource:
    """Footprints predicted by a model backend from the (N, 24, K, K) PSP patches of the asked pixels,
    cropped from the view's stack padded once (a 1080p stack is 200 MB) and given to
    ``predict_footprints`` ``chunk`` at a time (a K = 90 patch is 0.8 MB, and backends work on copies)."""
    from sssphase_core.data import crop_patches, pad_for_patches, to_channels_first

    k = int(backend.patch)  # type: ignore[attr-defined]
    stack = pad_for_patches(to_channels_first(np.asarray(psp, np.float32)), k)

    def source(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        parts = [backend.predict_footprints(crop_patches(stack, pixels[i:i + chunk], k, padded=True).numpy())  # type: ignore[attr-defined]
                 for i in range(0, len(pixels), chunk)]
        if not parts:
            return np.zeros((0, k, k, 3), np.float32)
        if torch.is_tensor(parts[0]):
            return torch.cat(parts)
        return np.concatenate(parts)

    return source


WHITE_FLOOR = 1e-3  # white values below this (linear camera units) are noise: no ratio is taken


def nearest_measured_source(pixels: np.ndarray, crops: np.ndarray, white: np.ndarray,
                            weights: np.ndarray | None = None) -> FootprintSource:
    """Captured footprints (dot-grid crops ``(N, K, K, 3)`` at ``pixels`` ``(N, 2)`` yx), each times its
    ``weights`` entry (``(N,)``, default 1): a pixel with its own crop gets it; any other pixel takes
    its nearest captured footprint, rescaled by the ratio of their white-image values (only where
    both are above the noise floor, at most 4x)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(pixels, np.float64))
    img = np.asarray(white, np.float32)
    img = np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img
    px_ref = np.asarray(pixels, np.int64)
    fps = np.asarray(crops, np.float32)  # read once: every relit pixel needs its crop
    if weights is not None:
        fps = fps * np.asarray(weights, np.float32)[:, None, None, None]

    def source(query: np.ndarray) -> np.ndarray:
        query = np.asarray(query, np.int64)
        _, idx = tree.query(query.astype(np.float64))
        wq, wr = img[query[:, 0], query[:, 1]], img[px_ref[idx, 0], px_ref[idx, 1]]
        ratio = np.where(wr > WHITE_FLOOR, np.clip(wq / np.maximum(wr, WHITE_FLOOR), 0.0, 4.0), 1.0)
        ratio[(px_ref[idx] == query).all(axis=1)] = 1.0
        return fps[idx] * ratio[:, None, None, :]

    return source


class FootprintCache:
    """A compressed (float16 ``.npz``) cache of footprints keyed by pixel, wrapped around a source.

    Later relights (other patterns) read cached footprints and run the source only for pixels that
    are not cached yet; ``save()`` writes the cache back when new footprints were computed. It holds
    at most ``max_bytes`` in memory (a 1080p view at K = 90 has ~15 GB of float16 footprints): past
    that, footprints pass through uncached and ``uncached`` counts them.
    """

    def __init__(self, source: FootprintSource, path: Path | str, shape: tuple[int, int], patch: int,
                 max_bytes: int = 2 * 2**30):
        self.source, self.path, self.shape, self.patch = source, Path(path), shape, patch
        self.max_rows = max(0, int(max_bytes) // (patch * patch * 3 * 2))
        self.slot = np.full(shape[0] * shape[1], -1, np.int64)
        self.data = np.zeros((0, patch, patch, 3), np.float16)  # capacity grows by doubling; ``size`` rows used
        self.size = 0
        self.hits = self.misses = self.uncached = 0
        self._dirty = False
        if self.path.exists():
            with np.load(self.path) as z:
                if z["data"].shape[1:] == (patch, patch, 3) and tuple(z["shape"]) == tuple(shape):
                    self.data = z["data"][: self.max_rows]
                    self.size = len(self.data)
                    self.slot[z["index"][: self.size]] = np.arange(self.size)

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        flat = pixels[:, 0].astype(np.int64) * self.shape[1] + pixels[:, 1]
        pos = self.slot[flat]
        miss = pos < 0
        out = np.empty((len(pixels), self.patch, self.patch, 3), np.float32)
        out[~miss] = self.data[pos[~miss]]
        if miss.any():
            fp = self.source(pixels[miss])
            fp = fp.float().cpu().numpy() if torch.is_tensor(fp) else np.asarray(fp, np.float32)
            out[miss] = fp
            keep = min(len(fp), self.max_rows - self.size)
            self.uncached += len(fp) - keep
            if keep > 0:
                if self.size + keep > len(self.data):
                    grown = np.zeros((min(self.max_rows, max(2 * len(self.data), self.size + keep, 1024)),
                                      self.patch, self.patch, 3), np.float16)
                    grown[: self.size] = self.data[: self.size]
                    self.data = grown
                self.data[self.size : self.size + keep] = fp[:keep]
                self.slot[flat[miss][:keep]] = self.size + np.arange(keep)
                self.size += keep
                self._dirty = True
        self.hits += int((~miss).sum())
        self.misses += int(miss.sum())
        return out

    def save(self) -> None:
        if not self._dirty:
            return
        index = np.flatnonzero(self.slot >= 0)
        index = index[np.argsort(self.slot[index])]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, data=self.data[: self.size], index=index, shape=np.asarray(self.shape))
        tmp.replace(self.path)
        self._dirty = False


# --- session views -----------------------------------------------------------------------------


@dataclass
class RelightView:
    """What relighting one view of a session needs, plus its references when it has any."""

    object: str
    view: int
    proj: Projection
    psp: np.ndarray  # (8, H, W, 3)
    white: np.ndarray  # (H, W, 3)
    patch: int
    references: dict[str, np.ndarray]  # name -> pattern (Hp, Wp[, 3]) of the ref/<name> captures
    captured: dict[str, np.ndarray]  # name -> reference image (noise-free sim render if stored, else capture)
    sim: dict | None = None  # SimScene arguments of a simulated session
    session: object | None = None
    saturation: float | None = None  # clipping level of the PSP frames (linear units), None: unknown
    white_saturation: float | None = None  # the white capture's (None: it does not clip, e.g. HDR)
    _camera: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def camera_image(self, name: str) -> np.ndarray:
        """The camera's noise-free image of reference ``name`` (simulated sessions; evaluation only): its
        render through the sensor's Bayer sampling and demosaicing, without noise. Made once for every
        reference of the view when first asked."""
        if not self._camera:
            names = sorted(self.captured)
            images = self.scene().sense_noise_free(np.stack([self.captured[n] for n in names]))
            self._camera.update(zip(names, images, strict=True))
        return self._camera[name]

    def scene(self):
        """The simulator scene of a simulated session (exact footprints, ``exact``: evaluation only)."""
        from sssphase_core.sim import SimScene, rig_preset

        if self.sim is None:
            raise InputError(f"{self.object}: not a simulated session")
        s = self.sim
        return SimScene(s["object"], rig=rig_preset(s["preset"]), view=self.view, n_views=s["n_views"], seed=s["seed"])


def load_view(session: object, view: int) -> RelightView:
    """Read one complete view of a :class:`sssphase_core.session.Session` for relighting."""
    from sssphase_core.patterns import PlannedFrame

    m = session.manifest  # type: ignore[attr-defined]
    if view not in session.views():  # type: ignore[attr-defined]
        raise InputError(f"session {session.path} has no complete view {view} (has {session.views()})")  # type: ignore[attr-defined]
    plan = m.get("plan", {})
    wp, hp = plan.get("projector", (0, 0))
    rig = m.get("rig", {})
    opts = rig.get("options", {})
    arrays = session.arrays(view)  # type: ignore[attr-defined]
    load = lambda name: np.asarray(session.load(view, name))  # type: ignore[attr-defined]  # noqa: E731
    white = load("white").astype(np.float32)
    mask = load("corr/mask").astype(bool)
    sim = None
    black = 0.0
    patch = int(rig.get("patch") or 32)
    if str(rig.get("camera", "")).startswith("sim:"):
        from sssphase_core.sim import rig_preset

        sim = {"object": opts.get("object", m.get("object")), "preset": opts.get("preset", "cpu"),
               "n_views": int(opts.get("n_views", m.get("n_views", 4))), "seed": int(opts.get("seed", 0))}
        preset = rig_preset(sim["preset"])
        black, patch = float(opts.get("projector_black", preset.projector.black)), int(rig.get("patch") or preset.patch)
    if rig.get("projector_black") is not None:  # calibrated (sss calibrate projector)
        black = float(rig["projector_black"])
    elif sim is None and "black" in arrays:  # the black frame is black_level * white
        blk, wl = load("black").mean(axis=-1), white.mean(axis=-1)
        ok = mask & (wl > 0.05)
        black = float(np.clip(np.median(blk[ok] / wl[ok]), 0, 0.5)) if ok.any() else 0.0
    proj = Projection(load("corr/xp").astype(np.float32), load("corr/yp").astype(np.float32), mask,
                      (int(wp), int(hp)), float(plan.get("gamma", 2.2)), black)
    references, captured = {}, {}
    for f in plan.get("frames", []):
        if f["kind"] == "ref" and f["key"] not in (f"ref/{n}" for n in references):
            name = f["key"].removeprefix("ref/")
            references[name] = PlannedFrame(f["key"], f["kind"], f["params"], 1.0).pattern()
    for name in (a.removeprefix("pattern/") for a in arrays if a.startswith("pattern/")):
        references.setdefault(name, load(f"pattern/{name}").astype(np.float32))  # the user's own pattern files
    for name in list(references):
        gt = f"gt/render/{name}"
        if gt in arrays:
            captured[name] = load(gt).astype(np.float32)
        elif f"ref/{name}" in arrays:
            captured[name] = load(f"ref/{name}").astype(np.float32)
        else:
            references.pop(name)
    psp_clip, white_clip = session.clip_levels()  # type: ignore[attr-defined]
    return RelightView(str(m.get("object")), view, proj, load("psp").astype(np.float32), white, patch,
                       references, captured, sim, session, psp_clip, white_clip)


def make_source(name: str, rv: RelightView, *, checkpoint: Path | str | None = None, device: str = "cpu",
                **options: object) -> tuple[FootprintSource, int]:
    """The footprint source of backend ``name`` for a view -> (source, patch size); ``options`` go to
    the model backend (e.g. ``supersample`` for ``analytic``)."""
    if name == "none":
        return no_scattering_source(rv.white), 1
    if name == "exact":  # ground truth for evaluation only: no lab has these
        if rv.sim is None:
            raise InputError(f"{rv.object}: exact footprints exist only for simulated sessions (use measured)")
        return rv.scene().footprints, rv.patch
    if name == "measured":  # the session's own captured dot-grid crops, simulated or not
        arrays = rv.session.arrays(rv.view)  # type: ignore[attr-defined]
        if "transport/crops" in arrays:  # one crop per projector dot: the captured light transport itself
            from sssphase_core.footprints import ring_noise

            crops = rv.session.read(rv.view, "transport/crops")  # type: ignore[attr-defined]
            info = rv.session.manifest["views"][str(rv.view)].get("transport", {})  # type: ignore[attr-defined]
            if info.get("noise_dropped"):  # the capture zeroed the noise floor already (and recorded it)
                noise = 0.0
            else:
                noise = ring_noise(np.asarray(crops[: min(len(crops), 512)], np.float32)) if len(crops) else 0.0
            return DotTransport(rv.session.load(rv.view, "transport/pixels"), rv.session.load(rv.view, "transport/dots"),  # type: ignore[attr-defined]
                                crops, noise), int(crops.shape[1])
        if "footprints/crops" not in arrays:
            raise InputError(f"{rv.object} view {rv.view} has no captured footprints: capture with --footprints")
        from sssphase_core.footprints import transport_weights

        px = np.asarray(rv.session.load(rv.view, "footprints/pixels"), np.int64)  # type: ignore[attr-defined]
        crops = rv.session.read(rv.view, "footprints/crops")  # type: ignore[attr-defined]
        weights = transport_weights(px, rv.proj.xp, rv.proj.yp, rv.proj.mask)
        return nearest_measured_source(px, crops, rv.white, weights), int(crops.shape[1])
    from sssphase_core.backends import get_backend

    if name == "torch":
        if checkpoint is None:
            raise InputError("the torch backend needs --checkpoint (a decoder checkpoint from `sss train decoder`)")
        backend = get_backend("torch", checkpoint=checkpoint, device=device, **options)
    elif name == "analytic":
        backend = get_backend("analytic", **{"patch": rv.patch, "black": rv.proj.black, **options})
    else:
        backend = get_backend(name, **options)
    psp, lost = model_inputs(rv)
    source = backend_source(backend, psp)
    usable = white_usable(rv.white, rv.white_saturation)
    if (lost & usable).any():  # fringes beyond repair: the energy from the white capture (reciprocity)
        source = energy_from_white(source, lost & usable, rv.white)
    return source, int(backend.patch)


def model_inputs(rv: RelightView) -> tuple[np.ndarray, np.ndarray]:
    """The view's PSP stack for a model backend, clipped samples repaired (:func:`psp.declip`), and the
    (H, W) bool map of pixels whose clipped fringes could not be repaired."""
    if rv.saturation is None:
        return rv.psp, np.zeros(rv.psp.shape[1:3], bool)
    from sssphase_core.psp import declip

    return declip(rv.psp, rv.saturation, white=rv.white, white_saturation=rv.white_saturation, black=rv.proj.black)


def white_usable(white: np.ndarray, saturation: float | None, margin: float = SATURATION_MARGIN) -> np.ndarray:
    """(H, W) bool: the white capture is finite, above the noise floor and below its clipping level in
    every colour (``saturation`` None: it does not clip)."""
    w = np.asarray(white, np.float32)
    ok = np.isfinite(w) & (w > WHITE_FLOOR)
    if saturation is not None:
        ok &= w < margin * saturation
    return ok.all(axis=-1)


def energy_from_white(source: FootprintSource, where: np.ndarray, white: np.ndarray) -> FootprintSource:
    """``source``'s footprints, those of the pixels where the (H, W) bool ``where`` is set rescaled per
    colour to carry the white capture's value (by reciprocity a footprint's energy), where the model's
    own energy came from clipped fringes. Mixing in no-scattering deltas instead counts light twice
    where scattering neighbours also deliver it (measured: 20.7 dB against 32.7 on the saturated
    stability case)."""
    img = np.asarray(white, np.float32)

    def rescaled(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        out = source(pixels)
        pick = where[pixels[:, 0], pixels[:, 1]]
        if not pick.any():
            return out
        out = out.float().cpu().numpy() if torch.is_tensor(out) else np.array(out, np.float32)
        energy = out[pick].sum(axis=(1, 2))  # (n, 3)
        target = img[pixels[pick, 0], pixels[pick, 1]]
        gain = np.where(energy > WHITE_FLOOR, target / np.maximum(energy, WHITE_FLOOR), 1.0)
        out[pick] *= gain[:, None, None, :].astype(np.float32)
        return out

    return rescaled


# --- output images -----------------------------------------------------------------------------


IMAGE_FORMATS = ("png", "exr")


def check_image_formats(formats: tuple[str, ...]) -> tuple[str, ...]:
    """``formats`` if each is one of :data:`IMAGE_FORMATS` (and there is one), else an InputError."""
    unknown = sorted(set(formats) - set(IMAGE_FORMATS)) or ([] if formats else ["(none)"])
    if unknown:
        raise InputError(f"unknown image format {', '.join(unknown)}: choose png, exr or png,exr")
    return formats


def write_images(stem: Path | str, image: np.ndarray, *, scale: float | None = None,
                 formats: tuple[str, ...] = ("png",)) -> list[Path]:
    """Write the relit ``image`` (H, W, 3) linear camera units; returns the paths.

    ``png``: ``stem.png``, 16-bit linear (65535 = 1.0 camera unit, brighter values clip);
    ``exr``: ``stem.exr``, float32 unclipped (OpenEXR bindings). Always ``stem_display.png`` (sRGB,
    exposure ``scale`` or the 99.5th percentile) for looking at.
    """
    import cv2

    from sssphase_core import exr

    check_image_formats(formats)
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, np.float32)
    finite = np.nan_to_num(img)
    bgr = finite[..., ::-1] if finite.ndim == 3 else finite
    paths = []
    if "exr" in formats:
        paths.append(exr.write_exr(stem.with_suffix(".exr"), img, attributes={"units": "linear camera units"}))
    if "png" in formats:
        paths.append(stem.with_suffix(".png"))
        cv2.imwrite(str(paths[-1]), np.round(np.clip(bgr, 0, 1) * 65535).astype(np.uint16))
    s = scale if scale is not None else display_scale(finite)
    paths.append(stem.with_name(stem.name + "_display.png"))
    cv2.imwrite(str(paths[-1]), np.round(srgb(bgr / s) * 255).astype(np.uint8))
    return paths


RESIZE_MODES = ("fit", "fill", "stretch")


def _resized(img, size: tuple[int, int], mode: str):
    """A PIL image brought to ``size`` (W, H): ``stretch`` ignores the aspect ratio, ``fit`` scales it
    inside and pads with black, ``fill`` scales it to cover and crops the centre."""
    from PIL import Image

    wp, hp = size
    if mode == "stretch":
        return img.resize((wp, hp), Image.Resampling.BILINEAR)
    w, h = img.size
    k = min(wp / w, hp / h) if mode == "fit" else max(wp / w, hp / h)
    scaled = img.resize((max(1, round(w * k)), max(1, round(h * k))), Image.Resampling.BILINEAR)
    canvas = Image.new(scaled.mode, (wp, hp))
    canvas.paste(scaled, ((wp - scaled.size[0]) // 2, (hp - scaled.size[1]) // 2))
    return canvas


def read_pattern(path: Path | str, projector_size: tuple[int, int], *, resize: str | bool = "") -> np.ndarray:
    """A pattern image file -> float32 values in [0, 1], (Hp, Wp) or (Hp, Wp, 3).

    The size must match the projector unless ``resize`` is ``fit``, ``fill`` or ``stretch`` (see
    :func:`_resized`; ``True`` means ``stretch``). Palette, alpha and CMYK images are read as RGB,
    16-bit images divided by 65535.
    """
    from PIL import Image

    mode = "stretch" if resize is True else (resize or "")
    if mode and mode not in RESIZE_MODES:
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {mode!r}")
    wp, hp = projector_size
    try:
        img = Image.open(path)  # reads the header only: the size is checked before any pixel is decoded
        w, h = img.size
        if w * h > max(4 * wp * hp, 1 << 22):
            raise InputError(f"pattern {path} is {w}x{h}, far larger than the {wp}x{hp} projector: refused "
                             "without decoding it (scale it down first)")
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img.load()
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise InputError(f"pattern {path} is far larger than the {wp}x{hp} projector: refused without decoding it "
                         "(scale it down first)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"cannot read pattern {path}: {exc}") from None
    if img.mode in ("1", "LA"):
        img = img.convert("L")
    elif img.mode not in ("L", "RGB", "F") and not img.mode.startswith("I"):
        img = img.convert("RGB")  # palette (P), RGBA, CMYK, YCbCr: the colours, not their codes
    if img.size != (wp, hp):
        if not mode:
            raise InputError(f"pattern {path} is {img.size[0]}x{img.size[1]} but the projector is {wp}x{hp} "
                             "(pass --resize fit, fill or stretch)")
        img = _resized(img, (wp, hp), mode)
    arr = np.asarray(img)
    if arr.dtype.kind == "f":
        scale = 1.0
    elif img.mode.startswith("I"):
        scale = 65535.0  # 16-bit PNG/TIFF (Pillow's I;16 and I modes)
    else:
        scale = 255.0
    arr = arr.astype(np.float32) / scale
    if arr.ndim == 3:
        arr = arr[..., :3]
        if np.allclose(arr, arr[..., :1]):
            arr = arr[..., 0]
    return np.clip(arr, 0, 1)
