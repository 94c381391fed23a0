"""Which footprint source a backend name gives a view (:func:`make_source`, :func:`make_sources` for
blends). The names and the checks that refuse unknown backends or a missing decoder before any work are
in :mod:`~sssphase_core.relight.choices` (no torch), re-exported here."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sssphase_core.errors import DataError, InputError
from sssphase_core.relight.calibration import (
    energy_from_white,
    fit_view_mix,
    mixed_with_no_scattering,
    model_inputs,
    white_usable,
)
from sssphase_core.relight.choices import BLENDS, MODEL_FREE, check_backends, needs_checkpoint, uses_decoder  # noqa: F401
from sssphase_core.relight.engine import FootprintSource
from sssphase_core.relight.sources import backend_source, nearest_measured_source, no_scattering_source
from sssphase_core.relight.transport import denoised_transport
from sssphase_core.relight.views import RelightView


def make_source(name: str, rv: RelightView, *, checkpoint: Path | str | None = None, device: str = "cpu",
                calibrate: bool = True, precision: str = "auto", **options: object) -> tuple[FootprintSource, int]:
    """The footprint source of backend ``name`` for a view -> (source, patch size); ``options`` go to
    the model backend (e.g. ``supersample`` for ``analytic``), ``precision`` to the decoder (``torch``), ``device``
    to both (the analytic model renders its footprints there). A model
    backend's footprints are ``calibrate``-d to the view (:func:`fit_view_mix`) unless told not to."""
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
            smoothings, stored_noise = _transport_record(rv, info)
            if info.get("noise_dropped") and len(smoothings) == 1:  # zeroed with one mask at capture: as stored
                noise = 0.0
            elif info.get("noise_dropped"):  # the union of several masks stored: the view's own captures choose
                noise = stored_noise
            else:
                noise = crop_noise(np.asarray(crops[: min(len(crops), 512)], np.float32)) if len(crops) else 0.0
            pixels, dots = rv.session.load(rv.view, "transport/pixels"), rv.session.load(rv.view, "transport/dots")  # type: ignore[attr-defined]
            _check_transport(rv, pixels, dots, crops)
            from sssphase_core.store.light import light_problem, white_level

            sample = np.asarray(crops[: min(len(crops), 4096)], np.float32)  # (crops of -60000 relit at 16 dB, exit 0)
            problem = light_problem("transport/crops", sample, white_level(rv.white))
            if problem:
                raise DataError(f"{rv.object} view {rv.view}: {problem}: the session's captured transport is damaged")
            return denoised_transport(rv, pixels, dots, crops, noise, smoothings), int(crops.shape[1])
        if "footprints/crops" not in arrays:
            raise InputError(f"{rv.object} view {rv.view} has no captured footprints: capture with --footprints")
        record = rv.session.manifest["views"][str(rv.view)].get("footprints", {})  # type: ignore[attr-defined]
        stride = record.get("dot_stride", 1) if isinstance(record, dict) else None
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:  # (was an internal error)
            raise DataError(f"{rv.object} view {rv.view}: the manifest's footprints record is damaged (dot_stride "
                            f"{str(stride)[:40] if isinstance(record, dict) else 'missing: the record is no table'})")
        if stride > 1:
            raise InputError(f"{rv.object} view {rv.view} was captured with --dot-stride {stride}: its dot grids give "
                             f"footprints to 1/{stride * stride} of the pixels, too few to relight with (they train a "
                             "decoder); capture with --dot-stride 1 for the measured backend")
        from sssphase_core.processing.footprints import transport_weights

        px = np.asarray(rv.session.load(rv.view, "footprints/pixels"), np.int64)  # type: ignore[attr-defined]
        crops = rv.session.read(rv.view, "footprints/crops")  # type: ignore[attr-defined]
        weights = transport_weights(px, rv.proj.xp, rv.proj.yp, rv.proj.mask)
        return nearest_measured_source(px, crops, rv.white, weights), int(crops.shape[1])
    from sssphase_core.learning.backends import accepted_options, get_backend

    if name == "torch":
        needs_checkpoint(name, checkpoint)
        backend = get_backend("torch", checkpoint=checkpoint, device=device, precision=precision,
                              **{"black": rv.proj.black, **options})
    elif name == "analytic":
        backend = get_backend("analytic", **{"patch": rv.patch, "black": rv.proj.black, "device": device, **options})
    else:  # a plugin's: what it takes of what is known of the view
        offered = {"patch": rv.patch, "black": rv.proj.black, "device": device,
                   **({"checkpoint": checkpoint} if checkpoint is not None else {})}
        backend = get_backend(name, **{**accepted_options(name, offered), **options})
    psp, lost = model_inputs(rv)
    source = backend_source(backend, psp)
    usable = white_usable(rv.white, rv.white_saturation)
    if (lost & usable).any():  # fringes beyond repair: the energy from the white capture (reciprocity)
        source = energy_from_white(source, lost & usable, rv.white)
    k = int(backend.patch)
    if calibrate and rv.psp_patterns is not None:
        source = mixed_with_no_scattering(source, fit_view_mix(source, k, rv, psp, lost), rv.white)
    source.backend = backend  # type: ignore[attr-defined]  # what it did, for the narration (domain_line)
    return source, k


#: Most denoising masks a view's transport record may name (the capture stores one to three).
MAX_SMOOTHINGS = 16


def _transport_record(rv: RelightView, info: object) -> tuple[list[float], float]:
    """The manifest's record of a view's captured transport -> (denoising smoothings px, stored noise); a record
    of the wrong types (a hostile or damaged manifest: internal errors, a "-5 px noise mask" used) is refused."""
    def damaged(what: str) -> DataError:
        return DataError(f"{rv.object} view {rv.view}: the manifest's transport record is damaged ({what})")

    if not isinstance(info, dict):
        raise damaged("not a table")
    smoothings = info.get("denoise_smoothing", [1.0])
    if (not isinstance(smoothings, list) or not 1 <= len(smoothings) <= MAX_SMOOTHINGS
            or not all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and 0 < x <= 1e3
                       for x in smoothings)):
        raise damaged(f"denoise_smoothing {str(smoothings)[:60]}: 1 to {MAX_SMOOTHINGS} mask widths in (0, 1000] px")
    noise = info.get("noise", 0.0)
    if isinstance(noise, bool) or not isinstance(noise, int | float) or not (math.isfinite(noise) and noise >= 0):
        raise damaged(f"noise {str(noise)[:40]}")
    return [float(x) for x in smoothings], float(noise)


def _check_transport(rv: RelightView, pixels: np.ndarray, dots: np.ndarray, crops: object) -> None:
    """The transport arrays' indices: camera pixels (y, x) inside the image, projector dots (x, y) inside the
    projector, one per crop (a dot of -1 lit the last column without a word; one of 10^6 was an internal error)."""
    h, w = rv.white.shape[:2]
    wp, hp = (int(v) for v in rv.plan["projector"])  # (checked when the view was loaded)
    n = len(crops)  # type: ignore[arg-type]
    for name, a, (hy, wx), order in (("pixels", pixels, (h, w), "yx"), ("dots", dots, (hp, wp), "xy")):
        a = np.asarray(a)
        if a.ndim != 2 or a.shape[1] != 2 or len(a) != n or not np.issubdtype(a.dtype, np.integer):
            raise DataError(f"{rv.object} view {rv.view}: transport/{name} is {a.shape} {a.dtype}, not {n} whole-number "
                            "pairs (one per crop): the session is damaged")
        y, x = (a[:, 0], a[:, 1]) if order == "yx" else (a[:, 1], a[:, 0])
        if len(a) and not ((y >= 0) & (y < hy) & (x >= 0) & (x < wx)).all():
            where = "camera image" if name == "pixels" else "projector"
            raise DataError(f"{rv.object} view {rv.view}: transport/{name} holds positions outside the {wx}x{hy} "
                            f"{where}: the session is damaged")


def domain_line(rv: RelightView, name: str, source: FootprintSource) -> str | None:
    """One line when the decoder behind ``source`` handed pixels beyond its training widths, or its footprints'
    rings beyond the radius its training crops held light above their noise to, to the analytic model
    (:mod:`sssphase_core.learning.domain`); None otherwise."""
    backend = getattr(source, "backend", None)
    far, total = getattr(backend, "beyond_domain", 0), getattr(backend, "predicted", 0)
    tail = getattr(backend, "tail_applied", None)
    if not total or not (far or tail):
        return None
    said = []
    if far:
        limit = "/".join(f"{x:.1f}" for x in backend.domain.limit)  # type: ignore[union-attr]
        said.append(f"{far:,} of {total:,} pixels ({far / total:.1%}) have footprints wider than the decoder was "
                    f"trained on (R/G/B {limit} px): the analytic model's footprints there")
    if tail:
        said.append(f"footprints from {'/'.join(str(r) for r in tail)} px out (R/G/B) are the analytic model's: its "
                    "training crops' median light was below their noise there")
    return f"{rv.object} view {rv.view}: {name}: " + "; ".join(said)


def make_sources(name: str, rv: RelightView, *, checkpoint: Path | str | None = None, device: str = "cpu",
                 precision: str = "auto", **options: object) -> list[tuple[FootprintSource, int]]:
    """The uncalibrated (source, patch) pairs of backend ``name``: its own, or for a blend
    (:data:`BLENDS`: ``blend`` = the decoder and the analytic model, weighted per view and colour by how
    well they relight the view's own fringe captures) each member's; ``options`` go to the analytic
    member of a blend, ``precision`` to its decoder."""
    if name not in BLENDS:
        return [make_source(name, rv, checkpoint=checkpoint, device=device, calibrate=False, precision=precision,
                            **options)]
    needs_checkpoint(name, checkpoint)
    return [make_source(m, rv, checkpoint=checkpoint, device=device, calibrate=False, precision=precision,
                        **(options if m == "analytic" else {})) for m in BLENDS[name]]
