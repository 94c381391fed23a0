"""Relit images against reference captures: metrics on the object mask and comparison figures.

PSNR uses a stated ``data_range`` (default 1.0: a white Lambertian reference under full white in
linear camera units). SSIM is kornia's Gaussian-window SSIM map (11 px, sigma 1.5) averaged over
the mask and the colour channels. LPIPS (``sssphase_core.learning.lpips``) is computed when its weights are on
this machine, and otherwise reported as skipped with what is missing (:func:`lpips_note`).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.learning.metrics import psnr
from sssphase_core.processing.colour import display_scale
from sssphase_core.relight.views import DECODED_SHARE_WARN
from sssphase_core.store.files import save_figure

METRICS = ("mse", "psnr", "ssim", "lpips")


def lpips_note() -> str:
    """How LPIPS was handled in this process: computed from local weights, or skipped and why."""
    from sssphase_core.learning import lpips

    ok, why = lpips.available()
    return "LPIPS: AlexNet v0.1 from local weights (lower is better)" if ok else f"LPIPS skipped: {why}"


SSIM_WINDOW = 11
SILHOUETTE_PX = 2  # the band next to the mask edge, where the camera's blur and demosaicing mix object and background


def edge_band(mask: np.ndarray, width: int = SILHOUETTE_PX) -> np.ndarray:
    """(H, W) bool: mask pixels within ``width`` px of a pixel outside the mask (the silhouette band)."""
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((2 * width + 1, 2 * width + 1), np.uint8), borderValue=0)
    return mask & ~inner.astype(bool)


def interior_psnr(relit: np.ndarray, reference: np.ndarray, mask: np.ndarray, *, data_range: float = 1.0) -> float:
    """PSNR (dB) of (H, W, 3) images on the mask less its silhouette band (:func:`edge_band`); NaN when
    nothing is left. At the silhouette a camera mixes object and background, which bounds every source
    that takes its light from captures (on the outer pixel row of the demo's crab the camera's noise-free
    image of the white differs from its render by rms 0.053); inside, the footprints decide."""
    inner = mask.astype(bool) & ~edge_band(mask)
    if not inner.any():
        return float("nan")
    diff = np.nan_to_num(relit.astype(np.float64))[inner] - np.nan_to_num(reference.astype(np.float64))[inner]
    return psnr(float(np.mean(diff ** 2)), data_range)


def relight_metrics(relit: np.ndarray, reference: np.ndarray, mask: np.ndarray, *, data_range: float = 1.0) -> dict[str, float]:
    """MSE, PSNR (dB, peak ``data_range``) and SSIM (NaN for images smaller than its 11 px window) of
    (H, W, 3) linear images on ``mask`` pixels."""
    import kornia
    import torch

    if relit.shape != reference.shape or relit.shape[:2] != mask.shape:
        raise InputError(f"relit {relit.shape}, reference {reference.shape} and mask {mask.shape} do not match")
    m = mask.astype(bool)
    if not m.any():
        raise InputError("the object mask is empty: nothing to evaluate")
    a, b = np.nan_to_num(relit.astype(np.float64)), np.nan_to_num(reference.astype(np.float64))
    mse = float(np.mean((a[m] - b[m]) ** 2))
    psnr_db = psnr(mse, data_range)
    if min(m.shape) > SSIM_WINDOW // 2:
        # only the mask's bounding box and the window's reach around it: the same SSIM at every mask pixel
        # (a window inside the crop, or the image's own border either way), a fraction of a 1080p image's cost
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        r = SSIM_WINDOW // 2
        box = (slice(max(rows[0] - r, 0), rows[-1] + r + 1), slice(max(cols[0] - r, 0), cols[-1] + r + 1))
        ta, tb = (torch.as_tensor(x[box], dtype=torch.float32).permute(2, 0, 1)[None] for x in (a, b))
        ssim_map = kornia.metrics.ssim(ta, tb, window_size=SSIM_WINDOW, max_val=data_range)[0].mean(0).numpy()
        ssim = float(ssim_map[m[box]].mean())
    else:
        ssim = float("nan")
    out = {"mse": mse, "psnr": psnr_db, "ssim": ssim, "data_range": data_range}
    from sssphase_core.learning import lpips

    if lpips.available()[0]:
        out["lpips"] = lpips.lpips_distance(a, b, m)
    return out


#: The difference panel's top, as a share of the reference's display white (its 99.5th percentile in the mask).
DIFFERENCE_SCALE = 0.2


def comparison_figure(reference: np.ndarray, relit: np.ndarray, mask: np.ndarray, path: Path | str, *, title: str = "",
                      metrics: dict[str, float] | None = None, reference_name: str = "reference (GT)") -> Path:
    """Reference | relit | |difference| (PNG); ``reference_name`` names the first panel (a simulated session's
    ground truth, or the camera's capture of the pattern). Reference and relit share one sRGB exposure; the difference panel
    is the per-pixel mean absolute error over RGB in linear camera units on the decoded pixels, with a colour bar
    up to :data:`DIFFERENCE_SCALE` of the reference's display white: every backend's figure of one view and pattern
    has the same scale (each had its own, up to its own 99.5th percentile, which hid which was worse)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sssphase_core.processing.colour import srgb

    scale = display_scale(reference, mask)
    diff = np.abs(np.nan_to_num(relit) - np.nan_to_num(reference)).mean(axis=-1)
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.2), constrained_layout=True)
    for ax, img, name in ((axes[0], reference, reference_name), (axes[1], relit, "relit")):
        ax.imshow(srgb(np.nan_to_num(img) / scale), interpolation="nearest")
        ax.set_title(name, fontsize=9)
    vmax = DIFFERENCE_SCALE * scale
    im = axes[2].imshow(np.where(mask, diff, 0.0), cmap="inferno", vmin=0, vmax=vmax, interpolation="nearest")
    axes[2].set_title("|relit - reference| on the decoded pixels", fontsize=9)
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.02, extend="max",
                 label=f"mean |error| (linear units)\nscale: {DIFFERENCE_SCALE:.0%} of its white")
    for ax in axes:
        ax.set_axis_off()
    if metrics:
        title = f"{title}  PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.3f}".strip()
    fig.suptitle(title, fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path


def evaluate_view(rv: Any, backend: str, out_dir: Path | str, *, checkpoint: Path | str | None = None,
                  chunk: int = 2048, device: str = "cpu", write: bool = True, cache: bool = False,
                  progress: Callable[[int, int], None] | None = None, precision: str = "auto",
                  **options: object) -> list[dict[str, Any]]:
    """Relight a :class:`~sssphase_core.relight.views.RelightView` under all its reference patterns in one
    pass with ``backend`` (``options`` go to the model backend); metrics per pattern (and figures /
    images under ``out_dir`` if ``write``). ``cache``: a model's footprints are kept in ``out_dir/cache`` as
    ``sss relight`` keeps them (:func:`footprint_caches`), and read back by the next evaluation of the view."""
    from sssphase_core.relight.backends import MODEL_FREE, make_sources
    from sssphase_core.relight.cache import kept, saved_if_interrupted
    from sssphase_core.relight.choices import widen_for
    from sssphase_core.relight.pipeline import relight_view

    if not rv.references:
        raise InputError(f"{rv.object} view {rv.view} has no reference captures to evaluate against "
                         "(capture with --reference checkerboard ..., or import ref__<name> frames)")
    names = sorted(rv.references)
    _warn_if_dim_white(rv)
    _warn_if_reference_off(rv, names)
    t0 = time.perf_counter()
    calibrate = bool(options.pop("calibrate", True)) and backend not in MODEL_FREE
    # relight_view's: the calibration may widen the footprints too (by default as `sss relight` does for the backend)
    asked_widen = options.pop("widen", None)  # never a backend's option (it was passed on without the calibration)
    widen = widen_for(backend, asked_widen) if calibrate else None
    sources = make_sources(backend, rv, checkpoint=checkpoint, device=device, precision=precision, **options)
    decoders = [m for m in (getattr(src, "backend", None) for src, _ in sources) if getattr(m, "name", "") == "torch"]
    caches = footprint_caches(rv, backend, sources, Path(out_dir), checkpoint) if cache and not options else []
    if caches:
        sources = [(c, k) for c, (_, k) in zip(caches, sources, strict=True)]
    (source, patch), *also = sources
    with saved_if_interrupted(caches):
        relit, mix = relight_view(source, patch, rv, [rv.references[n] for n in names], calibrate=calibrate, also=also,
                                  chunk=chunk, device=device, progress=progress, widen=widen)
    for c in caches:
        if (line := kept(c.save, c.path)) is not None:
            warnings.warn(line, UserWarning, stacklevel=2)
            break
    seconds = time.perf_counter() - t0
    kept = sum(c.kept_read for c in caches)  # footprints an earlier run kept: not predicted now (a calibration's
    read = kept / max(1, kept + sum(c.misses for c in caches))  # footprints read again by its relight are not)
    rows = []
    out = Path(out_dir)
    exposure = display_scale(rv.white) if write else None  # one display exposure per view, shared by its patterns
    for name, img in zip(names, relit, strict=True):
        capture = _captured_reference(rv, name)  # a simulated session's capture beside its noise-free render
        # A capture is compared with the relit image as the camera would record it (its Bayer sampling and
        # demosaicing, when the session says which); a render, with the relit image itself. The captured
        # transport (measured) is made of captured crops, which have been through the camera already.
        seen = img if backend == "measured" else rv.through_camera(img)
        compared = img if capture is not None else seen
        met = relight_metrics(compared, rv.captured[name], rv.proj.mask)
        _warn_if_near_black(rv, name)
        row = {"object": rv.object, "view": rv.view, "pattern": name, "backend": backend, **met,
               "psnr_interior": interior_psnr(compared, rv.captured[name], rv.proj.mask),
               "seconds": seconds / len(names), "lit_pixels": int(rv.proj.mask.sum()),
               "decoded_share": round(rv.decoded_share, 4)}
        if decoders:  # the decoder's inference: float32, or bf16 (--precision)
            row["precision"] = decoders[0].precision
        if caches:  # its seconds are the model's run time only for the footprints it predicted now
            row["footprints_from_cache"] = round(read, 4)
        if mix is not None:  # a model calibrated to the view: its weight against no scattering, per colour
            row["mix"] = np.asarray(mix, float).round(4).tolist()  # (3,), or (members, 3) for a blend
        if getattr(source, "fit", None):  # the captured transport's noise mask, chosen on the view's fringe captures
            row["denoise_smoothing"] = source.smoothing  # type: ignore[attr-defined]
            row["denoise_fit_psnr"] = {str(k): round(v, 3) for k, v in source.fit.items()}  # type: ignore[attr-defined]
        if capture is not None:  # a simulated session is scored against its noise-free render and its capture
            cap = relight_metrics(seen, capture, rv.proj.mask)
            row.update({"psnr_capture": cap["psnr"], "ssim_capture": cap["ssim"]})
            # ... and against what the camera records of the render without its noise
            row["psnr_camera"] = relight_metrics(seen, rv.camera_image(name), rv.proj.mask)["psnr"]
        if write:
            stem = out / f"{rv.object}_v{rv.view}_{name}_{backend}"
            from sssphase_core.relight.images import write_images

            write_images(stem, img, scale=exposure)
            row["figure"] = str(comparison_figure(rv.captured[name], img, rv.proj.mask, stem.with_name(stem.name + "_compare.png"),
                                                  title=f"{rv.object} view {rv.view}, {name}, {backend}", metrics=met,
                                                  reference_name=rv.reference_name))
        rows.append(row)
    return rows


def footprint_caches(rv: Any, backend: str, sources: Sequence[tuple[Any, int]], out: Path,
                     checkpoint: Path | str | None) -> list[Any]:
    """Each of a model backend's (uncalibrated) sources in a :class:`~sssphase_core.relight.cache.FootprintCache`
    at ``out/cache`` (named as ``sss relight`` names them; started from the checkpoint run's check, where it
    relit this view: :func:`~sssphase_core.relight.cache.seed_cache`); [] for data sources and where the view's
    footprints would not fit the cache's memory budget."""
    from sssphase_core.relight.cache import CACHE_BYTES, footprint_bytes, view_caches
    from sssphase_core.relight.choices import BLENDS, MODEL_FREE

    if backend in MODEL_FREE or getattr(rv, "session", None) is None:
        return []
    if footprint_bytes(int(rv.proj.mask.sum()), max(k for _, k in sources)) > CACHE_BYTES:
        return []
    return view_caches(out, rv, list(sources), BLENDS.get(backend, (backend,)), checkpoint)


def _captured_reference(rv: Any, name: str) -> np.ndarray | None:
    """The camera's capture ``ref/<name>`` of a view scored against a noise-free render (else None)."""
    session = getattr(rv, "session", None)
    if session is None or rv.sim is None or f"ref/{name}" not in session.arrays(rv.view):
        return None
    from sssphase_core.errors import DataError

    image = np.asarray(session.load(rv.view, f"ref/{name}"), np.float32)
    if image.shape != rv.white.shape:
        raise DataError(f"view {rv.view} of {session.path}: ref/{name} is {'x'.join(map(str, image.shape))} where the "
                        f"view's white image is {'x'.join(map(str, rv.white.shape))}: the view's arrays do not belong together")
    from sssphase_core.relight.views import _check_finite

    # NaN scored as 0 read 23.1 dB where the intact capture reads 33.5
    _check_finite(f"view {rv.view} of {session.path}", rv.proj.mask, {}, {f"ref/{name}": image})
    return image


def aggregate(rows: Sequence[dict[str, Any]], by: Sequence[str] = ("backend", "pattern")) -> list[dict[str, Any]]:
    """Mean of the metrics and run times over the rows sharing the ``by`` keys (objects and views)."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in by), []).append(r)
    out = []
    for key, rs in groups.items():
        agg = {k: v for k, v in zip(by, key, strict=True)}
        agg.update({m: float(np.mean([r[m] for r in rs])) for m in (*METRICS, "seconds", "psnr_interior", "psnr_capture", "psnr_camera")
                    if all(m in r for r in rs)})
        agg["n"] = len(rs)
        out.append(agg)
    return out


#: A reference capture whose mean on the decoded pixels is below this share of the white capture's is near black:
#: its PSNR (peak 1.0) is high whatever is relit (a black reference scored "none" 91.5 dB).
NEAR_BLACK_SHARE = 0.02


def _warn_if_near_black(rv: Any, name: str) -> None:
    """Warn when the reference ``name`` of view ``rv`` is near black (:data:`NEAR_BLACK_SHARE` of its white)."""
    mask = rv.proj.mask
    white = float(np.mean(rv.white[mask])) if mask.any() else 0.0
    share = float(np.mean(rv.captured[name][mask])) / white if white > 0 else 0.0
    if share < NEAR_BLACK_SHARE:
        warnings.warn(f"{rv.object} view {rv.view}, reference {name}: near black ({share:.2%} of the white capture on "
                      "the decoded pixels): its PSNR (peak 1.0) is high whatever is relit; score on a pattern that "
                      "lights the object", UserWarning, stacklevel=3)


#: A view whose white (99.9th percentile on the decoded pixels) is below this level is scored far from white = 1.
DIM_WHITE_LEVEL = 0.25


def _warn_if_dim_white(rv: Any) -> None:
    """Warn when view ``rv``'s white is far below the PSNR's peak of 1 (:data:`DIM_WHITE_LEVEL`): its scores read
    ``20 log10(1 / level)`` dB higher than the same relighting of frames at full range."""
    mask = rv.proj.mask
    level = float(np.percentile(np.asarray(rv.white)[mask], 99.9)) if mask.any() else 0.0
    if 0 < level < DIM_WHITE_LEVEL:
        warnings.warn(f"{rv.object} view {rv.view}: its white's level is {level:.3g} where the PSNR's peak is 1.0, so its "
                      f"scores read {20 * np.log10(1 / level):.0f} dB higher than at full range (16-bit files of a 10-, "
                      "12- or 14-bit camera: import them with --bit-depth; else the camera was exposed far below its "
                      "range)", UserWarning, stacklevel=3)


def _warn_if_reference_off(rv: Any, names: Sequence[str]) -> None:
    """Warn of the references the view's import measured at another brightness than its white and pattern give
    (``reference_brightness`` outside :data:`~sssphase_core.capture.importer.REFERENCE_BRIGHTNESS`): every backend's
    score against them measures that, not relighting (one at 1.98x scored 11.6 dB, said only at the import)."""
    from sssphase_core.capture.importer import REFERENCE_BRIGHTNESS

    views = getattr(rv.session, "manifest", {}).get("views", {})
    bright = views.get(str(rv.view), {}).get("reference_brightness") or {}
    off = {n: b for n, b in bright.items() if n in names and isinstance(b, (int, float))
           and not REFERENCE_BRIGHTNESS[0] <= b <= REFERENCE_BRIGHTNESS[1]}
    if off:
        warnings.warn(f"{rv.object} view {rv.view}: the reference capture{'s' if len(off) > 1 else ''} "
                      f"{', '.join(f'{n} ({b:.2f}x)' for n, b in off.items())} hold{'' if len(off) > 1 else 's'} another "
                      "amount of light than the white and the pattern give (as its import said): every backend's score "
                      "against it measures that, not the relighting; re-capture it at the white's exposure",
                      UserWarning, stacklevel=3)


def metrics_table(rows: Sequence[dict[str, Any]], by: Sequence[str] = ("backend", "pattern"), title: str = "Relighting"):
    """A :class:`sssphase_core.tables.Table` of :func:`aggregate` (LPIPS noted as skipped)."""
    from sssphase_core.tables import Table

    agg = aggregate(rows, by)
    both = all("psnr_capture" in a for a in agg)
    with_lpips = bool(agg) and all("lpips" in a for a in agg)
    camera = both and all("psnr_camera" in a for a in agg)
    interior = bool(agg) and all("psnr_interior" in a for a in agg)
    cols = [*by, "PSNR (dB)", *([f"PSNR >= {SILHOUETTE_PX} px inside (dB)"] if interior else []),
            *(["PSNR vs capture (dB)"] if both else []), *(["PSNR vs camera, no noise (dB)"] if camera else []),
            "SSIM", *(["LPIPS"] if with_lpips else []), "MSE", "time (s)", "n"]
    body = [[*(a[k] for k in by), a["psnr"], *([a["psnr_interior"]] if interior else []), *([a["psnr_capture"]] if both else []),
             *([a["psnr_camera"]] if camera else []),
             a["ssim"], *([a["lpips"]] if with_lpips else []), a["mse"], a["seconds"], a["n"]] for a in agg]
    note = ("Mean over objects and views; PSNR peak 1.0 (linear camera units), on the decoded mask (every pixel whose "
            "fringes decoded: the object and any background the projector lights; a view where less than "
            f"{DECODED_SHARE_WARN:.0%} of the lit pixels decoded is warned of)"
            + (f" ('inside': less the {SILHOUETTE_PX} px next to the silhouette, where the camera mixes object and "
               "background)" if interior else "")
            + ("; simulated sessions are scored against the noise-free render and, in 'vs capture', against the "
               "camera's own noisy capture of the pattern" if both else "")
            + ("; a relit image is compared with a capture as the camera would record it (its Bayer sampling and "
               "demosaicing, where the session records them)")
            + ("; 'vs camera, no noise': against the render seen through the camera's Bayer sampling and "
               "demosaicing without its noise (what relighting from captured data can reach)" if camera else "") + f". {lpips_note()}.")
    return Table(title, cols, body, note=note)


BASELINES = ("none", "analytic")


def training_overlap(checkpoint: Path | str, views: Sequence[tuple[str, int]], *, held_out: bool = True) -> str | None:
    """The note for an evaluation of ``views`` ((object, view)) with decoder ``checkpoint`` that scores views it was
    trained on (and, with ``held_out``, other views of its training objects); None when it scores only unseen
    objects (or the checkpoint predates the record)."""
    from sssphase_core.learning.training.checkpoints import trained_views

    trained, views = trained_views(checkpoint), sorted(set(views))
    fitted = [f"{o} view {v}" for o, v in views if v in trained.get(o, ())]
    others = [f"{o} view {v}" for o, v in views if held_out and o in trained and v not in trained[o]]
    if not fitted and not others:
        return None
    parts = []
    if fitted:
        parts.append(f"the decoder was trained on {', '.join(fitted)}: the torch and blend figures there measure how "
                     "it fits what it saw, not relighting of unseen data")
    if others:
        parts.append(f"{', '.join(others)} {'is another view' if len(others) == 1 else 'are other views'} of its "
                     "training objects, not unseen objects")
    return "note: " + "; ".join(parts)


def baseline_check(sessions: Sequence[Any], checkpoint: Path | str, out_dir: Path | str, *,
                   views: Sequence[int] | None = None, max_views: int = 2, device: str = "cpu") -> dict[str, Any]:
    """Relight views with reference captures by the trained model and by the ``none`` and ``analytic``
    baselines: ``{"rows": per object/view/pattern/backend metrics, "mean_psnr": {backend: dB},
    "losing_to": [baselines the model is below], "views": [(object, view)]}``.

    ``views`` restricts the views of each session (e.g. held-out ones); at most ``max_views`` views are
    relit in all. Sessions without reference captures give an empty result (``views == []``).
    """
    from sssphase_core.learning.runlog import resolve_checkpoint
    from sssphase_core.relight.views import load_view

    checkpoint = resolve_checkpoint(checkpoint)  # the file, as `sss eval relight` names it: their caches share names
    picked = []
    for session in sessions:
        for v in session.views():
            if (views is None or v in views) and len(picked) < max_views:
                if any(a.startswith("ref/") or a.startswith("gt/render/") for a in session.arrays(v)):
                    picked.append((session, v))
    rows: list[dict[str, Any]] = []
    for session, v in picked:
        rv = load_view(session, v)
        if not rv.references:
            continue
        for backend in ("torch", *BASELINES):  # footprints cached: `sss eval relight` of this run reads them
            rows += evaluate_view(rv, backend, out_dir, checkpoint=checkpoint if backend == "torch" else None,
                                  device=device, write=False, cache=True)
    mean = {b: float(np.mean([r["psnr"] for r in rows if r["backend"] == b])) for b in ("torch", *BASELINES)} if rows else {}
    losing = [b for b in BASELINES if mean and mean["torch"] < mean[b]]
    return {"rows": rows, "mean_psnr": mean, "losing_to": losing,
            "views": sorted({(r["object"], r["view"]) for r in rows})}


def footprints_at(rv: Any, pixels: np.ndarray, backends: Sequence[str], *, checkpoint: Path | str | None = None,
                  device: str = "cpu") -> dict[str, np.ndarray]:
    """Each backend's footprints at camera ``pixels`` (N, 2) yx of a view -> {backend: (N, K, K, 3)},
    all centre-cropped or zero-padded to the largest K among them (``captured``: the session's own crops)."""
    from sssphase_core.relight.backends import make_source
    from sssphase_core.relight.engine import footprint_array

    out: dict[str, np.ndarray] = {}
    for name in backends:
        if name == "captured":
            px = np.asarray(rv.session.load(rv.view, "footprints/pixels"), np.int64)
            index = {tuple(p): i for i, p in enumerate(px)}
            missing = [tuple(p) for p in pixels if tuple(p) not in index]
            if missing:
                raise InputError(f"no captured footprint at pixel(s) {missing[:3]}")
            crops = rv.session.read(rv.view, "footprints/crops")
            out[name] = np.stack([np.asarray(crops[index[tuple(p)]], np.float32) for p in pixels])
        else:
            source, _ = make_source(name, rv, checkpoint=checkpoint, device=device, calibrate=False)  # the model's own
            fps = source(np.asarray(pixels, np.int64))
            out[name] = footprint_array(fps)
    k = max(f.shape[1] for f in out.values())
    for name, f in out.items():
        pad = (k - f.shape[1]) // 2
        out[name] = np.pad(f, ((0, 0), (pad, k - f.shape[1] - pad), (pad, k - f.shape[1] - pad), (0, 0)))
    return out
