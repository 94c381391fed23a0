"""How a decoder's footprints depend on the camera that made its input frames (issue 42, item 2).

    python benchmarks/camera_inputs.py SESSION CHECKPOINT [CHECKPOINT ...] [--pixels 400]

For view 0 of a simulated session (its exact footprints are the simulator's ground truth, for evaluation only),
``SESSION`` typically from a three-chip camera (`sss demo --three-chip`), the footprints of interior pixels (3 px
inside the decoded mask) by the analytic model and by each decoder, uncalibrated, two ways: from the frames as
they are, and from the frames sampled on an RGGB mosaic and demosaiced by Malvar's method (what a Bayer-trained
decoder saw in training; each pixel's energy kept from its own frames). Per colour: the median ratio of the
footprints' second-moment radius to the exact ones', their PSNR against the exact ones (data range 1, over the
crops), the median L1 error over the footprint's energy, and the view calibration's weight against no scattering
(``fit_view_mix``: 1 when the fringes ask for the footprints as they are). Prints a Markdown table.
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


def row(name: str, f: np.ndarray, exact: np.ndarray, mix: np.ndarray) -> str:
    ratio = np.median(radius(f) / radius(exact), axis=0)
    mse = np.maximum(((f - exact) ** 2).mean(axis=(0, 1, 2)), MSE_FLOOR)  # identical footprints: the floor's PSNR
    l1 = np.median(np.abs(f - exact).sum(axis=(1, 2)) / np.maximum(exact.sum(axis=(1, 2)), 1e-12), axis=0)

    def three(v: np.ndarray, fmt: str) -> str:
        return " / ".join(format(float(x), fmt) for x in v)

    return f"| {name} | {three(ratio, '.2f')} | {three(-10 * np.log10(mse), '.1f')} | {three(l1, '.2f')} | {three(mix, '.2f')} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("checkpoints", type=Path, nargs="+")
    ap.add_argument("--pixels", type=int, default=400)
    args = ap.parse_args()
    rv = load_view(Session.open(args.session), 0)
    inner = np.argwhere(binary_erosion(rv.proj.mask, iterations=3))
    pixels = inner[np.sort(np.random.default_rng(0).choice(len(inner), min(args.pixels, len(inner)), replace=False))]
    exact_source, _ = make_source("exact", rv)
    exact = as_array(exact_source(pixels))
    psp, lost = model_inputs(rv)
    print(f"{args.session.name}: {len(pixels)} interior pixels; exact radius {' / '.join(f'{r:.2f}' for r in np.median(radius(exact), axis=0))} px (R / G / B)\n")
    print("| footprints | radius / exact | PSNR (dB) | L1 / energy | view calibration's weight |")
    print("|---|---|---|---|---|")
    analytic, k = make_source("analytic", rv, calibrate=False)
    print(row("analytic", as_array(analytic(pixels)), exact, fit_view_mix(analytic, k, rv, psp, lost)))
    seen = bayer_frames(psp)
    own = psp.mean(axis=0)
    energy = np.where((own > 1e-4) & (seen.mean(axis=0) > 1e-4), own / np.maximum(seen.mean(axis=0), 1e-4), 1.0)
    for ck in args.checkpoints:
        plain, k = make_source("torch", rv, checkpoint=ck, calibrate=False)
        print(row(f"{ck.name}, frames as they are", as_array(plain(pixels)), exact, fit_view_mix(plain, k, rv, psp, lost)))
        decoder = plain.backend  # type: ignore[attr-defined]
        through = backend_source(decoder, seen)

        def mosaic_source(px: np.ndarray, through=through) -> np.ndarray:  # each pixel's energy from its own frames
            return as_array(through(px)) * energy[px[:, 0], px[:, 1]][:, None, None, :]

        print(row(f"{ck.name}, frames through a Bayer mosaic", mosaic_source(pixels), exact,
                  fit_view_mix(mosaic_source, k, rv, psp, lost)))


if __name__ == "__main__":
    main()
