"""`sss bench gap`: what separates a model's relighting from the exact footprints' (issue 16 §3).

On simulated test sessions (the simulator's exact footprints are the reference; evaluation only), each
lit pixel's model footprint M and exact footprint E are computed once, and hybrids swap one property
at a time:

* ``energy``: E's shape with M's per-colour energy -> the error the energy alone causes;
* ``shape``: M's shape with E's energy -> the error of the shape (profile and angular detail);
* ``centre``: E with M's fraction of the energy on the entry pixel (the rest of E rescaled to keep
  E's energy) -> the error of the centre (direct reflection and the profile's peak);
* ``angular``: E averaged over rings around the entry pixel -> what the anisotropy is worth;
* ``silhouette``: the model's own error split into the pixels within 2 px of the mask's edge and the rest;
* ``white``: E's shape with the captured white's value as its energy (reciprocity): what exact shapes reach
  with the energy a capture gives, beside the white capture's own accuracy against the white that the
  exact footprints relight (noise-free, before the camera) -> how far captured light can take any model.

Errors are MSE against the noise-free render of each reference pattern on the object mask; a hybrid's
*share* is (MSE(hybrid) - MSE(exact)) / (MSE(model) - MSE(exact)). Shares need not add to 1 (the terms
interact), but the largest one says what to attack first.

The model's footprints are calibrated as footprints (``calibrate``: mixed with no scattering by the view-wide weight,
:func:`~sssphase_core.relight.make_source`), not as ``sss relight`` calibrates its images (the widened members, the
per-pixel weights and the white-consistent gain of :func:`~sssphase_core.relight.pipeline.relight_view`): each
hybrid needs one footprint per pixel.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.bench.output import Table, machine_info, write_bench_report
from sssphase_core.bench.relight_bench import InMemorySource
from sssphase_core.learning.metrics import psnr
from sssphase_core.relight.evaluation import SILHOUETTE_PX, edge_band

HYBRIDS = ("energy", "shape", "centre", "angular")


def ring_average(fps: np.ndarray) -> np.ndarray:
    """(N, K, K, 3) -> the same with each ring of integer radius around the centre replaced by its mean."""
    k = fps.shape[1]
    d = np.arange(k) - k // 2
    ring = np.rint(np.hypot(*np.meshgrid(d, d, indexing="ij"))).astype(int).ravel()
    member = np.eye(ring.max() + 1, dtype=np.float32)[ring]  # (K*K, R) one-hot
    average = member @ (member / member.sum(axis=0)).T  # (K*K, K*K): each pixel -> its ring's mean
    flat = fps.reshape(len(fps), k * k, 3)
    return np.einsum("pq,nqc->npc", average, flat, optimize=True).reshape(fps.shape).astype(np.float32)


def hybrid(name: str, model: np.ndarray, exact: np.ndarray, white: np.ndarray | None = None) -> np.ndarray:
    """(N, K, K, 3) footprints of hybrid ``name`` (see the module docstring) from model and exact ones;
    ``white`` (N, 3): the captured white at each footprint's pixel (hybrid ``white`` only)."""
    em, ee = model.sum(axis=(1, 2), keepdims=True), exact.sum(axis=(1, 2), keepdims=True)
    safe = lambda e: np.where(np.abs(e) > 1e-12, e, 1.0)  # noqa: E731
    if name == "white":
        if white is None:
            raise ValueError("the white hybrid needs the captured white at each pixel")
        return exact / safe(ee) * np.asarray(white, np.float32)[:, None, None, :]
    if name == "energy":
        return exact / safe(ee) * em
    if name == "shape":
        return model / safe(em) * ee
    if name == "centre":
        c = model.shape[1] // 2
        frac = model[:, c : c + 1, c : c + 1] / safe(em)  # (N, 1, 1, 3)
        out = exact.copy()
        centre = exact[:, c : c + 1, c : c + 1]
        rest = ee - centre
        out *= (ee * (1 - frac)) / np.where(np.abs(rest) > 1e-12, rest, 1.0)
        out[:, c : c + 1, c : c + 1] = ee * frac
        return out
    if name == "angular":
        return ring_average(exact)
    raise ValueError(name)


def _lookup(fps: np.ndarray, like: InMemorySource) -> Callable[[np.ndarray], np.ndarray]:
    """A footprint source returning rows of ``fps`` (N, K, K, 3) for the pixels ``like`` holds, in its order."""
    return lambda px: fps[like.slot[px[:, 0] * like.width + px[:, 1]]]


def decompose(rv: Any, backend: str, checkpoint: Path | str | None, calibrate: bool = True) -> list[dict[str, Any]]:
    """Rows (one per reference pattern) of MSE/PSNR for none, the model, exact and each hybrid of one view."""
    from sssphase_core.relight import emitted_light, lit_pixels, make_source, relight

    names = sorted(rv.references)
    if not names:  # was "internal error: need at least one array to stack"
        from sssphase_core.errors import InputError

        raise InputError(f"{rv.object} view {rv.view} has no reference captures to compare relit images with: capture "
                         "it with --reference checkerboard (the gap bench needs simulated sessions with references)")
    pats = [rv.references[n] for n in names]
    pixels, _ = lit_pixels(rv.proj, emitted_light(np.stack(pats), rv.proj.gamma))
    model_src, k = make_source(backend, rv, checkpoint=checkpoint, calibrate=calibrate)
    exact_src, ke = make_source("exact", rv)
    if ke != k:
        from sssphase_core.errors import InputError

        raise InputError(f"the {backend} footprints are {k}x{k} and the exact ones {ke}x{ke}: compare at one size")
    model, exact = InMemorySource(model_src, pixels, rv.proj.shape), InMemorySource(exact_src, pixels, rv.proj.shape)
    none_src, _ = make_source("none", rv)
    pad = ((0, 0), (k // 2, k - 1 - k // 2), (k // 2, k - 1 - k // 2), (0, 0))  # a delta at the centre of K x K
    sources: dict[str, Callable] = {"none": lambda p: np.pad(none_src(p), pad), backend: model, "exact": exact}
    for h in HYBRIDS:
        sources[h] = _lookup(hybrid(h, model.fps, exact.fps), model)
    sources["white"] = _lookup(hybrid("white", model.fps, exact.fps, rv.white[pixels[:, 0], pixels[:, 1]]), model)
    mask, band = rv.proj.mask, edge_band(rv.proj.mask)
    inside = mask & ~band
    relit = {name: relight(src, rv.proj, pats, k, white=rv.white) for name, src in sources.items()}
    # the white capture against the white the exact footprints relight (noise-free, before the camera)
    flat = np.ones((rv.proj.projector_size[1], rv.proj.projector_size[0]), np.float32)
    true_white = relight(exact_src, rv.proj, [flat], k)[0] / np.float32(1.0 - rv.proj.black)  # light 1, black included
    white_err = (np.asarray(rv.white, np.float32) - true_white) ** 2
    white_capture = {"psnr_white_capture": psnr(float(white_err[mask].mean())),
                     "psnr_inside_white_capture": psnr(float(white_err[inside].mean())) if inside.any() else float("nan")}
    rows = []
    for i, pat in enumerate(names):
        ref = rv.captured[pat]
        mse = {name: float(np.mean((img[i][mask] - ref[mask]) ** 2)) for name, img in relit.items()}
        mse_in = {name: float(np.mean((img[i][inside] - ref[inside]) ** 2)) for name, img in relit.items()} if inside.any() else {}
        gap = mse[backend] - mse["exact"]
        err = ((relit[backend][i] - ref) ** 2).mean(axis=-1)
        row = {"object": rv.object, "view": rv.view, "pattern": pat, "backend": backend, "lit_pixels": len(pixels),
               **{f"psnr_{n}": psnr(m) for n, m in mse.items()}, **{f"mse_{n}": m for n, m in mse.items()},
               **{f"psnr_inside_{n}": psnr(m) for n, m in mse_in.items()},
               **{f"share_{h}": (mse[h] - mse["exact"]) / gap if gap > 0 else float("nan") for h in HYBRIDS},
               **white_capture, "edge_fraction_of_pixels": float(band.sum() / mask.sum()),
               "share_silhouette": float(err[band].sum() / err[mask].sum()) if err[mask].sum() > 0 else float("nan")}
        rows.append(row)
    return rows


def run(sessions: Sequence[Any], out: Path, *, checkpoint: Path | str | None, backend: str = "torch",
        views: Sequence[int] | None = None, calibrate: bool = True,
        progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """:func:`decompose` over simulated sessions' views; writes ``out`` (JSON) and ``out.md``."""
    from sssphase_core.errors import InputError
    from sssphase_core.relight import load_view

    rows: list[dict[str, Any]] = []
    for s in sessions:
        for v in (views if views is not None else s.views()):
            rv = load_view(s, v)
            if rv.sim is None:
                raise InputError(f"{s.path}: the gap to exact footprints needs a simulated session (exact footprints)")
            if progress:
                progress(f"{rv.object} view {v}: {backend} and exact footprints, {len(HYBRIDS)} hybrids")
            rows += decompose(rv, backend, checkpoint, calibrate)
    if not rows:
        raise InputError("no view to decompose: give sessions with a reference pattern")
    fmt = lambda x: f"{100 * x:.0f}%" if np.isfinite(x) else "-"  # noqa: E731
    table = Table(f"Relit PSNR (dB) against the noise-free render, and each property's share of the {backend}-exact gap",
                  ["object", "pattern", "none", backend, "exact", *(f"{h} (dB / share)" for h in HYBRIDS),
                   "silhouette share (px share)"],
                  [[r["object"], r["pattern"], r["psnr_none"], r[f"psnr_{backend}"], r["psnr_exact"],
                    *(f"{r[f'psnr_{h}']:.1f} / {fmt(r[f'share_{h}'])}" for h in HYBRIDS),
                    f"{fmt(r['share_silhouette'])} ({fmt(r['edge_fraction_of_pixels'])})"] for r in rows],
                  note="energy: exact shape, model energy; shape: model shape, exact energy; centre: exact with the "
                       "model's centre fraction; angular: exact averaged over rings; silhouette: the model's squared "
                       f"error within {SILHOUETTE_PX} px of the mask edge over all of it (in brackets: those pixels' share).")
    names = ["none", backend, "exact", *HYBRIDS]
    inside = Table(f"Relit PSNR (dB) against the noise-free render away from the silhouette (the mask less its "
                   f"{SILHOUETTE_PX} px edge band)", ["object", "pattern", *names],
                   [[r["object"], r["pattern"], *(r.get(f"psnr_inside_{n}", float("nan")) for n in names)] for r in rows],
                   note="The same relit images as above; the hybrids as above. At the silhouette the camera mixes object "
                        "and background in every capture, which bounds every source that takes its light from captures.")
    def share(r: dict[str, Any], top: float) -> float:  # the backend's share of the way from none to ``top`` (dB)
        return (r[f"psnr_{backend}"] - r["psnr_none"]) / (top - r["psnr_none"]) if top > r["psnr_none"] else float("nan")

    bound = Table("What captured light allows: the white capture, and exact shapes with its energy (PSNR, dB, whole "
                  "mask / inside)", ["object", "pattern", "white capture", "exact shapes, white's energy",
                                     f"{backend}'s share of none -> exact", f"{backend}'s share of none -> exact shapes, "
                                     "white's energy"],
                  [[r["object"], r["pattern"], f"{r['psnr_white_capture']:.1f} / {r['psnr_inside_white_capture']:.1f}",
                    f"{r['psnr_white']:.1f} / {r.get('psnr_inside_white', float('nan')):.1f}",
                    fmt(share(r, r["psnr_exact"])), fmt(share(r, r["psnr_white"]))] for r in rows],
                  note="white capture: the view's white image against the white that the exact footprints relight "
                       "(noise-free, before the camera's Bayer sampling and demosaicing); exact shapes, white's energy: "
                       "each exact footprint rescaled to the captured white at its pixel (the energy by reciprocity, "
                       "as every source that reads its light from captures has it), relit against the render.")
    result = {"machine": machine_info(), "backend": backend, "checkpoint": str(checkpoint), "calibrated": calibrate, "rows": rows}
    write_bench_report(result, [table, inside, bound], Path(out), md=Path(out).with_suffix(".md"), title="The gap to exact footprints")
    return result
