"""How a decoder's footprints depend on the camera that made its input frames (issue 42, item 2).

    python benchmarks/camera_inputs.py SESSION CHECKPOINT [CHECKPOINT ...] [--pixels 400] [--band 6] [--detail]

For view 0 of a simulated session (its exact footprints are the simulator's ground truth, for evaluation only),
``SESSION`` typically from a three-chip camera (`sss demo --three-chip`), the footprints of interior pixels (3 px
inside the decoded mask) by the analytic model and by each decoder, uncalibrated, two ways: from the frames as
they are, and from the frames sampled on an RGGB mosaic and demosaiced by Malvar's method (what a Bayer-trained
decoder saw in training; each pixel's energy kept from its own frames). Per colour: the median ratio of the
footprints' second-moment radius to the exact ones', their PSNR against the exact ones (data range 1, over the
crops), the median L1 error over the footprint's energy, and the view calibration's weight against no scattering
(``fit_view_mix``: 1 when the fringes ask for the footprints as they are), over the whole decoded mask and with a
``--band`` px band along the silhouette left out. ``--detail``: each source's share of the footprint energy per ring,
its MTF at fringe periods of 8, 11 and 16 px (median) and its centroid's error. Prints Markdown tables.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_erosion

from sssphase_core.learning.camera import rebayer
from sssphase_core.learning.metrics import MSE_FLOOR
from sssphase_core.relight.backends import make_source
from sssphase_core.relight.calibration import fit_view_mix, model_inputs
from sssphase_core.relight.sources import backend_source
from sssphase_core.relight.views import load_view
from sssphase_core.store.session import Session


def bayer_frames(psp: np.ndarray) -> np.ndarray:
    """(8, H, W, 3) frames through an RGGB mosaic and Malvar demosaicing."""
    x = torch.from_numpy(np.ascontiguousarray(psp, np.float32)).permute(0, 3, 1, 2)
    return rebayer(x, 0).permute(0, 2, 3, 1).numpy()


def as_array(f: object) -> np.ndarray:
    """(N, K, K, 3) float64 footprints from a source's numpy array or tensor."""
    return np.asarray(f.detach().cpu().numpy() if torch.is_tensor(f) else f, np.float64)


def radius(f: np.ndarray) -> np.ndarray:
    """(N, 3) second-moment radius (px) of (N, K, K, 3) footprints about the crop centre."""
    k = f.shape[1]
    d = np.arange(k) - k // 2
    r2 = (d[:, None] ** 2 + d[None, :] ** 2)[None, :, :, None]
    f = f.clip(0)
    return np.sqrt((f * r2).sum(axis=(1, 2)) / np.maximum(f.sum(axis=(1, 2)), 1e-12))


def three(v: np.ndarray, fmt: str) -> str:
    """Three per-colour values as ``R / G / B``."""
    return " / ".join(format(float(x), fmt) for x in v)


RINGS = ((0, 0.5), (0.5, 1.5), (1.5, 3), (3, 6), (6, 10), (10, 64))  # px from the crop centre
PERIODS = (8.0, 11.0, 16.0)  # px, fringe periods for the MTF


def detail(name: str, f: np.ndarray, exact: np.ndarray) -> str:
    """A row of ring energy shares, MTFs along x and median |centroid error| (px), colours as R / G / B."""
    k = f.shape[1]
    d = np.arange(k) - k // 2
    r = np.hypot(d[:, None], d[None, :])
    g = f.clip(0)
    e = np.maximum(g.sum(axis=(1, 2)), 1e-12)  # (N, 3)
    shares = [(g[:, (r >= lo) & (r < hi)].sum(axis=1) / e).mean(axis=0) for lo, hi in RINGS]
    mtf = [np.median(np.abs((g * np.exp(2j * np.pi * d / t)[None, None, :, None]).sum(axis=(1, 2))) / e, axis=0)
           for t in PERIODS]
    ge, ee = exact.clip(0), np.maximum(exact.clip(0).sum(axis=(1, 2)), 1e-12)
    cen = [np.median(np.abs((g * d[ax]).sum(axis=(1, 2)) / e - (ge * d[ax]).sum(axis=(1, 2)) / ee), axis=0)
           for ax in ((None, slice(None), None, None), (None, None, slice(None), None))]

    return (f"| {name} | " + " | ".join(three(v, ".3f") for v in shares) + " | "
            + " | ".join(three(v, ".3f") for v in mtf) + f" | {three(np.maximum(*cen), '.3f')} |")


def row(name: str, f: np.ndarray, exact: np.ndarray, mix: np.ndarray) -> str:
    ratio = np.median(radius(f) / radius(exact), axis=0)
    mse = np.maximum(((f - exact) ** 2).mean(axis=(0, 1, 2)), MSE_FLOOR)  # identical footprints: the floor's PSNR
    l1 = np.median(np.abs(f - exact).sum(axis=(1, 2)) / np.maximum(exact.sum(axis=(1, 2)), 1e-12), axis=0)

    weights = " | ".join(three(m, ".2f") for m in np.atleast_2d(mix))
    return f"| {name} | {three(ratio, '.2f')} | {three(-10 * np.log10(mse), '.1f')} | {three(l1, '.2f')} | {weights} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("checkpoints", type=Path, nargs="+")
    ap.add_argument("--pixels", type=int, default=400)
    ap.add_argument("--band", type=int, default=6, help="px along the silhouette left out of the second fit")
    ap.add_argument("--detail", action="store_true")
    args = ap.parse_args()
    rv = load_view(Session.open(args.session), 0)
    inner = np.argwhere(binary_erosion(rv.proj.mask, iterations=3))
    pixels = inner[np.sort(np.random.default_rng(0).choice(len(inner), min(args.pixels, len(inner)), replace=False))]
    exact_source, k = make_source("exact", rv)
    exact = as_array(exact_source(pixels))
    psp, lost = model_inputs(rv)
    band = lost | (rv.proj.mask & ~binary_erosion(rv.proj.mask, iterations=args.band))

    def weights(source: object, patch: int) -> np.ndarray:  # (2, 3): the whole mask, the silhouette band left out
        return np.stack([fit_view_mix(source, patch, rv, psp, lost), fit_view_mix(source, patch, rv, psp, band)])

    rows = [("exact", exact, weights(exact_source, k))]
    analytic, k = make_source("analytic", rv, calibrate=False)
    rows.append(("analytic", as_array(analytic(pixels)), weights(analytic, k)))
    seen = bayer_frames(psp)
    own = psp.mean(axis=0)
    energy = np.where((own > 1e-4) & (seen.mean(axis=0) > 1e-4), own / np.maximum(seen.mean(axis=0), 1e-4), 1.0)
    for ck in args.checkpoints:
        plain, k = make_source("torch", rv, checkpoint=ck, calibrate=False)
        rows.append((f"{ck.name}, frames as they are", as_array(plain(pixels)), weights(plain, k)))
        through = backend_source(plain.backend, seen)  # type: ignore[attr-defined]

        def mosaic_source(px: np.ndarray, through=through) -> np.ndarray:  # each pixel's energy from its own frames
            return as_array(through(px)) * energy[px[:, 0], px[:, 1]][:, None, None, :]

        rows.append((f"{ck.name}, frames through a Bayer mosaic", mosaic_source(pixels), weights(mosaic_source, k)))
    radii = " / ".join(f"{r:.2f}" for r in np.median(radius(exact), axis=0))
    print(f"{args.session.name}: {len(pixels)} interior pixels; exact radius {radii} px (R / G / B)\n")
    print(f"| footprints | radius / exact | PSNR (dB) | L1 / energy | calibration's weight | the same, {args.band} px silhouette band left out |")
    print("|---|---|---|---|---|---|")
    for name, f, w in rows:
        print(row(name, f, exact, w))
    if args.detail:
        rings = " | ".join(f"energy in r {lo}-{hi} px" for lo, hi in RINGS)
        mtfs = " | ".join(f"MTF at {t:g} px" for t in PERIODS)
        print(f"\n| footprints | {rings} | {mtfs} | centroid error (px) |")
        print("|---|" + "---|" * (len(RINGS) + len(PERIODS) + 1))
        for name, f, _ in rows:
            print(detail(name, f, exact))


if __name__ == "__main__":
    main()
