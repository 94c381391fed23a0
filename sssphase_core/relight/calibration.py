"""The view calibration: a model's footprints weighted against no scattering by how well they relight
the view's own fringe captures (:func:`fit_view_mix`, :func:`view_mixture`, per pixel
:func:`local_mixture`, the constrained fit :func:`mixture_weights`), a model left out of the colours whose
fringe modulation shows none of its scattering (:func:`scattering_evidence`), and the source wrappers that
apply it or repair a model's energy (:func:`mixed_with_no_scattering`, :func:`energy_from_white`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from sssphase_core.errors import InputError
from sssphase_core.processing.isp import SATURATION_MARGIN
from sssphase_core.relight.engine import FootprintSource, footprint_array, relight
from sssphase_core.relight.sources import WHITE_FLOOR, no_scattering_source
from sssphase_core.relight.views import RelightView


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
    return view_mix(rv, relight(source, rv.proj, rv.psp_patterns, patch, white=rv.white), psp, exclude)


#: Gaussian sigma (px) of the window over which local_mixture fits a model's weight, and the prior's
#: strength (a fraction of the median evidence) that pulls it toward the view-wide weight.
LOCAL_MIX_SIGMA, LOCAL_MIX_PRIOR = 2.0, 0.05
#: The fringes' modulation must show a model's scattering: its best fit to the captures' modulation must
#: lower their squared error by this many times the noise variance (a chi-square with S degrees of freedom
#: under pure noise; 25 is beyond its 99.99th percentile for S <= 3), or the model is left out of that
#: colour (no scattering).
EVIDENCE_THRESHOLD = 25.0


def fringe_ac(x: np.ndarray) -> np.ndarray:
    """(8, ...) PSP-shaped values less each orientation's mean over its four shifts: the fringes' modulation.
    A model's energy comes from that mean of the captures themselves, so a fit that includes it rewards the
    model for repeating their noise; for independent noise the mean and the modulation are independent."""
    x = np.asarray(x)
    out = x.reshape(2, 4, *x.shape[1:])
    return (out - out.mean(axis=1, keepdims=True)).reshape(x.shape).astype(x.dtype, copy=False)


def fringe_noise_variance(psp: np.ndarray) -> np.ndarray:
    """(H, W, 3) noise variance per capture of the 8 PSP frames (two orientations of four shifts a quarter
    period apart): for a sinusoid ``I0 - I1 + I2 - I3 = 0``, so with independent noise of variance v in each
    frame that sum has variance 4 v; averaged over the two orientations. A projector's gamma error adds its
    second harmonic, which only makes the estimate larger."""
    x = np.asarray(psp, np.float32)
    total = np.zeros(x.shape[1:], np.float32)
    for o in (0, 4):  # one orientation at a time: float copies of a 1080p stack would be hundreds of MB
        r = x[o] - x[o + 1] + x[o + 2] - x[o + 3]
        total += r * r
    return np.nan_to_num(total / 8.0)


def scattering_evidence(d: Sequence[np.ndarray], e: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(3,) bool: per colour, whether the captures' modulation shows the sources' scattering. ``d``: S of
    (8, ...) the sources' relit fringes less no scattering's, ``e`` (8, ..., 3) the captures less no
    scattering's, ``noise`` (..., 3) each pixel's :func:`fringe_noise_variance`, all on the fit's pixels.
    The best constrained fit of the sources to the modulation must lower its squared error by more than
    :data:`EVIDENCE_THRESHOLD` times the noise variance along the sources' directions. Measured on ``sss
    bench stability``: a decoder's weight fitted to the noise of a material that does not scatter took it from
    "none"'s 153 dB to 58.7 (delta) and 184 to 68.8 (black object)."""
    ac = [fringe_ac(x) for x in d]
    eac = fringe_ac(e)
    axes = tuple(range(eac.ndim - 1))
    gram = np.stack([np.stack([(a * b).sum(axis=axes, dtype=np.float64) for b in ac], -1) for a in ac], -2)  # (3, S, S)
    cross = np.stack([(a * eac).sum(axis=axes, dtype=np.float64) for a in ac], -1)  # (3, S)
    d2 = sum((a * a).sum(axis=0, dtype=np.float64) for a in ac)  # (..., 3)
    out = np.zeros(3, bool)
    for c in range(3):
        w = mixture_weights(gram[c], cross[c])
        reduction = 2 * float(cross[c] @ w) - float(w @ gram[c] @ w)
        total = float(d2[..., c].sum())
        expected = float((d2[..., c] * noise[..., c]).sum()) / total if total > 0 else 0.0
        out[c] = reduction > EVIDENCE_THRESHOLD * expected
    return out


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
    # Only the fitted pixels' box (and the windows that reach them) is worked on: elsewhere every window is empty
    # and its weights are the view-wide ones (a 1080p view is mostly background: 2M windows of which 0.2M hold
    # evidence; 71 s of a 1080p torch relight on 2 cores had gone into fitting the empty ones).
    box = _box_around(m, LOCAL_MIX_REACH)
    mb = m[box]
    d = [np.where(mb[None, ..., None], r[:, box[0], box[1]] - none_psp[:, box[0], box[1]], 0).astype(np.float32)
         for r in relit_psps]
    e = np.where(mb[None, ..., None], np.nan_to_num(psp[:, box[0], box[1]] - none_psp[:, box[0], box[1]]),
                 0).astype(np.float32)
    gram = np.empty((*mb.shape, 3, s, s), np.float32)  # per pixel and colour, summed over the 8 fringes
    cross = np.empty((*mb.shape, 3, s), np.float32)
    for i in range(s):
        cross[..., i] = np.einsum("phwc,phwc->hwc", d[i], e)
        for j in range(i, s):
            gram[..., i, j] = gram[..., j, i] = np.einsum("phwc,phwc->hwc", d[i], d[j])
    total_gram, total_cross = gram.sum(axis=(0, 1), dtype=np.float64), cross.sum(axis=(0, 1), dtype=np.float64)
    view_weights = np.stack([mixture_weights(total_gram[c], total_cross[c]) for c in range(3)], axis=1)
    # colours whose fringes show none of the models' scattering: left out of every pixel (no scattering)
    left_out = ~scattering_evidence([x[:, mb] for x in d], e[:, mb], fringe_noise_variance(psp[:, box[0], box[1]])[mb])
    view_weights[:, left_out] = 0
    view_weights = view_weights.astype(np.float32)  # (S, 3)
    local = np.broadcast_to(view_weights[:, None, None, :], (s, *m.shape, 3)).copy()
    blur = lambda a: cv2.GaussianBlur(np.ascontiguousarray(a), (0, 0), LOCAL_MIX_SIGMA)  # noqa: E731
    for i in range(s):
        cross[..., i] = blur(cross[..., i])
        for j in range(i, s):
            gram[..., i, j] = gram[..., j, i] = blur(gram[..., i, j])
    # the prior: a fraction of the median evidence (per source) in a window
    trace = np.trace(gram, axis1=-2, axis2=-1)  # (h, w, 3)
    prior = LOCAL_MIX_PRIOR * float(np.median(trace[mb])) / s if mb.any() else 0.0
    if not prior > 0:
        return local, view_weights
    held = trace > 0  # (h, w, 3) the windows with evidence; the others' optimum is the prior's: the view-wide weights
    cross += prior * view_weights.T
    gram[..., range(s), range(s)] += prior
    if s == 1:  # the constrained optimum of one source is its fitted weight clipped to [0, 1]
        fitted = np.clip(cross[..., 0] / gram[..., 0, 0], 0.0, 1.0).astype(np.float32)
        local[0][box] = np.where(held, fitted, local[0][box])
    else:
        g, c = gram[held], cross[held]  # (n, S, S), (n, S)
        step = 1 << 20  # problems per batch: within a few hundred MB
        weights = np.concatenate([batched_mixture_weights(g[i:i + step], c[i:i + step])
                                  for i in range(0, len(c), step)] or [np.zeros((0, s))])
        for i in range(s):
            local[i][box][held] = weights[:, i]
    local[..., left_out] = 0
    return local, view_weights


#: Pixels beyond the fitted ones that local_mixture works on: its window's reach (OpenCV's Gaussian kernel spans
#: 4 sigma each way for float images) twice over, so that no window's border reflection reads a fitted pixel.
LOCAL_MIX_REACH = 2 * int(np.ceil(4 * LOCAL_MIX_SIGMA)) + 1


def _box_around(mask: np.ndarray, margin: int) -> tuple[slice, slice]:
    """The (rows, columns) slices of ``mask``'s bounding box grown by ``margin`` pixels (within the image); an
    empty mask: a 1x1 box."""
    ys, xs = np.nonzero(mask)
    if not len(ys):
        return slice(0, 1), slice(0, 1)
    h, w = mask.shape
    return (slice(max(0, ys.min() - margin), min(h, ys.max() + margin + 1)),
            slice(max(0, xs.min() - margin), min(w, xs.max() + margin + 1)))


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
    weights = np.stack([mixture_weights(gram[c], cross[c]) for c in range(3)], axis=1)
    weights[:, ~scattering_evidence(list(d), e, fringe_noise_variance(captured)[m])] = 0  # nothing to model there
    return weights.astype(np.float32)


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

    def mixed(pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        out = source(pixels)
        delta = (1 - weight) * np.nan_to_num(img[pixels[:, 0], pixels[:, 1]])  # (n, 3)
        c = out.shape[1] // 2
        if torch.is_tensor(out):  # a model's footprints on its device stay there
            out = out.float() * torch.as_tensor(weight, device=out.device)
            out[:, c, c] += torch.as_tensor(delta, device=out.device)
            return out
        out = footprint_array(out, writable=True)
        out *= weight
        out[:, c, c] += delta
        return out

    mixed.mix = weight  # type: ignore[attr-defined]
    return mixed


#: Bounds of :func:`exit_gain` (a pixel that a model relights 4x too bright or too dark under white is left at the bound).
EXIT_GAIN_RANGE = (0.25, 4.0)


#: The shot-noise variance of the white capture over that of 2 x the PSP frames' mean (8 frames at half its light):
#: the PSP offset's weight beside the white capture in :func:`exit_white`
PSP_WHITE_WEIGHT = 4.0
#: Fewer usable pixels than this give no reliable offset-to-white ratio: :func:`exit_white` is then the white capture
MIN_RATIO_PIXELS = 16


def exit_white(rv: RelightView) -> np.ndarray:
    """(H, W, 3) float32: the view's white at each pixel from the nine captures that measure it. These are the white
    capture and 2 x the mean of the 8 PSP frames (their offset), the offset scaled per colour to the white by the
    median ratio over the pixels where both are usable, averaged by inverse shot-noise variance
    (:data:`PSP_WHITE_WEIGHT`). A pixel's texture is in both, so it stays, and the capture's noise falls by about
    sqrt(5). The white capture alone where the fringes clipped beyond repair, off the decoded mask, where the white
    is unusable, or when too few pixels give a ratio. Made once per view (every model's gain and the calibration's
    no-scattering term read it)."""
    return _nine_capture_white(rv)[0]


def exit_white_variance(rv: RelightView) -> np.ndarray:
    """(H, W, 3) float32: the noise variance of :func:`exit_white` at each pixel, from the view's
    :func:`noise_model`: the white capture's at its light, the offset's (2 x the mean of 8 frames) a half of the
    frames' at theirs, weighed as :func:`exit_white` weighs the two."""
    return _nine_capture_white(rv)[1]


def noise_model(rv: RelightView) -> np.ndarray:
    """(2, 3) float64 ``(a, b)`` per colour: a capture's noise variance at light ``L`` is ``a + b L`` (read noise
    and shot noise), fitted by least squares to the PSP frames' :func:`fringe_noise_variance` against their mean
    light on the decoded pixels where no frame nears its clipping level; both at least 0. Made once per view."""
    cached = getattr(rv, "_noise_model", None)
    if cached is None:
        psp = np.asarray(rv.psp, np.float32)[:, rv.proj.mask]  # (8, n, 3): the decoded pixels only
        m = np.isfinite(psp).all(axis=(0, -1))
        if rv.saturation is not None:
            m &= (psp < SATURATION_MARGIN * rv.saturation).all(axis=(0, -1))
        cached = np.zeros((2, 3))
        if m.sum() >= MIN_RATIO_PIXELS:
            psp = psp[:, m]  # (and unclipped)
            v, light = fringe_noise_variance(psp).astype(np.float64), psp.mean(axis=0).astype(np.float64)
            for c in range(3):
                design = np.stack([np.ones_like(light[:, c]), light[:, c]], axis=1)
                a, b = np.linalg.lstsq(design, v[:, c], rcond=None)[0]
                if b < 0:  # no growth with light: the mean variance
                    a, b = float(v[:, c].mean()), 0.0
                elif a < 0:  # no read noise: through the origin
                    a, b = 0.0, float((light[:, c] * v[:, c]).sum() / max((light[:, c] ** 2).sum(), 1e-30))
                cached[:, c] = a, b
        rv._noise_model = cached
    return cached


def _nine_capture_white(rv: RelightView) -> tuple[np.ndarray, np.ndarray]:
    cached = getattr(rv, "_exit_white", None)  # views built elsewhere (the benchmarks' SimView) have no cache yet
    if cached is None:
        cached = rv._exit_white = _white_and_variance(rv)
    return cached


def _white_and_variance(rv: RelightView) -> tuple[np.ndarray, np.ndarray]:
    white = np.asarray(rv.white, np.float32)
    psp, lost = model_inputs(rv)
    a, b = noise_model(rv).astype(np.float32)
    alone = np.maximum(white, 0.0) * b  # the white capture's own variance (a + b L), made in place: 1080p frames
    alone += a
    ok = rv.proj.mask & white_usable(white, rv.white_saturation) & ~lost
    if ok.sum() < MIN_RATIO_PIXELS:
        return white, alone
    light = np.asarray(psp, np.float32)[:, ok].mean(axis=0)  # (n, 3): the decoded pixels only
    offset = 2.0 * light
    ratio = np.median(offset / white[ok], axis=0)  # (3,): the projector's black and gamma, per colour
    if not (np.isfinite(ratio).all() and (ratio > 0).all()):
        return white, alone
    both, variance = white.copy(), alone.copy()
    both[ok] = (white[ok] + PSP_WHITE_WEIGHT * offset / ratio) / (1 + PSP_WHITE_WEIGHT)
    offset_variance = 0.5 * (a + b * np.maximum(light, 0)) / ratio ** 2  # 4 x a mean of 8 frames' variance
    variance[ok] = (alone[ok] + PSP_WHITE_WEIGHT ** 2 * offset_variance) / (1 + PSP_WHITE_WEIGHT) ** 2
    return both, variance


def exit_gain(rv: RelightView, relit_white: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 gain per pixel and colour that makes a model's relighting of the view under full white
    return the view's own white (:func:`exit_white`) as far as that white stands above its noise: ``1 + keep (g - 1)``
    with ``g`` that white over ``relit_white`` (H, W, 3), the model's relighting under a pattern of 1s, on the decoded
    mask where the white capture is usable (:func:`white_usable`) and the relit white above the noise floor (1
    elsewhere; clipped to :data:`EXIT_GAIN_RANGE`), and ``keep`` per colour :func:`noise_shrinkage`'s.

    A model gives each pixel the energy of its own captured light and spreads it by its footprint, so what
    the camera sees at that point only (pigment, surface grain: the texture of the exit) is spread over the
    neighbours and lost where it was. The gain puts it back where light leaves the surface. It is linear in
    the pattern (one map per model and view) and leaves exact footprints as they are (gain 1 up to the
    captures' noise). The white capture alone would copy its own noise into every relit image (measured: 0.9-3.8 dB
    lost on the three-chip demo against the nine-capture white); in low light the nine-capture white's noise is
    the gain's power too (`sss bench stability` lowlight: the decoder 69.2 -> 65.0 dB unshrunk, 68.8 shrunk). Every
    view, its camera's demosaicing or not: with the nine-capture white a Bayer camera's views relight better with it
    too (analytic +1.3 to +4.7 dB against the render on five sim objects, the demo's blend +1.0 / +1.3 dB inside the
    silhouette); with the white capture alone it cost them (demo crab 32.3 -> 24.7 dB)."""
    white = np.asarray(rv.white, np.float32)
    inside = rv.proj.mask & white_usable(white, rv.white_saturation)  # (the rest keeps gain 1: work on these only)
    seen = np.asarray(relit_white, np.float32)[inside]  # (n, 3)
    ok = np.isfinite(seen) & (seen > WHITE_FLOOR)
    seen = np.where(ok, seen, 1.0)
    departure = np.where(ok, np.clip(exit_white(rv)[inside] / seen, *EXIT_GAIN_RANGE) - 1.0, 0.0).astype(np.float32)
    keep = noise_shrinkage(departure, np.where(ok, exit_white_variance(rv)[inside] / (seen * seen), 0.0), ok)
    gain = np.ones(white.shape, np.float32)
    gain[inside] = np.clip(1.0 + keep.astype(np.float32) * departure, *EXIT_GAIN_RANGE)
    return gain


def noise_shrinkage(departure: np.ndarray, noise: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(3,) the share of a gain's departure from 1 to keep, per colour: ``1 - noise / power`` clipped to [0, 1]
    (James-Stein), ``power`` the departure's mean square and ``noise`` its noise variance's mean, both over ``ok``.
    ``departure``, ``noise``, ``ok``: (..., 3), e.g. (H, W, 3) or (n, 3). A departure no larger than its noise is
    dropped, one far above it kept whole (0.93-1.0 on the sim rig's captures at their exposure)."""
    axes = tuple(range(np.ndim(ok) - 1))
    n = np.maximum(np.count_nonzero(ok, axis=axes), 1)
    power = (np.where(ok, departure, 0.0).astype(np.float64) ** 2).sum(axis=axes) / n
    mean_noise = np.where(ok, noise, 0.0).sum(axis=axes, dtype=np.float64) / n
    return np.clip(1.0 - mean_noise / np.maximum(power, 1e-30), 0.0, 1.0)


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
        target = img[pixels[pick, 0], pixels[pick, 1]]
        if torch.is_tensor(out):  # a model's footprints on its device stay there
            out = out.float().clone()
            rows = torch.as_tensor(np.flatnonzero(pick), device=out.device)
            energy = out[rows].sum(dim=(1, 2))  # (n, 3)
            gain = torch.where(energy > WHITE_FLOOR, torch.as_tensor(target, device=out.device)
                               / energy.clamp_min(WHITE_FLOOR), torch.ones_like(energy))
            out[rows] *= gain[:, None, None, :]
            return out
        out = footprint_array(out, writable=True)
        energy = out[pick].sum(axis=(1, 2))  # (n, 3)
        gain = np.where(energy > WHITE_FLOOR, target / np.maximum(energy, WHITE_FLOOR), 1.0)
        out[pick] *= gain[:, None, None, :].astype(np.float32)
        return out

    return rescaled
