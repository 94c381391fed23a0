"""The one call that relights a view (:func:`relight_view`): the user's patterns and the view calibration
in one footprint pass, blends included; and its fast twin from cached eigen-footprints (:func:`relight_lowrank`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import white as full_white
from sssphase_core.relight.calibration import (
    exit_gain,
    exit_white,
    local_mixture,
    model_inputs,
)
from sssphase_core.relight.choices import WIDEN_MAX, WIDEN_MEMBERS
from sssphase_core.relight.engine import FootprintSource, calibration_members, relight
from sssphase_core.relight.lowrank import LowRankFootprints
from sssphase_core.relight.sources import no_scattering_source
from sssphase_core.relight.views import RelightView


def relight_view(source: FootprintSource, patch: int, rv: RelightView, patterns: list[np.ndarray], *,
                 calibrate: bool, also: Sequence[tuple[FootprintSource, int]] = (), chunk: int = 2048,
                 device: str = "cpu", progress: Callable[[int, int], None] | None = None,
                 calibration: list[tuple[np.ndarray, np.ndarray]] | None = None, widen: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Relight a view under ``patterns`` (P of (Hp, Wp[, 3])) with an uncalibrated ``source``
    (``make_source(..., calibrate=False)``) -> ((P, H, W, 3) images, view-wide per-colour mix (3,) or None).

    With ``calibrate`` (and the view's PSP patterns known) each model's images are first made consistent with
    the view's white (the white capture and the PSP frames' offset: :func:`white_consistent`; the white pattern
    rides on the same pass), and the view calibration of
    :func:`fit_view_mix` rides on it too: the 8 PSP patterns are splatted beside the user's, and since relighting
    is linear in the footprints the mixed source's images are ``mix * model + (1 - mix) * none``, with the mix
    refined per pixel (:func:`local_mixture`). One pass instead of two (each footprint is predicted once).

    ``also``: more (source, patch) pairs blended in by the same fit: the images are
    ``sum_i mix_i * source_i + (1 - sum_i mix_i) * none``, each ``mix_i`` refined per pixel too, and the
    view-wide mix returned is (1 + len(also), 3). Blending needs ``calibrate``.

    ``calibration``: a list that receives the fit's (per-pixel weights (S, H, W, 3), view-wide weights (S, 3), each
    source's gain (S, H, W, 3), the no-scattering term's white (H, W, 3)), which relight any other pattern the same
    way (:func:`relight_lowrank`); with ``widen``, ``source`` is four members (stretched along x, y and both, softened).

    ``widen`` (> 1, with ``calibrate``): ``source``'s footprints join the fit not as they are but as four members
    (:func:`~sssphase_core.relight.engine.calibration_members`, splatted in the same pass): stretched by that factor
    along x, along y and along both, so that the view's two fringe orientations can widen them along either axis or
    both, and softened at their own width (a core softer than the model's); any of them narrows toward no scattering.
    The view-wide mix returned gives the members' weights together. The ``also`` sources join as they are (a blend stretches its
    decoder, whose widths are a prediction, and not the analytic model, whose widths the same fringes fit: stretched
    too, it cost volumetric stand-ins 1.1 to 1.4 dB).
    """
    calibrate = calibrate and rv.psp_patterns is not None
    if also and not calibrate:
        raise InputError(f"{rv.object} view {rv.view}: blending sources needs the view calibration (the projector "
                         "patterns of its PSP captures, and calibration on)")
    if widen is not None and not (1.0 < widen <= WIDEN_MAX):
        raise InputError(f"widen {widen}: the stretch of each model's footprints must be above 1 and at most {WIDEN_MAX:g}")
    n = len(patterns)
    every = list(patterns) + (list(rv.psp_patterns) if calibrate else [])
    under_white = [full_white(*rv.proj.projector_size)] if calibrate else []  # (white_consistent reads it)
    members = calibration_members(widen) if calibrate and widen else ()
    relits = [relight(src, rv.proj, every + under_white, k, white=rv.white, chunk=chunk, device=device, progress=progress,
                      variants=members if i == 0 else (), plain=not (members and i == 0))
              for i, (src, k) in enumerate(((source, patch), *also))]
    if not calibrate:
        return relits[0], None
    if members:  # the source's members' images (stretched along x, y and both, softened), then the others': in that order
        relits = [*relits[0], *relits[1:]]
    relits, gains = zip(*(white_consistent(rv, r) for r in relits), strict=True)
    psp, lost = model_inputs(rv)
    none = relight(no_scattering_source(exit_white(rv)), rv.proj, every, 1, white=rv.white)
    # each source's weight refined pixel by pixel where the view's own fringes say so
    weights, view_weights = local_mixture(rv, [r[n:] for r in relits], none[n:], psp, lost)
    if calibration is not None:
        calibration.append((weights, view_weights, np.stack(gains), exit_white(rv)))
    images = mix_images(none[:n], [r[:n] for r in relits], weights)
    view_weights = split_stretches(view_weights, bool(members))[0]
    return images, (view_weights[0] if not also else view_weights)


def split_stretches(view_weights: np.ndarray, stretched: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """A calibration's view-wide weights (S, 3), the first source as its members (stretched along x, y and both,
    softened) where ``stretched`` (:func:`relight_view`'s ``widen``), each other source one member -> (each source's
    weight (M, 3), each of the first source's members' share of it (4 members, 3 colours), or None unstretched)."""
    if not stretched:
        return view_weights, None
    weights = np.asarray(view_weights)
    first = weights[: len(WIDEN_MEMBERS)]
    return np.concatenate([first.sum(axis=0, keepdims=True), weights[len(WIDEN_MEMBERS):]]), first


def white_consistent(rv: RelightView, relit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A model's images (P + 1, H, W, 3), the last one relit under full white -> (the first P times the model's
    :func:`~sssphase_core.relight.calibration.exit_gain` (in place), that gain (H, W, 3)): relit under white, the
    model returns the view's nine-capture white (:func:`~sssphase_core.relight.calibration.exit_white`) as far as
    that white stands above its noise."""
    gain = exit_gain(rv, relit[-1])
    images = relit[:-1]
    images *= gain
    return images, gain


def mix_images(none: np.ndarray, relits: Sequence[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """The calibrated images ``none + sum_i weights_i * (relit_i - none)``: (P, H, W, 3) each, ``weights``
    (S, H, W, 3) for the S ``relits``."""
    images = none.copy()
    for weight, relit in zip(weights, relits, strict=True):
        images += weight * (relit - none)
    return images


def relight_lowrank(rv: RelightView, members: Sequence[LowRankFootprints], weights: np.ndarray, gains: np.ndarray,
                    white: np.ndarray, patterns: list[np.ndarray]) -> np.ndarray:
    """:func:`relight_view`'s calibrated images under new ``patterns`` from its eigen-footprints (one
    :class:`~sssphase_core.relight.lowrank.LowRankFootprints` per source), its calibration's per-pixel ``weights``
    (S, H, W, 3), each source's gain ``gains`` (S, n, 3) and the no-scattering term's ``white`` (n, 3) at the view's
    n decoded pixels (:func:`~sssphase_core.relight.lowrank.load_lowrank`), with no footprint computed -> (P, H, W, 3)."""
    mask = rv.proj.mask
    none_white = np.array(rv.white, np.float32)
    none_white[mask] = white
    none = relight(no_scattering_source(none_white), rv.proj, patterns, 1, white=rv.white)
    relits = []
    for member, gain in zip(members, gains, strict=True):
        images = member.relight(rv.proj, list(patterns), white=rv.white)
        images[:, mask] *= gain
        relits.append(images)
    return mix_images(none, relits, weights)
