"""A decoder's and the analytic model's footprints against a volumetric stand-in's true ones, pixel by pixel.

    python benchmarks/standin_footprints.py shapes RENDERS SESSIONS NAME MATERIAL MM_PER_PX CHECKPOINT [PIXELS]
    python benchmarks/standin_footprints.py relit RENDERS SESSIONS NAME MATERIAL MM_PER_PX CHECKPOINT

RENDERS, NAME, MATERIAL, MM_PER_PX: as given to ``standin_volumetric.py`` (its cached kernels and
``NAME_geometry.npz`` are read: evaluation only); SESSIONS: where ``sss import`` put the session;
CHECKPOINT: a decoder (``sss train decoder``'s run folder).

``shapes``: on PIXELS (default 300) seeded pixels at least 10 px inside the decoded mask, prints per colour, for the truth (the stand-in's kernel at the pixel's
incidence angle, turned along its azimuth), the torch backend (as ``sss relight`` runs it, and its decoder
alone, ``guard=False``) and the analytic model:

- each ring's share of the footprint's energy (px from the centre) and the energy over the truth's;
- the relative L2 error of each pixel's footprint shape (energy matched), and of one view-mean shape;
- the spread of the per-pixel shapes (their variance over the truth's) and the correlation of their first
  principal component with the pixel's incidence angle;
- the modulation each footprint gives the finest fringes (period 11 projector px, in camera px by the
  decoded map's local density) over the truth's: below 1, the footprint is wider than the truth for the
  fringes that the view calibration fits on.

``relit``: relit PSNR (dB, whole mask / >= 2 px inside) against the render's noise-free references, every source
calibrated to the view as ``sss relight`` does (:func:`~sssphase_core.relight.pipeline.relight_view`; the decoder
widened by its default), of: the true footprints (each pixel's kernel times the texture its light enters through,
in the session's units) placed at the decoded points; the same re-centred on their centroid (the decoded point
already carries a leaning footprint's shift); the decoder; the decoder's shapes with the true energies and the true
shapes with the decoder's energies; the analytic model.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from standin_volumetric import RADIUS, kernels, per_pixel_kernels  # noqa: E402

RINGS = (0, 0.5, 1.5, 2.5, 3.5, 5.5, 8.5, 12.5, 30)
FRINGE_PERIOD = 11.0  # the finest PSP period of the stand-ins' capture plan (projector px)


def ring_shares(fp: np.ndarray) -> np.ndarray:
    """(N, K, K, 3) footprints -> (N, len(RINGS) - 1, 3) energy shares by distance from the centre pixel."""
    off = np.arange(fp.shape[1]) - fp.shape[1] // 2
    r = np.hypot(off[:, None], off[None, :])
    parts = [(fp * ((r >= lo) & (r < hi))[None, :, :, None]).sum(axis=(1, 2)) for lo, hi in itertools.pairwise(RINGS)]
    return np.stack(parts, 1) / fp.sum(axis=(1, 2))[:, None, :]


def shape_error(fp: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N, 3) relative L2 error of each footprint's shape (scaled to the truth's energy)."""
    g = fp / fp.sum(axis=(1, 2), keepdims=True) * truth.sum(axis=(1, 2), keepdims=True)
    return np.sqrt(((g - truth) ** 2).sum(axis=(1, 2)) / (truth**2).sum(axis=(1, 2)))


def modulation(fp: np.ndarray, period_x: np.ndarray, period_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) each footprint's modulation of fringes of ``period_x`` / ``period_y`` (N,) camera px."""
    off = np.arange(fp.shape[1]) - fp.shape[1] // 2
    e = fp.sum(axis=(1, 2))
    fx = np.exp(-2j * np.pi * off[None, :] / period_x[:, None])
    fy = np.exp(-2j * np.pi * off[None, :] / period_y[:, None])
    mx = np.abs(np.einsum("nyxc,nx->nc", fp.astype(np.complex128), fx)) / e
    my = np.abs(np.einsum("nyxc,ny->nc", fp.astype(np.complex128), fy)) / e
    return mx, my


def main(renders: Path, sessions: Path, name: str, material: str, mm_per_px: float, checkpoint: str, n: int = 300) -> None:
    from sssphase_core.learning.backends.analytic_backend import AnalyticBackend
    from sssphase_core.learning.backends.torch_backend import TorchBackend
    from sssphase_core.relight import load_view
    from sssphase_core.store.session import find_sessions

    session = next(s for s in find_sessions([sessions]) if s.name == name)
    rv = load_view(session, 0)
    geo = np.load(renders / f"{name}_geometry.npz")
    lit = np.isfinite(geo["theta"]) & rv.proj.mask
    deep = cv2.erode(lit.astype(np.uint8), np.ones((21, 21), np.uint8)).astype(bool)
    pix = np.argwhere(deep)
    pix = pix[np.random.default_rng(0).choice(len(pix), min(n, len(pix)), replace=False)]
    theta = geo["theta"][pix[:, 0], pix[:, 1]]
    truth = per_pixel_kernels(kernels(renders, material, mm_per_px, 0.0), theta, geo["azimuth"][pix[:, 0], pix[:, 1]])
    truth = np.pad(truth.transpose(0, 2, 3, 1), ((0, 0), (1, 0), (1, 0), (0, 0)))  # (N, 32, 32, 3): centre at 16
    query = (rv.psp, pix)
    models = {"torch": TorchBackend(checkpoint).predict_footprints(query),
              "decoder alone": TorchBackend(checkpoint, guard=False).predict_footprints(query),
              "analytic": AnalyticBackend(patch=32).predict_footprints(query)}
    if next(iter(models.values())).shape[1] != 2 * RADIUS + 2:
        sys.exit(f"{checkpoint}: a decoder of {2 * RADIUS + 2} px footprints is compared here (the stand-ins' kernels)")
    gy, gx = np.gradient(rv.proj.xp.astype(np.float64))
    hy, hx = np.gradient(rv.proj.yp.astype(np.float64))
    period_x = FRINGE_PERIOD / np.hypot(gx, gy)[pix[:, 0], pix[:, 1]]
    period_y = FRINGE_PERIOD / np.hypot(hx, hy)[pix[:, 0], pix[:, 1]]
    tx, ty = modulation(truth, period_x, period_y)
    t_norm = (truth / truth.sum(axis=(1, 2), keepdims=True)).reshape(len(truth), -1, 3)
    t_var = ((t_norm - t_norm.mean(0)) ** 2).sum(axis=1).mean(0)
    print(f"{name}: {len(pix)} pixels >= 10 px inside; rings (px) {RINGS}")
    for c, colour in enumerate("RGB"):
        print(f" {colour} {'truth':14s}" + " ".join(f"{v:.3f}" for v in ring_shares(truth)[:, :, c].mean(0)))
        for label, fp in models.items():
            energy = np.median(fp.sum(axis=(1, 2))[:, c] / truth.sum(axis=(1, 2))[:, c])
            print(f" {colour} {label:14s}" + " ".join(f"{v:.3f}" for v in ring_shares(fp)[:, :, c].mean(0))
                  + f"   energy / truth {energy:.3f}")
    print(" shape error per pixel | of one view-mean shape | per-pixel variance / truth's | corr(PC1, incidence) "
          "| fringe modulation / truth's along x, y (R G B, medians)")
    for label, fp in models.items():
        g = (fp / fp.sum(axis=(1, 2), keepdims=True)).reshape(len(fp), -1, 3)
        mean_shape = np.broadcast_to(g.mean(0), g.shape).reshape(fp.shape)
        var = ((g - g.mean(0)) ** 2).sum(axis=1).mean(0)
        x = g[..., 0] - g[..., 0].mean(0)
        u, s, _ = np.linalg.svd(x, full_matrices=False)
        corr = abs(np.corrcoef(u[:, 0] * s[0], theta)[0, 1])
        mx, my = modulation(fp, period_x, period_y)
        print(f"  {label:14s} {np.median(shape_error(fp, truth), 0).round(3)} | {np.median(shape_error(mean_shape, truth), 0).round(3)}"
              f" | {(var / t_var).round(1)} | {corr:.2f} | {np.median(mx / tx, 0).round(3)} {np.median(my / ty, 0).round(3)}")


def shifted_to_centroid(fp: np.ndarray) -> np.ndarray:
    """(N, K, K, 3) footprints moved (:func:`~sssphase_core.learning.camera.shift_subpixel`, colours together) so
    that their centroid is the centre pixel K // 2, each colour's energy kept."""
    import torch

    from sssphase_core.learning.camera import shift_subpixel

    off = np.arange(fp.shape[1]) - fp.shape[1] // 2
    w = fp.sum(-1)
    total = np.where(w.sum((1, 2)) > 0, w.sum((1, 2)), 1.0)
    centroid = np.stack([(w * off[None, :, None]).sum((1, 2)), (w * off[None, None, :]).sum((1, 2))], 1) / total[:, None]
    x = torch.from_numpy(np.ascontiguousarray(fp.transpose(0, 3, 1, 2), np.float32))
    out = shift_subpixel(x, -centroid).numpy().transpose(0, 2, 3, 1)
    now = out.sum(axis=(1, 2), keepdims=True)
    return (out * np.where(now > 0, fp.sum(axis=(1, 2), keepdims=True) / np.where(now > 0, now, 1.0), 1.0)).astype(np.float32)


def relit(renders: Path, sessions: Path, name: str, material: str, mm_per_px: float, checkpoint: str) -> None:
    from standin_score import session_scale

    from sssphase_core.bench.gap_bench import hybrid
    from sssphase_core.processing.patterns import reference_pattern
    from sssphase_core.relight import load_view, make_source
    from sssphase_core.relight.choices import DECODER_WIDEN
    from sssphase_core.relight.pipeline import relight_view
    from sssphase_core.store.exr import read_exr
    from sssphase_core.store.session import find_sessions

    session = next(s for s in find_sessions([sessions]) if s.name == name)
    rv, scale = load_view(session, 0), session_scale(session)
    geo = np.load(renders / f"{name}_geometry.npz")
    if "texture" not in geo.files:
        sys.exit(f"{renders / name}_geometry.npz holds no texture: render it again with this version of standin_volumetric.py")
    table, theta, azimuth, texture = kernels(renders, material, mm_per_px, 0.0), geo["theta"], geo["azimuth"], geo["texture"]
    k = 2 * RADIUS + 2

    def truth(pixels: np.ndarray) -> np.ndarray:
        out = np.zeros((len(pixels), k, k, 3), np.float32)
        ok = np.isfinite(theta[pixels[:, 0], pixels[:, 1]])
        if ok.any():
            y, x = pixels[ok, 0], pixels[ok, 1]
            kern = per_pixel_kernels(table, theta[y, x], azimuth[y, x]).transpose(0, 2, 3, 1)
            out[ok, 1:, 1:] = kern * texture[y, x][:, None, None, :] * scale
        return out

    decoder = make_source("torch", rv, checkpoint=checkpoint, calibrate=False)[0]
    sources = {"true footprints": (truth, None), "true, re-centred": (lambda p: shifted_to_centroid(truth(p)), None),
               "torch": (decoder, DECODER_WIDEN),
               "torch shapes, true energy": (lambda p: hybrid("shape", np.asarray(decoder(p)), truth(p)), DECODER_WIDEN),
               "true shapes, torch energy": (lambda p: hybrid("energy", np.asarray(decoder(p)), truth(p)), None),
               "analytic": (make_source("analytic", rv, calibrate=False)[0], None)}
    names = ("checkerboard", "stripes_x")
    wp, hp = rv.proj.projector_size
    refs = [read_exr(renders / f"{name}_clean_ref__{n}.exr") * scale for n in names]
    mask = rv.proj.mask
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    print(f"{name}: relit as sss relight calibrates, PSNR whole mask / >= 2 px inside, {' | '.join(names)}")
    for label, (source, widen) in sources.items():
        images, _ = relight_view(source, k, rv, [reference_pattern(n, wp, hp) for n in names], calibrate=True, widen=widen)
        cells = [f"{10 * np.log10(1 / np.mean((im[m] - r[m]) ** 2)):.2f}" for im, r in zip(images, refs, strict=True)
                 for m in (mask, inner)]
        print(f"  {label:26s} " + " | ".join(f"{cells[i]} / {cells[i + 1]}" for i in range(0, len(cells), 2)))


if __name__ == "__main__":
    a = sys.argv[1:]
    if len(a) in (7, 8) and a[0] == "shapes":
        main(Path(a[1]), Path(a[2]), a[3], a[4], float(a[5]), a[6], *(int(v) for v in a[7:]))
    elif len(a) == 7 and a[0] == "relit":
        relit(Path(a[1]), Path(a[2]), a[3], a[4], float(a[5]), a[6])
    else:
        sys.exit(__doc__)
