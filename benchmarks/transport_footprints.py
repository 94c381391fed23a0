"""What a captured view's own light transport says about per-pixel footprints (issue 42, item 1).

    python benchmarks/transport_footprints.py SESSION [CHECKPOINT ...] [--pixels 400] [--renders DIR]

For view 0 of a session captured or imported with dot grids (its ``transport/`` arrays: one crop per projector
dot), the footprint of each camera pixel as the transport gives it: the crops of the dots whose light enters
through that pixel (each dot to the decoded pixel nearest to it, as the transport stores it), denoised as
``sss relight --backend measured`` reads them, summed. Prints:

* how the per-pixel training crops (``footprints/crops``: the dot at each pixel's *rounded* projector coordinate)
  cover the dots: pixels, distinct dots among them, dots of the transport that no pixel's crop holds;
* each source's share of the footprint energy per ring about the pixel, on ``--pixels`` interior pixels (3 px
  inside the mask) that have transport: the transport's, the analytic model's and each decoder's (uncalibrated,
  normalised to unit energy);
* with reference patterns in the session, PSNR of the view relit from the transport's per-pixel footprints and
  from the training crops (uncalibrated, each splatted with the pattern at its decoded point, as a model's are)
  against the reference captures, or against ``DIR/OBJECT_clean_ref__PATTERN.exr`` with ``--renders``
  (`mitsuba_render.py`'s noise-free renders);
* with ``--calibrated``: each source relit through ``sss relight``'s own pipeline
  (:func:`~sssphase_core.relight.pipeline.relight_view`: the white-consistent gain and the view calibration on the
  view's fringes): the transport's per-pixel footprints treated as a model's, beside the analytic model, no
  scattering, the dot transport as ``sss relight --backend measured`` uses it, and each checkpoint's torch and
  blend, with each one's margin over the analytic model (the bar of issue 42, item 1); and the same footprints
  with each dot shared among the camera pixels it overlaps (:func:`pixel_area_transport`: light entering each
  pixel's area, what a per-pixel model is asked for), averaged over rings, or one shape per view. With converged
  references in ``--renders`` also against those, on pixels chosen independently of the sources, beside the clean
  render itself: the ceiling of any model of these captures (:func:`calibrated_table`).

Prints Markdown.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

from sssphase_core.errors import SssError
from sssphase_core.relight.backends import make_source
from sssphase_core.relight.engine import relight
from sssphase_core.relight.views import load_view
from sssphase_core.store.session import Session

RINGS = ((0, 0.5), (0.5, 1.5), (1.5, 3), (3, 6), (6, 10), (10, 1e9))  # px from the crop centre


def per_pixel_transport(transport, crops: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (N, 2) yx, footprints (N, K, K, 3) float32): each dot's transport crop (``crops``, every row of the
    ``measured`` source ``transport``, denoised as it reads them: the noise mask that relights the view's own
    fringes best), summed into its pixel, in an image ``width`` px wide."""
    return sum_into_pixels(np.asarray(transport.pixels, np.int64), crops, width)


def sum_into_pixels(pixels: np.ndarray, crops: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(distinct pixels (M, 2) yx in row-major order, (M, K, K, C) float32 sums of the ``crops`` (N, K, K, C) that
    share each of ``pixels`` (N, 2) yx) in an image ``width`` px wide."""
    key = np.asarray(pixels, np.int64) @ np.array([width, 1])
    unique, inverse = np.unique(key, return_inverse=True)
    out = np.zeros((len(unique), *np.shape(crops)[1:]), np.float32)
    np.add.at(out, inverse.ravel(), np.asarray(crops, np.float32))
    return np.stack([unique // width, unique % width], axis=1), out


def pixel_area_transport(rv, transport, crops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (M, 2) yx, footprints (M, K, K, 3) float32): the light that enters each camera pixel's *area*: every
    dot's crop (``crops`` of the ``measured`` source ``transport``, as for :func:`per_pixel_transport`) shared among the 4 camera pixels nearest to
    where the dot lit the surface (its projector point through the local inverse Jacobian, bilinear weights: the
    share of the dot that overlaps each pixel) and re-centred on each. Unlike :func:`per_pixel_transport` (each dot
    whole in one pixel) its footprints change smoothly between neighbours, as a per-pixel model's can."""
    from sssphase_core.processing.footprints import dot_offsets

    centre = np.asarray(transport.pixels, np.int64)
    dots = np.asarray(rv.session.load(rv.view, "transport/dots"), np.float64)  # (N, 2) projector (x, y)
    where = centre + dot_offsets(rv.proj.xp, rv.proj.yp, rv.proj.mask, centre, dots=dots).astype(np.float64)
    return spread_over_pixels(where, crops, centre, rv.proj.shape)


def spread_over_pixels(where: np.ndarray, crops: np.ndarray, centre: np.ndarray,
                       shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Crops (N, K, K, C), each centred on pixel ``centre`` (N, 2) yx, of light that entered at ``where`` (N, 2)
    (y, x) camera px, shared among the 4 pixels nearest to ``where`` by bilinear weights and re-centred on each
    (an integer shift, zero from outside) -> :func:`sum_into_pixels` of them (pixels inside ``shape`` (H, W))."""
    crops = np.asarray(crops, np.float32)
    k = crops.shape[1]
    top = np.floor(where).astype(np.int64)
    frac = where - top
    pixels, parts = [], []
    for oy in (0, 1):
        for ox in (0, 1):
            weight = ((frac[:, 0] if oy else 1 - frac[:, 0]) * (frac[:, 1] if ox else 1 - frac[:, 1])).astype(np.float32)
            to = top + [oy, ox]
            inside = (to >= 0).all(axis=1) & (to[:, 0] < shape[0]) & (to[:, 1] < shape[1]) & (weight > 0)
            step = to - centre  # the receiving pixel relative to the crop's centre
            for sy, sx in np.unique(step[inside], axis=0):
                sel = inside & (step[:, 0] == sy) & (step[:, 1] == sx)
                moved = np.zeros((int(sel.sum()), k, k, crops.shape[3]), np.float32)  # moved[i] = crop[i + step]
                y0, y1, x0, x1 = max(0, sy), min(k, k + sy), max(0, sx), min(k, k + sx)
                moved[:, y0 - sy:y1 - sy, x0 - sx:x1 - sx] = crops[sel, y0:y1, x0:x1]
                pixels.append(to[sel])
                parts.append(moved * weight[sel, None, None, None])
    if not pixels:
        return np.zeros((0, 2), np.int64), np.zeros((0, *crops.shape[1:]), np.float32)
    return sum_into_pixels(np.concatenate(pixels), np.concatenate(parts), shape[1])


def ring_shares(footprints: np.ndarray) -> np.ndarray:
    """(len(RINGS),) mean share of each (N, K, K, 3) footprint's energy (values below 0 as 0) per ring."""
    k = footprints.shape[1]
    d = np.arange(k) - k // 2
    r = np.hypot(d[:, None], d[None, :])
    f = footprints.clip(0).sum(axis=-1)
    e = np.maximum(f.sum(axis=(1, 2)), 1e-12)
    return np.array([(f[:, (r >= lo) & (r < hi)].sum(axis=1) / e).mean() for lo, hi in RINGS])


def signed_ring_shares(footprints: np.ndarray) -> np.ndarray:
    """(len(RINGS),) share per ring of the (N, K, K, 3) footprints' summed energy, negative values included: the
    zero-mean noise of captured crops cancels in the sums, where clipping each crop keeps its positive half."""
    k = footprints.shape[1]
    d = np.arange(k) - k // 2
    r = np.hypot(d[:, None], d[None, :])
    f = np.asarray(footprints, np.float64).sum(axis=(0, -1))  # (K, K)
    return np.array([f[(r >= lo) & (r < hi)].sum() for lo, hi in RINGS]) / max(float(f.sum()), 1e-12)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("checkpoints", type=Path, nargs="*")
    ap.add_argument("--pixels", type=int, default=400)
    ap.add_argument("--renders", type=Path, default=None)
    ap.add_argument("--calibrated", action="store_true",
                    help="also relight every source through sss relight's pipeline (white-consistent gain, view "
                         "calibration) and print each one's PSNR and its margin over the analytic model")
    ap.add_argument("--signed", action="store_true",
                    help="shares of the summed energy with negative values kept (noise cancels), on pixels that also "
                         "have training crops, with rows for those crops as they are and clipped at 0")
    args = ap.parse_args()
    try:
        rv = load_view(Session.open(args.session), 0)
    except SssError as e:  # a wrong folder: one line, as `sss` gives it
        raise SystemExit(f"error: {e}") from None
    arrays = rv.session.arrays(0)
    if "transport/crops" not in arrays:
        raise SystemExit(f"{args.session}: view 0 has no captured transport (capture or import it with dot grids)")
    transport, _ = make_source("measured", rv)  # built (denoised) once, its crops read once
    crops_all = transport.crops_at(np.arange(len(transport.pixels)))
    px, fp = per_pixel_transport(transport, crops_all, rv.proj.shape[1])
    if "footprints/pixels" in arrays:
        train_px = np.asarray(rv.session.load(0, "footprints/pixels"), np.int64)
        rx = np.floor(rv.proj.xp[train_px[:, 0], train_px[:, 1]] + 0.5).astype(np.int64)
        ry = np.floor(rv.proj.yp[train_px[:, 0], train_px[:, 1]] + 0.5).astype(np.int64)
        dots = np.asarray(rv.session.load(0, "transport/dots"), np.int64)
        rounded = set(zip(rx.tolist(), ry.tolist(), strict=True))
        missed = sum((x, y) not in rounded for x, y in dots.tolist())
        print(f"{rv.object}: {len(train_px):,} pixels with training crops hold {len(rounded):,} distinct dots; "
              f"{missed:,} of the transport's {len(dots):,} dots are in no pixel's crop\n")
    inner = binary_erosion(rv.proj.mask, iterations=3)[px[:, 0], px[:, 1]] & (fp.sum(axis=(1, 2)) > 0).all(axis=-1)
    crop_row = None
    if args.signed and "footprints/pixels" in arrays:  # the training crops' own row: pixels that have both
        crop_row = np.full(rv.proj.shape, -1, np.int64)
        crop_row[train_px[:, 0], train_px[:, 1]] = np.arange(len(train_px))
        inner &= crop_row[px[:, 0], px[:, 1]] >= 0
    pick = np.flatnonzero(inner)
    pick = np.sort(np.random.default_rng(0).choice(pick, min(args.pixels, len(pick)), replace=False))
    rows = [("the transport, each dot's crop in its pixel", fp[pick])]
    if crop_row is not None:
        rows_at = crop_row[px[pick, 0], px[pick, 1]]
        order = np.argsort(rows_at)  # a chunked array reads in increasing order
        crops = np.empty((len(pick), *fp.shape[1:]), np.float32)
        crops[order] = np.asarray(rv.session.read(0, "footprints/crops")[rows_at[order]], np.float32)
        rows += [("the training crops", crops), ("the training crops, each clipped at 0", crops.clip(0))]
    analytic, _ = make_source("analytic", rv, calibrate=False)
    rows.append(("analytic", np.asarray(analytic(px[pick]), np.float32)))
    for ck in args.checkpoints:
        src, _ = make_source("torch", rv, checkpoint=ck, calibrate=False)
        out = src(px[pick])
        rows.append((str(ck), np.asarray(out.detach().cpu().numpy() if hasattr(out, "detach") else out, np.float32)))
    shares = signed_ring_shares if args.signed else ring_shares
    print(f"Energy share per ring about the pixel ({len(pick)} interior pixels{', signed sums' if args.signed else ''}):\n")
    print("| footprints | " + " | ".join(f"{lo:g}-{hi:g} px" if hi < 1e9 else f"> {lo:g} px" for lo, hi in RINGS) + " |")
    print("|---|" + "---|" * len(RINGS))
    for name, f in rows:
        print(f"| {name} | " + " | ".join(f"{x:.3f}" for x in shares(f)) + " |")
    names = sorted(rv.references)
    if not names:
        return
    index = np.full(rv.proj.shape, -1, np.int64)
    index[px[:, 0], px[:, 1]] = np.arange(len(px))

    transport_source = per_pixel_source(fp, index)

    pats = [rv.references[n] for n in names]
    sources = [("the transport's per-pixel footprints", transport_source, fp.shape[1])]
    if "footprints/pixels" in arrays:  # what decoder training reads, splatted as footprints
        from sssphase_core.relight.sources import nearest_measured_source

        crops = rv.session.read(0, "footprints/crops")
        sources.append(("the training crops", nearest_measured_source(train_px, crops, rv.white), int(crops.shape[1])))
    m = rv.proj.mask
    if args.renders is not None:
        from sssphase_core.store.exr import read_exr

        truths, what = [read_exr(args.renders / f"{rv.object}_clean_ref__{n}.exr") for n in names], "noise-free renders"
    else:
        truths, what = [rv.captured[n] for n in names], "reference captures"
    print(f"\nRelit as footprints, uncalibrated, against the {what} (PSNR, dB, decoded mask):\n")
    print("| footprints | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for label, source, k in sources:
        relit = relight(source, rv.proj, pats, k, white=rv.white)
        cells = [f"{10 * np.log10(1 / np.mean((img[m] - t[m]) ** 2)):.2f}" for img, t in zip(relit, truths, strict=True)]
        print(f"| {label} | " + " | ".join(cells) + " |")
    if args.calibrated:
        area_px, area_fp = pixel_area_transport(rv, transport, crops_all)
        area_index = np.full(rv.proj.shape, -1, np.int64)
        area_index[area_px[:, 0], area_px[:, 1]] = np.arange(len(area_px))
        variants = [("the transport's per-pixel footprints", transport_source),
                    ("the same, each averaged over rings about its pixel", per_pixel_source(ring_averaged(fp), index)),
                    ("the view's mean transport shape, times each pixel's energy",
                     per_pixel_source(mean_shape(fp), index)),
                    ("the transport shared among the pixels each dot overlaps", per_pixel_source(area_fp, area_index)),
                    ("the shared transport, each averaged over rings about its pixel",
                     per_pixel_source(ring_averaged(area_fp), area_index)),
                    ("the shared transport's mean shape, times each pixel's energy",
                     per_pixel_source(mean_shape(area_fp), area_index))]
        calibrated_table(rv, variants, fp.shape[1], pats, names, truths, args.checkpoints, args.renders, transport)


def per_pixel_source(fp: np.ndarray, index: np.ndarray):  # noqa: ANN201
    """A footprint source giving the pixel at (y, x) the footprint ``fp[index[y, x]]`` ((M, K, K, C) footprints,
    (H, W) row index, -1 where a pixel has none: no light enters there)."""
    def source(pixels: np.ndarray) -> np.ndarray:
        pixels = np.asarray(pixels, np.int64)
        out = np.zeros((len(pixels), *fp.shape[1:]), np.float32)
        i = index[pixels[:, 0], pixels[:, 1]]
        out[i >= 0] = fp[i[i >= 0]]
        return out

    return source


def ring_averaged(fp: np.ndarray) -> np.ndarray:
    """(N, K, K, C) footprints, each replaced by its own mean over the 1-px rings about its centre (its energy per
    ring kept, its angular detail dropped)."""
    n, k, _, c = fp.shape
    d = np.arange(k) - k // 2
    ring = np.rint(np.hypot(d[:, None], d[None, :])).astype(np.int64).ravel()  # (K*K,)
    onehot = np.zeros((k * k, ring.max() + 1), np.float32)
    onehot[np.arange(k * k), ring] = 1
    flat = np.asarray(fp, np.float32).reshape(n, k * k, c).transpose(0, 2, 1)  # (N, C, K*K)
    means = (flat @ onehot) / onehot.sum(axis=0)  # (N, C, rings)
    return (means @ onehot.T).transpose(0, 2, 1).reshape(n, k, k, c)


def mean_shape(fp: np.ndarray) -> np.ndarray:
    """(N, K, K, C) footprints, each replaced by the mean normalised shape of those with light in every colour,
    times its own energy per colour: what is left when footprints differ between pixels only in energy."""
    energy = np.asarray(fp, np.float64).sum(axis=(1, 2))  # (N, C)
    lit = (energy > 0).all(axis=1)
    shape = (fp[lit] / energy[lit][:, None, None, :]).mean(axis=0)  # (K, K, C), each colour summing to 1
    return (shape[None] * np.maximum(energy, 0)[:, None, None, :]).astype(np.float32)


def reference_noise(half0: np.ndarray, half1: np.ndarray, where: np.ndarray) -> float:
    """The mean squared error of a reference that is the mean of two independent halves (H, W, 3) on ``where``
    (H, W): a quarter of the halves' mean squared difference (exact for means; the converged references' trimmed
    means differ from it by ~10%)."""
    return float(np.mean((half0[where] - half1[where]) ** 2)) / 4


#: Pixels whose two converged halves (or clean and converged render) differ by more than this, in any colour, are
#: left out of a scoring: a firefly there outweighs every model's error.
CALM = 0.01


def steady_white(white: np.ndarray, tolerance: float = 0.1) -> np.ndarray:
    """(H, W) bool: the white capture (H, W, 3) is within ``tolerance`` (relative, with a floor of 0.01) of its own
    3 x 3 median in every colour: no Monte-Carlo firefly there for the white-consistent gain to pass to every model.
    Chosen from the inputs and the converged halves only, so that no source's error picks its own pixels."""
    from scipy.ndimage import median_filter

    med = np.stack([median_filter(white[..., c], 3) for c in range(white.shape[-1])], axis=-1)
    return (np.abs(white - med) / np.maximum(med, 0.01)).max(axis=-1) <= tolerance


def shares(wheres: list[np.ndarray], mask: np.ndarray) -> str:
    """Each selection's share of ``mask``, as "82%, 83%"."""
    return ", ".join(f"{w.sum() / mask.sum():.0%}" for w in wheres)


def noise_corrected(mse: float, base_mse: float, noise: float) -> tuple[float, float]:
    """(PSNR, margin over the base in dB) of an image whose mean squared error against a noisy reference is
    ``mse``, once the reference's own ``noise`` (its mean squared error, independent of the image's) is taken out
    of it and of the base's ``base_mse``: a noisy truth adds the same error to every image and pulls margins to 0."""
    e, b = max(mse - noise, 1e-12), max(base_mse - noise, 1e-12)
    return 10 * float(np.log10(1 / e)), 10 * float(np.log10(b / e))


def calibrated_table(rv, variants: list[tuple[str, object]], k: int, pats: list[np.ndarray], names: list[str],
                     truths: list[np.ndarray], checkpoints: list[Path], renders: Path | None, measured) -> None:
    """PSNR of the view relit through ``sss relight``'s pipeline from each source, and its margin over the
    analytic model's: the transport's per-pixel footprints (the first of ``variants``: (label, source) pairs of
    patch ``k``) calibrated as a model's, and what of them others keep (a radial profile per pixel, one shape for
    the view), beside no scattering, ``measured`` (the view's ``measured`` source, relit as `sss relight` does) and
    each checkpoint's torch and blend. Scored on the decoded mask against ``truths``, and where
    ``renders`` holds converged references and their halves (`mitsuba_render.py --converged`: random numbers of their
    own), against those too, their own noise subtracted, beside the clean render itself (the ceiling of any model of
    these captures). The clean references share every capture's fixed Monte-Carlo pattern, and so does the
    transport: against them, copying that pattern scores as physics. So the pixels are chosen from the converged
    halves and the white capture only (``calm``); the ``quiet`` pixels (where the clean renders agree with the
    converged ones) are printed too, to show how a selection made with the clean renders favours the transport."""
    from sssphase_core.relight.backends import make_sources
    from sssphase_core.relight.pipeline import relight_view
    from sssphase_core.store.exr import read_exr

    m = rv.proj.mask
    images: list[tuple[str, np.ndarray]] = []
    none, k1 = make_source("none", rv)
    images.append(("none", relight(none, rv.proj, pats, k1, white=rv.white)))
    images.append(("measured (the dot transport, sss relight --backend measured)",  # model-free: relit as it is
                   relight(measured, rv.proj, pats, k, white=rv.white)))
    (analytic, ka), = make_sources("analytic", rv)
    images.append(("analytic", relight_view(analytic, ka, rv, pats, calibrate=True)[0]))
    for label, source in variants:
        images.append((f"{label}, calibrated as a model's", relight_view(source, k, rv, pats, calibrate=True)[0]))
    images.append((f"{variants[0][0]}, blended with the analytic model",
                   relight_view(variants[0][1], k, rv, pats, calibrate=True, also=[(analytic, ka)])[0]))
    for ck in checkpoints:
        (torch_src, kt), *rest = make_sources("blend", rv, checkpoint=ck)
        images.append((f"torch {ck}", relight_view(torch_src, kt, rv, pats, calibrate=True)[0]))
        images.append((f"blend {ck}", relight_view(torch_src, kt, rv, pats, calibrate=True, also=rest)[0]))
    # (what, truths, where, the truth's own noise: its mean squared error per pattern, estimated)
    scorings = [("the decoded mask, against the references above", truths, [m] * len(names), None)]
    converged = [renders / f"{rv.object}_converged_ref__{n}.exr" for n in names] if renders is not None else []
    halves = [[renders / f"{rv.object}_converged_half{i}_ref__{n}.exr" for i in (0, 1)] for n in names] if converged else []
    if converged and all(f.is_file() for f in [*converged, *(f for pair in halves for f in pair)]):
        conv = [read_exr(f) for f in converged]
        pairs = [(read_exr(a), read_exr(b)) for a, b in halves]
        # the renders the captures share their Monte-Carlo pattern with: the ceiling of any model of these captures
        images.append(("the clean render itself (every capture's Monte-Carlo pattern, no camera noise)", truths))
        steady = m & steady_white(rv.white)
        calm = [steady & (np.abs(a - b).max(axis=-1) <= CALM) for a, b in pairs]
        quiet = [m & (np.abs(t - c).max(axis=-1) <= CALM) for t, c in zip(truths, conv, strict=True)]
        for what, where in ((f"the calm pixels ({shares(calm, m)} of the mask: the converged halves agree, the white "
                             "capture has no firefly), against the converged references", calm),
                            (f"the quiet pixels ({shares(quiet, m)} of the mask: the clean renders agree with the "
                             "converged ones, so biased toward every source that shares the clean renders' "
                             "Monte-Carlo pattern), against the converged references", quiet)):
            scorings.append((what, conv, where, [reference_noise(a, b, w) for (a, b), w in zip(pairs, where, strict=True)]))
    for what, truth, where, noise in scorings:
        mses = [(label, [float(np.mean((img[w] - t[w]) ** 2)) for img, t, w in zip(imgs, truth, where, strict=True)])
                for label, imgs in images if imgs is not truth]  # the clean render is not scored against itself
        base = dict(mses)["analytic"]
        print(f"\nRelit through sss relight's pipeline (calibrated; white-consistent where the camera records every "
              f"colour), PSNR (dB) on {what}, and the margin over the analytic model"
              + ("; then the same without the converged reference's own noise (PSNR "
                 + ", ".join(f"{10 * np.log10(1 / x):.1f}" for x in noise) + " dB), subtracted from every mean "
                 "squared error" if noise else "") + ":\n")
        print("| source | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for label, cells in mses:
            out = []
            for i, (e, b) in enumerate(zip(cells, base, strict=True)):
                cell = f"{10 * np.log10(1 / e):.2f} ({10 * np.log10(b / e):+.2f})"
                if noise and e <= noise[i]:
                    cell += "; within the reference's own noise"
                elif noise:
                    psnr, margin = noise_corrected(e, b, noise[i])
                    cell += f"; {psnr:.2f} ({margin:+.2f})"
                out.append(cell)
            print(f"| {label} | " + " | ".join(out) + " |")


if __name__ == "__main__":
    main()
