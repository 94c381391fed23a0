"""Footprint sources: where each lit pixel's (K, K, 3) footprint comes from (no scattering, a model
backend, the captured light transport or crops, the simulator), and :func:`make_source`, which picks one
by name for a view."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from sssphase_core.errors import InputError
from sssphase_core.processing.isp import SATURATION_MARGIN
from sssphase_core.relight.engine import FootprintSource
from sssphase_core.relight.views import RelightView


class DotTransport:
    """The measured light transport of a captured view (``transport/`` arrays of a session): crop ``i``
    (K, K, 3) is the camera's response to projector pixel ``dots[i]`` (x, y), centred on camera pixel
    ``pixels[i]`` (y, x). :func:`relight` splats ``sum_i L(dots[i]) crop_i`` with the pattern's light at
    each dot exactly.

    With ``noise`` > 0 (the crops' noise std, ``footprints.crop_noise``) crops are denoised as they are
    read by the mask of ``smoothing`` px (``footprints.above_noise``; :func:`denoised_transport` picks it
    per view); crops whose noise floor was zeroed with a single mask pass 0.
    """

    def __init__(self, pixels: np.ndarray, dots: np.ndarray, crops: object, noise: float, smoothing: float = 1.0) -> None:
        self.pixels, self.dots, self.crops, self.noise = np.asarray(pixels, np.int64), np.asarray(dots, np.int64), crops, noise
        self.smoothing = float(smoothing)
        self.fit: dict[float, float] = {}  # PSNR (dB) of each candidate mask on the view's fringe captures, when chosen

    def lit(self, light: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Dots lit by some pattern: (camera pixels (N, 2), light (N, P, C), rows into the crops (N,))."""
        c = light[:, self.dots[:, 1], self.dots[:, 0], :].transpose(1, 0, 2)
        rows = np.nonzero((c > 0).any(axis=(1, 2)))[0]
        return self.pixels[rows], c[rows], rows

    def crops_at(self, rows: np.ndarray) -> np.ndarray:
        """Denoised crops (n, K, K, 3) float32 of ``rows`` (ascending, as :meth:`lit` gives them)."""
        if len(rows) == 0:
            return np.zeros((0, *self.crops.shape[1:]), np.float32)  # type: ignore[attr-defined]
        from sssphase_core.processing.footprints import above_noise

        lo, hi = int(rows.min()), int(rows.max()) + 1
        if hi - lo <= 4 * len(rows) or not hasattr(self.crops, "oindex"):  # one contiguous read of the chunks
            crops = np.asarray(self.crops[lo:hi])[rows - lo].astype(np.float32)  # type: ignore[index]
        else:  # a sparse pattern lights few of the rows in between: read only theirs
            crops = np.asarray(self.crops.oindex[rows]).astype(np.float32)  # type: ignore[attr-defined]
        if self.noise > 0 and len(crops):
            crops = crops * above_noise(crops, self.noise, smoothing=self.smoothing)[..., None]
        return crops


def denoised_transport(rv: RelightView, pixels: np.ndarray, dots: np.ndarray, crops: object, noise: float,
                       smoothings: Sequence[float]) -> DotTransport:
    """The captured transport of a view denoised by the mask (one of ``smoothings`` px, see
    ``footprints.DENOISE_SMOOTHING``) that relights the view's own 8 fringe captures best: no ground
    truth, and the crops are camera images like the captures, so they are compared as they are. Its
    ``fit`` records each candidate's PSNR (dB) on those captures. Without the view's PSP patterns, the
    first candidate."""
    from sssphase_core.learning.metrics import psnr
    from sssphase_core.relight.engine import relight

    candidates = [DotTransport(pixels, dots, crops, noise, s) for s in smoothings]
    if rv.psp_patterns is None or noise <= 0 or len(candidates) == 1:
        return candidates[0]
    m = rv.proj.mask & np.isfinite(rv.psp).all(axis=(0, -1))
    k = int(crops.shape[1])  # type: ignore[attr-defined]
    fit = {t.smoothing: psnr(float(np.mean((relight(t, rv.proj, rv.psp_patterns, k, white=rv.white)[:, m] - rv.psp[:, m]) ** 2)))
           for t in candidates}
    best = next(t for t in candidates if t.smoothing == max(fit, key=fit.__getitem__))
    best.fit = fit
    return best



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
    from sssphase_core.learning.data import crop_patches, pad_for_patches, to_channels_first

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
    that, footprints pass through uncached and ``uncached`` counts them. It holds the source's own
    footprints (before any view calibration, which :func:`relight_view` applies after the splat); a
    file of another ``FORMAT`` (format 1 held calibrated footprints) is ignored and rewritten.
    """

    FORMAT = 2

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
            self._load()

    def _load(self) -> None:
        """Take the file's footprints when it is a cache of this view and patch; anything else (another
        format, a damaged or foreign file) is ignored and rewritten: a cache only saves time."""
        import zipfile

        try:
            with np.load(self.path, allow_pickle=False) as z:
                if not ("format" in z.files and int(z["format"]) == self.FORMAT and tuple(z["shape"]) == tuple(self.shape)):
                    return
                data, index = z["data"], z["index"]
        except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile):
            return
        data, index = data[: self.max_rows], np.asarray(index)
        if (data.shape[1:] != (self.patch, self.patch, 3) or data.dtype != np.float16 or index.ndim != 1
                or index.dtype.kind not in "iu" or len(index) < len(data)):
            return
        index = index[: len(data)].astype(np.int64)
        if len(index) and (index.min() < 0 or index.max() >= len(self.slot) or len(np.unique(index)) != len(index)):
            return
        self.data, self.size = data, len(data)
        self.slot[index] = np.arange(self.size)

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
        from sssphase_core.store.files import atomic_path

        with atomic_path(self.path, ".npz") as tmp:
            np.savez_compressed(tmp, data=self.data[: self.size], index=index, shape=np.asarray(self.shape),
                                format=np.asarray(self.FORMAT))
        self._dirty = False


MODEL_FREE = ("none", "exact", "measured")  # footprint sources that are data, not a model: never calibrated
#: Backends that blend several models by the view calibration (:func:`relight_view` ``also``).
BLENDS: dict[str, tuple[str, ...]] = {"blend": ("torch", "analytic")}


def make_source(name: str, rv: RelightView, *, checkpoint: Path | str | None = None, device: str = "cpu",
                calibrate: bool = True, **options: object) -> tuple[FootprintSource, int]:
    """The footprint source of backend ``name`` for a view -> (source, patch size); ``options`` go to
    the model backend (e.g. ``supersample`` for ``analytic``). A model backend's footprints are
    ``calibrate``-d to the view (:func:`fit_view_mix`) unless told not to."""
    if name == "none":
        return no_scattering_source(rv.white), 1
    if name == "exact":  # ground truth for evaluation only: no lab has these
        if rv.sim is None:
            raise InputError(f"{rv.object}: exact footprints exist only for simulated sessions (the simulator's ground "
                             "truth); this session was captured or imported")
        return rv.scene().footprints, rv.patch
    if name == "measured":  # the session's own captured dot-grid crops, simulated or not
        arrays = rv.session.arrays(rv.view)  # type: ignore[attr-defined]
        if "transport/crops" in arrays:  # one crop per projector dot: the captured light transport itself
            from sssphase_core.processing.footprints import crop_noise

            crops = rv.session.read(rv.view, "transport/crops")  # type: ignore[attr-defined]
            info = rv.session.manifest["views"][str(rv.view)].get("transport", {})  # type: ignore[attr-defined]
            smoothings = [float(x) for x in info.get("denoise_smoothing", [1.0])]
            if info.get("noise_dropped") and len(smoothings) == 1:  # zeroed with one mask at capture: as stored
                noise = 0.0
            elif info.get("noise_dropped"):  # the union of several masks stored: the view's own captures choose
                noise = float(info.get("noise", 0.0))
            else:
                noise = crop_noise(np.asarray(crops[: min(len(crops), 512)], np.float32)) if len(crops) else 0.0
            pixels, dots = rv.session.load(rv.view, "transport/pixels"), rv.session.load(rv.view, "transport/dots")  # type: ignore[attr-defined]
            return denoised_transport(rv, pixels, dots, crops, noise, smoothings), int(crops.shape[1])
        if "footprints/crops" not in arrays:
            raise InputError(f"{rv.object} view {rv.view} has no captured footprints: capture with --footprints")
        from sssphase_core.processing.footprints import transport_weights

        px = np.asarray(rv.session.load(rv.view, "footprints/pixels"), np.int64)  # type: ignore[attr-defined]
        crops = rv.session.read(rv.view, "footprints/crops")  # type: ignore[attr-defined]
        weights = transport_weights(px, rv.proj.xp, rv.proj.yp, rv.proj.mask)
        return nearest_measured_source(px, crops, rv.white, weights), int(crops.shape[1])
    from sssphase_core.learning.backends import get_backend

    if name == "torch":
        needs_checkpoint(name, checkpoint)
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
    k = int(backend.patch)
    if calibrate and rv.psp_patterns is not None:
        source = mixed_with_no_scattering(source, fit_view_mix(source, k, rv, psp, lost), rv.white)
    return source, k


def check_backends(names: Sequence[str], checkpoint: Path | str | None) -> None:
    """Refuse unknown footprint sources, and the decoder's without a readable checkpoint, before any work
    starts (a missing or foreign checkpoint is one line before any progress is shown)."""
    from sssphase_core.learning.backends import available_backends

    known = [*MODEL_FREE, *BLENDS, *available_backends()]
    for name in names:
        if name not in known:
            raise InputError(f"unknown backend {name!r}; available: {', '.join(sorted(set(known)))}")
        needs_checkpoint(name, checkpoint)
    if checkpoint is not None and any(uses_decoder(n) for n in names):
        from sssphase_core.learning.training.checkpoints import load_decoder

        load_decoder(checkpoint)  # raises DataError naming what the file is, or weights that are not finite


def uses_decoder(name: str) -> bool:
    """Whether backend ``name`` runs the decoder (``torch``, or a blend with it): it needs a checkpoint."""
    return name == "torch" or "torch" in BLENDS.get(name, ())


def needs_checkpoint(name: str, checkpoint: Path | str | None) -> None:
    """Refuse the decoder, or a blend with it, without a decoder checkpoint."""
    if checkpoint is not None or not uses_decoder(name):
        return
    if name == "torch":
        raise InputError("the torch backend needs --checkpoint (a decoder checkpoint from `sss train decoder`)")
    raise InputError(f"the {name} backend blends the decoder in: it needs --checkpoint (a decoder from `sss train decoder`)")


def make_sources(name: str, rv: RelightView, *, checkpoint: Path | str | None = None, device: str = "cpu",
                 **options: object) -> list[tuple[FootprintSource, int]]:
    """The uncalibrated (source, patch) pairs of backend ``name``: its own, or for a blend
    (:data:`BLENDS`: ``blend`` = the decoder and the analytic model, weighted per view and colour by how
    well they relight the view's own fringe captures) each member's; ``options`` go to the analytic
    member of a blend."""
    if name not in BLENDS:
        return [make_source(name, rv, checkpoint=checkpoint, device=device, calibrate=False, **options)]
    needs_checkpoint(name, checkpoint)
    return [make_source(m, rv, checkpoint=checkpoint, device=device, calibrate=False,
                        **(options if m == "analytic" else {})) for m in BLENDS[name]]


def fit_view_mix(source: FootprintSource, patch: int, rv: RelightView, psp: np.ndarray | None = None,
                 exclude: np.ndarray | None = None) -> np.ndarray:
    """Per-colour weight ``a`` (3,) in [0, 1] of a model's footprints against no scattering, fitted on the
    view's own captures: the 8 PSP frames are images under known patterns, so the view is relit under
    them with both sources and ``a`` minimises ``|a R_model + (1 - a) R_none - captured|^2`` on the valid
    pixels (relighting is linear in the footprints, so the mixed footprints relight to exactly that
    mixture). It needs no ground truth, and the mixture relights the captures at least as well as either
    source alone. Measured on the demo's unseen objects against the noise-free render: the decoder
    trained on captured crops 27.3-30.2 dB, no scattering 31.3-32.8, the mixture 33.2-34.0.

    Args:
        psp: (8, H, W, 3) the captures (default ``rv.psp``; repaired ones from :func:`model_inputs`).
        exclude: (H, W) bool pixels left out of the fit (e.g. fringes clipped beyond repair).
    """
    if rv.psp_patterns is None:
        raise InputError(f"{rv.object} view {rv.view}: the projector patterns of its PSP captures are unknown")
    from sssphase_core.relight.engine import relight

    return view_mix(rv, relight(source, rv.proj, rv.psp_patterns, patch, white=rv.white), psp, exclude)


def relight_view(source: FootprintSource, patch: int, rv: RelightView, patterns: list[np.ndarray], *,
                 calibrate: bool, also: Sequence[tuple[FootprintSource, int]] = (), chunk: int = 2048,
                 device: str = "cpu", progress: Callable[[int, int], None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Relight a view under ``patterns`` (P of (Hp, Wp[, 3])) with an uncalibrated ``source``
    (``make_source(..., calibrate=False)``) -> ((P, H, W, 3) images, view-wide per-colour mix (3,) or None).

    With ``calibrate`` (and the view's PSP patterns known) the view calibration of :func:`fit_view_mix`
    rides on the same footprint pass: the 8 PSP patterns are splatted beside the user's, and since
    relighting is linear in the footprints the mixed source's images are ``mix * model + (1 - mix) *
    none``, with the mix refined per pixel (:func:`local_mixture`). One pass instead of two (each
    footprint is predicted once).

    ``also``: more (source, patch) pairs blended in by the same fit: the images are
    ``sum_i mix_i * source_i + (1 - sum_i mix_i) * none``, each ``mix_i`` refined per pixel too, and the
    view-wide mix returned is (1 + len(also), 3). Blending needs ``calibrate``.
    """
    from sssphase_core.relight.engine import relight

    calibrate = calibrate and rv.psp_patterns is not None
    if also and not calibrate:
        raise InputError(f"{rv.object} view {rv.view}: blending sources needs the view calibration (the projector "
                         "patterns of its PSP captures, and calibration on)")
    n = len(patterns)
    every = list(patterns) + (list(rv.psp_patterns) if calibrate else [])
    relits = [relight(src, rv.proj, every, k, white=rv.white, chunk=chunk, device=device, progress=progress)
              for src, k in ((source, patch), *also)]
    if not calibrate:
        return relits[0], None
    psp, lost = model_inputs(rv)
    none = relight(no_scattering_source(rv.white), rv.proj, every, 1, white=rv.white)
    # each source's weight refined pixel by pixel where the view's own fringes say so
    weights, view_weights = local_mixture(rv, [r[n:] for r in relits], none[n:], psp, lost)
    images = none[:n].copy()
    for weight, relit in zip(weights, relits, strict=True):
        images += weight * (relit[:n] - none[:n])
    return images, (view_weights[0] if not also else view_weights)


#: Gaussian sigma (px) of the window over which local_mixture fits a model's weight, and the prior's
#: strength (a fraction of the median evidence) that pulls it toward the view-wide weight.
LOCAL_MIX_SIGMA, LOCAL_MIX_PRIOR = 2.0, 0.05


def local_mixture(rv: RelightView, relit_psps: Sequence[np.ndarray], none_psp: np.ndarray, psp: np.ndarray,
                  exclude: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(weights (S, H, W, 3), view_weights (S, 3))``: the weights of S sources against no scattering per
    pixel and colour, the constrained least-squares fit of :func:`view_mixture` (``a >= 0``,
    ``sum(a) <= 1``) made over a Gaussian window (:data:`LOCAL_MIX_SIGMA`) around each pixel, pulled
    toward the view-wide fit (``view_weights``, :func:`view_mixture`'s) where the window holds little
    evidence.

    A scene holds more than one material: an object on a diffuse table, a wax figure with a painted
    base. One weight per view is their compromise: on a stand-in skin over a diffuse floor the decoder
    (trained on objects only) spread light over the floor, and the view-wide weights relit it at
    27.0 / 28.1 dB (none 23.3 / 25.2, its own captured transport 34.7 / 34.1); weighted per pixel,
    32.9 / 32.2 (a blend of torch and analytic: 28.4 / 28.7 view-wide, 32.9 / 32.4 per pixel). On
    single-material views it changes little (demo crab and sand rake +0.0 to +0.2 dB).
    ``relit_psps``: S of (8, H, W, 3) the sources' relit fringes; ``none_psp``, ``psp``: no scattering's and
    the captures; ``exclude``: (H, W) pixels left out of the fit. Output pixels apply the weights of their
    own window (relighting is linear in the footprints; the weights vary over a few pixels only)."""
    import cv2

    if getattr(rv, "camera_isp", None):
        relit_psps, none_psp = [rv.through_camera(r) for r in relit_psps], rv.through_camera(none_psp)
    m = rv.proj.mask & np.isfinite(psp).all(axis=(0, -1))  # the silhouette too: see view_mixture
    if exclude is not None:
        m &= ~exclude
    s = len(relit_psps)
    d = [np.where(m[None, ..., None], r - none_psp, 0).astype(np.float32) for r in relit_psps]
    e = np.where(m[None, ..., None], np.nan_to_num(psp - none_psp), 0).astype(np.float32)
    gram = np.empty((*m.shape, 3, s, s), np.float32)  # per pixel and colour, summed over the 8 fringes
    cross = np.empty((*m.shape, 3, s), np.float32)
    for i in range(s):
        cross[..., i] = np.einsum("phwc,phwc->hwc", d[i], e)
        for j in range(i, s):
            gram[..., i, j] = gram[..., j, i] = np.einsum("phwc,phwc->hwc", d[i], d[j])
    total_gram, total_cross = gram.sum(axis=(0, 1), dtype=np.float64), cross.sum(axis=(0, 1), dtype=np.float64)
    view_weights = np.stack([mixture_weights(total_gram[c], total_cross[c]) for c in range(3)], axis=1)
    view_weights = view_weights.astype(np.float32)  # (S, 3)
    blur = lambda a: cv2.GaussianBlur(np.ascontiguousarray(a), (0, 0), LOCAL_MIX_SIGMA)  # noqa: E731
    for i in range(s):
        cross[..., i] = blur(cross[..., i])
        for j in range(i, s):
            gram[..., i, j] = gram[..., j, i] = blur(gram[..., i, j])
    # the prior: a fraction of the median evidence (per source) in a window
    prior = LOCAL_MIX_PRIOR * float(np.median(np.trace(gram, axis1=-2, axis2=-1)[m])) / s if m.any() else 0.0
    if not prior > 0:
        return np.broadcast_to(view_weights[:, None, None, :], (s, *m.shape, 3)).copy(), view_weights
    cross += prior * view_weights.T
    gram[..., range(s), range(s)] += prior
    if s == 1:  # the constrained optimum of one source is its fitted weight clipped to [0, 1]
        return np.clip(cross[..., 0] / gram[..., 0, 0], 0.0, 1.0)[None].astype(np.float32), view_weights
    gram, cross = gram.reshape(-1, s, s), cross.reshape(-1, s)
    step = 1 << 20  # problems per batch: a 1080p view's 6M stay within a few hundred MB
    weights = np.concatenate([batched_mixture_weights(gram[i:i + step], cross[i:i + step])
                              for i in range(0, len(cross), step)])
    return np.moveaxis(weights.reshape(*m.shape, 3, s), -1, 0).astype(np.float32), view_weights


def view_mix(rv: RelightView, relit_psp: np.ndarray, psp: np.ndarray | None = None,
             exclude: np.ndarray | None = None) -> np.ndarray:
    """:func:`fit_view_mix` from the model's relighting of the view under its PSP patterns,
    ``relit_psp`` (8, H, W, 3): a caller that relights other patterns too does it in the same pass."""
    return view_mixture(rv, [relit_psp], psp, exclude)[0]


def view_mixture(rv: RelightView, relit_psps: Sequence[np.ndarray], psp: np.ndarray | None = None,
                 exclude: np.ndarray | None = None) -> np.ndarray:
    """Per-colour weights (S, 3) of S sources' relightings of the view under its PSP patterns
    (each (8, H, W, 3)) against no scattering: ``sum_i a_i R_i + (1 - sum_i a_i) R_none`` fitted to the
    captures by least squares with ``a_i >= 0`` and ``sum_i a_i <= 1`` (:func:`mixture_weights`).
    ``psp``: the captures (default ``rv.psp``); ``exclude``: (H, W) pixels left out of the fit."""
    from sssphase_core.relight.engine import relight

    captured = rv.psp if psp is None else psp
    none = relight(no_scattering_source(rv.white), rv.proj, rv.psp_patterns, 1, white=rv.white)
    # The whole decoded mask, its silhouette included: the relit fringes are compared as the camera records them,
    # so demosaicing's mixing of object and background is on both sides, and the masks hold no background that
    # only demosaicing lit (psp.demosaic_bleed). Leaving out the 2 px next to the silhouette (as before that fix)
    # left the local weights there to the interior's: with decoders trained through the capture model the demo's
    # sand rake relit 0.1-0.3 dB worse against the render and 0.5-1.3 dB worse against its captures.
    m = rv.proj.mask & np.isfinite(captured).all(axis=(0, -1))
    if getattr(rv, "camera_isp", None):  # views built elsewhere (the benchmarks' SimView) have no camera record
        # Compare like with like: the relit fringes as the camera would record them. Without this the fit
        # reads demosaicing's contrast changes as scattering (measured: the exact footprints themselves
        # got weights 0.06-0.35 instead of 1 on the demo's crab, 0.97-1.0 with it).
        none, relit_psps = rv.through_camera(none), [rv.through_camera(r) for r in relit_psps]
    if exclude is not None:
        m &= ~exclude
    d = np.stack([(r - none)[:, m] for r in relit_psps]).astype(np.float64)  # (S, 8, n, 3)
    e = (captured - none)[:, m].astype(np.float64)  # (8, n, 3)
    gram = np.einsum("spnc,tpnc->cst", d, d)
    cross = np.einsum("spnc,pnc->cs", d, e)
    return np.stack([mixture_weights(gram[c], cross[c]) for c in range(3)], axis=1).astype(np.float32)


def mixture_weights(gram: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """The weights ``a`` (S,) minimising ``a^T G a - 2 c^T a`` (a least-squares fit with Gram matrix
    ``gram`` (S, S) and ``cross`` (S,)) subject to ``a >= 0`` and ``sum(a) <= 1``: exact, by trying
    every set of active sources, free or on the face ``sum(a) = 1`` (2^S small systems; S is 1-3).
    With one source this is the fitted weight clipped to [0, 1]."""
    s = len(cross)
    best, best_cost = np.zeros(s), 0.0
    for bits in range(1, 2**s):
        idx = [i for i in range(s) if bits >> i & 1]
        g, c = gram[np.ix_(idx, idx)], cross[idx]
        candidates = [np.linalg.lstsq(g, c, rcond=None)[0]]
        kkt = np.block([[g, np.ones((len(idx), 1))], [np.ones((1, len(idx))), np.zeros((1, 1))]])
        candidates.append(np.linalg.lstsq(kkt, np.append(c, 1.0), rcond=None)[0][:-1])
        for sub in candidates:
            if (sub < -1e-12).any() or sub.sum() > 1 + 1e-9:
                continue
            a = np.zeros(s)
            a[idx] = np.clip(sub, 0, None)
            cost = float(a @ gram @ a - 2 * cross @ a)
            if cost < best_cost - 1e-15 * max(1.0, abs(best_cost)):
                best, best_cost = a, cost
    return best


def batched_mixture_weights(gram: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """:func:`mixture_weights` for N problems at once: ``gram`` (N, S, S) positive definite, ``cross``
    (N, S) -> (N, S), each the exact optimum over ``a >= 0``, ``sum(a) <= 1`` (every active set tried,
    free and on the face ``sum(a) = 1``, the feasible candidate of least cost kept)."""
    n, s = cross.shape
    gram, cross = gram.astype(np.float64), cross.astype(np.float64)
    best, best_cost = np.zeros((n, s)), np.zeros(n)
    for bits in range(1, 2**s):
        idx = [i for i in range(s) if bits >> i & 1]
        g, c = gram[:, idx][:, :, idx], cross[:, idx]
        k = len(idx)
        kkt = np.zeros((n, k + 1, k + 1))
        kkt[:, :k, :k], kkt[:, :k, k], kkt[:, k, :k] = g, 1.0, 1.0
        rhs = np.concatenate([c, np.ones((n, 1))], axis=1)
        for sub in (np.linalg.solve(g, c[..., None])[..., 0], np.linalg.solve(kkt, rhs[..., None])[:, :k, 0]):
            ok = (sub >= -1e-9).all(axis=1) & (sub.sum(axis=1) <= 1 + 1e-9)
            a = np.zeros((n, s))
            a[:, idx] = np.clip(sub, 0, None)
            cost = np.einsum("ni,nij,nj->n", a, gram, a) - 2 * np.einsum("ni,ni->n", cross, a)
            better = ok & (cost < best_cost)
            best[better], best_cost[better] = a[better], cost[better]
    return best


def mixed_with_no_scattering(source: FootprintSource, mix: np.ndarray, white: np.ndarray) -> FootprintSource:
    """Footprints ``mix * model + (1 - mix) * delta * white`` per colour (``mix`` (3,)); the mixture is
    recorded as the source's ``mix`` attribute."""
    img = np.asarray(white, np.float32)
    weight = np.asarray(mix, np.float32)

    def mixed(pixels: np.ndarray) -> np.ndarray:
        out = source(pixels)
        out = out.float().cpu().numpy() if torch.is_tensor(out) else np.array(out, np.float32)
        c = out.shape[1] // 2
        out *= weight
        out[:, c, c] += (1 - weight) * np.nan_to_num(img[pixels[:, 0], pixels[:, 1]])
        return out

    mixed.mix = weight  # type: ignore[attr-defined]
    return mixed


def model_inputs(rv: RelightView) -> tuple[np.ndarray, np.ndarray]:
    """The view's PSP stack for a model backend, clipped samples repaired (:func:`psp.declip`), and the
    (H, W) bool map of pixels whose clipped fringes could not be repaired (made once per view)."""
    cached = getattr(rv, "_model_inputs", None)  # views built elsewhere (the benchmarks' SimView) have no cache yet
    if cached is None:
        if rv.saturation is None:
            cached = rv.psp, np.zeros(rv.psp.shape[1:3], bool)
        else:
            from sssphase_core.processing.psp import declip

            cached = declip(rv.psp, rv.saturation, white=rv.white, white_saturation=rv.white_saturation, black=rv.proj.black)
        rv._model_inputs = cached
    return cached


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
