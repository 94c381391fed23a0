"""Correspondences for geometry: the projector point that *lit* each camera pixel.

PSP decoding returns, per camera pixel q, the phase of ``C(q) = sum_p F_p(q) exp(i 2 pi x_p / T)``:
the footprint-weighted mean of the phases of the projector points x_p whose light re-emerges at q.
That is the map relighting needs (it says where a pattern's light shows up), and
:class:`~sssphase_core.relight.engine.Projection` keeps it. On a translucent object lit obliquely the
footprints are skewed toward the direction the light travels, so the decoded point is shifted along
the projector-camera baseline from the point that lit q, and 3D triangulated from it is biased.

Given footprints (a session's measured crops or a model's), the shift is predicted by relighting
the view under the fringe's cosine and sine and removed (one pass; the points x_p, x_q are the
decoded ones, smoothed, since only their differences matter):

    b(q) = T / (2 pi) arg(C(q) exp(-i 2 pi x_q / T)),    x_geometry(q) = x_decoded(q) - b(q)

Exact footprints of the simulator remove the bias of the directional dipole (``sss bench psp``);
symmetric footprints predict no shift.

That holds for footprints centred on the point where light *enters* (the simulator's exact ones, the
analytic model's). A model trained on dot-grid crops learns footprints centred where the crops were cut:
at the camera pixel whose *decoded* point is the dot's, i.e. on the fringe-weighted mean of where the
dot's light emerges. Such a footprint reproduces the decoded point by construction (relighting it predicts
no shift, or noise: the correction went the wrong way), and the shift is instead where the light entered
inside it: for light entering at offset e (camera px) from the crop's centre, the decoded point of the
centre is the projector point of e, so b = J e with J the decoded map's Jacobian. The entry point is the
footprint's maximum (the light is densest where it enters; the tail runs the way it travels):
:func:`entry_shift`. On the simulator's directional dipole with a demo-size decoder this turned the
correction's sign (hand: bias +0.110 px decoded, +0.130 relit-fringe correction, +0.073 entry-point one).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from sssphase_core.relight.engine import FootprintSource, Projection, footprint_array, relight


def scattering_shift(source: FootprintSource, proj: Projection, patch: int, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Shift (bx, by) (H, W) in projector pixels of the decoded correspondence from the points in
    ``proj`` (taken as where each pixel is lit), predicted from ``source``'s footprints for PSP
    fringes of ``period`` projector pixels; NaN off the mask or where no light arrives."""
    wp, hp = proj.projector_size
    u = 2 * np.pi / period
    xs, ys = np.meshgrid(np.arange(wp, dtype=np.float64), np.arange(hp, dtype=np.float64))
    light = [np.ones((hp, wp))]
    for coord in (xs, ys):
        light += [(1 + np.cos(u * coord)) / 2, (1 + np.sin(u * coord)) / 2]
    # pattern values whose emitted light is linear in ``light`` (relighting applies the gamma)
    patterns = np.stack([np.power(v, 1.0 / proj.gamma) for v in light]).astype(np.float32)
    img = relight(source, proj, patterns, patch).sum(axis=-1, dtype=np.float64)  # (5, H, W), colours summed
    total = img[0]
    out = []
    for i, coord in enumerate((proj.xp, proj.yp)):
        c = (2 * img[1 + 2 * i] - total) + 1j * (2 * img[2 + 2 * i] - total)
        shift = np.angle(c * np.exp(-1j * u * coord.astype(np.float64))) / u
        out.append(np.where(proj.mask & (np.abs(c) > 0) & np.isfinite(coord), shift, np.nan).astype(np.float32))
    return out[0], out[1]


#: How the backends' footprints are centred: on the point where light enters (physical models), or where the
#: dot-grid crops they were trained on were cut (learned models: on the decoded point).
ENTRY_CENTRED = frozenset({"exact", "analytic"})


def entry_offsets(source: FootprintSource, pixels: np.ndarray, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Where light enters inside each of ``pixels``' (N, 2) footprints, relative to their centre (camera px):
    the sub-pixel maximum of the colour-summed footprint (a parabola through it and its neighbours along each
    axis); NaN where the maximum lies on the footprint's border (not a single-peaked footprint)."""
    ey, ex = np.full(len(pixels), np.nan), np.full(len(pixels), np.nan)
    for i in range(0, len(pixels), chunk):
        fp = footprint_array(source(pixels[i:i + chunk])).sum(axis=-1, dtype=np.float64)  # (n, K, K)
        n, k = fp.shape[:2]
        iy, ix = np.divmod(fp.reshape(n, -1).argmax(axis=1), k)
        inner = (iy > 0) & (iy < k - 1) & (ix > 0) & (ix < k - 1)
        r, cy, cx = np.arange(n), np.clip(iy, 1, k - 2), np.clip(ix, 1, k - 2)
        centre = fp[r, cy, cx]
        for out, lo, hi, at in ((ex, fp[r, cy, cx - 1], fp[r, cy, cx + 1], cx), (ey, fp[r, cy - 1, cx], fp[r, cy + 1, cx], cy)):
            curve = lo - 2 * centre + hi
            step = np.where(curve < 0, 0.5 * (lo - hi) / np.where(curve < 0, curve, -1.0), 0.0)
            out[i:i + n] = np.where(inner, at - k // 2 + np.clip(step, -0.5, 0.5), np.nan)
    return ey, ex


def entry_shift(source: FootprintSource, proj: Projection) -> tuple[np.ndarray, np.ndarray]:
    """Shift (bx, by) (H, W) in projector pixels of the decoded correspondence for footprints centred on the
    decoded point (a learned model's): the entry point inside each pixel's footprint (:func:`entry_offsets`)
    through the Jacobian of the decoded map (``proj``, smoothed); NaN off the mask, at its edge (no
    Jacobian) and where a footprint has no inner maximum."""
    valid = proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp)
    ys, xs = np.nonzero(valid)
    ey, ex = entry_offsets(source, np.stack([ys, xs], axis=1))
    out = []
    for coord in (proj.xp, proj.yp):
        dy, dx = np.gradient(np.where(valid, coord, np.nan).astype(np.float64))  # NaN next to the mask's edge
        shift = np.full(proj.mask.shape, np.nan, np.float32)
        shift[ys, xs] = dx[ys, xs] * ex + dy[ys, xs] * ey
        out.append(shift)
    return out[0], out[1]


#: Gaussian sigma (camera px) of the smoothing applied to the points the shift is predicted from: the
#: shift depends on differences x_p - x_q, and decoding noise in x_q would otherwise pass into it.
SMOOTH_SIGMA = 2.0


def smoothed(proj: Projection, sigma: float = SMOOTH_SIGMA) -> Projection:
    """``proj`` with its points Gaussian-smoothed within the mask (normalised convolution)."""
    import cv2

    valid = proj.mask & np.isfinite(proj.xp) & np.isfinite(proj.yp)
    weight = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma)
    out = []
    for coord in (proj.xp, proj.yp):
        blurred = cv2.GaussianBlur(np.where(valid, coord, 0).astype(np.float32), (0, 0), sigma)
        out.append(np.where(valid, blurred / np.maximum(weight, 1e-6), coord).astype(np.float32))
    return replace(proj, xp=out[0], yp=out[1])


def geometric_correspondence(source: FootprintSource, proj: Projection, patch: int, period: float,
                             sigma: float = SMOOTH_SIGMA, *, centred_on: str = "entry") -> Projection:
    """``proj`` with the scattering shift removed: the projector point that lit each pixel, for
    triangulation (keep ``proj``, the decoded points, for relighting). Pixels whose shift cannot be
    predicted keep their decoded point.

    The shift depends only on differences x_p - x_q, and the decoded map has the right differences
    wherever its bias varies slowly, so it is predicted in one pass from the decoded points,
    smoothed (``sigma`` camera px, 0: not) so that decoding noise is not amplified. Iterating with
    the corrected points was tried and is unstable: pixels no light reaches keep their decoded
    point, and that step propagates a footprint's reach inward each iteration (a 1.6 px shift grew
    to 8 px after 6 iterations on a synthetic ramp).

    ``centred_on``: ``"entry"`` for footprints centred where light enters (:data:`ENTRY_CENTRED` backends:
    the shift is predicted by relighting the fringes), ``"decoded"`` for a learned model's, centred on the
    decoded point (the shift is the entry point inside them, :func:`entry_shift`)."""
    if centred_on not in ("entry", "decoded"):
        raise ValueError(f"centred_on must be 'entry' or 'decoded', got {centred_on!r}")
    points = smoothed(proj, sigma) if sigma > 0 else proj
    bx, by = scattering_shift(source, points, patch, period) if centred_on == "entry" else entry_shift(source, points)
    decoded_x, decoded_y = proj.xp.astype(np.float32), proj.yp.astype(np.float32)
    return replace(proj, xp=np.where(np.isfinite(bx), decoded_x - bx, decoded_x).astype(np.float32),
                   yp=np.where(np.isfinite(by), decoded_y - by, decoded_y).astype(np.float32))


def shift_figure(white: np.ndarray, shift_x: np.ndarray, mask: np.ndarray, path: Path | str, *, title: str = "",
                 depth: np.ndarray | None = None, unit: str = "") -> Path:
    """The view's white capture | the scattering shift along the baseline (projector px) | with ``depth`` (H, W: the
    decoded points' depth minus the corrected ones', in ``unit``) how far behind the surface scattering put each
    point (PNG, diverging colour bars centred on 0)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sssphase_core.processing.colour import display_scale, srgb
    from sssphase_core.store.files import save_figure

    panels = [("shift along the baseline (x)", shift_x, "projector px")]
    if depth is not None:
        panels.append(("depth: decoded - corrected", depth, f"{unit} (+: behind the surface)"))
    fig, axes = plt.subplots(1, 1 + len(panels), figsize=(3.6 * (1 + len(panels)), 3.2), constrained_layout=True)
    axes[0].imshow(srgb(np.nan_to_num(white) / display_scale(white, mask)), interpolation="nearest")
    axes[0].set_title("white capture", fontsize=9)
    for ax, (name, values, label) in zip(axes[1:], panels, strict=True):
        shown = mask & np.isfinite(values)
        vmax = float(max(np.percentile(np.abs(values[shown]), 99) if shown.any() else 0.0, 1e-6))
        im = ax.imshow(np.where(shown, values, np.nan), cmap="coolwarm", vmin=-vmax, vmax=vmax, interpolation="nearest")
        ax.set_title(name, fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label=label)
    for ax in axes:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return Path(path)
