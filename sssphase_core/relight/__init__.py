"""Relighting by footprint splatting: I(q) = sum_p PSF_p(q - p) * c(p), with c(p) = L(pi(p)).

The footprint of every lit surface pixel is produced once per chunk (by a network, an analytic model,
measured captures or the simulator) and splatted for all requested patterns at once, so several
patterns share the footprint cost and footprints are never all held in memory.

Only pixels that are valid *and* receive light from at least one pattern are evaluated. The
projector's black level lights every pixel weakly; its contribution is ``black * white`` (the
captured white image is the sum of all footprints at unit light), so it costs nothing per pixel.

One job per module, imports flowing one way (down this list; the ``layers`` contract in
``pyproject.toml`` holds it):

* :mod:`~sssphase_core.relight.runner`: a session relit, its geometry or its evaluation, as the CLI
  (and any other front end) runs them, narration through callbacks (:func:`relight_session`);
* :mod:`~sssphase_core.relight.evaluation`: relit images against reference captures;
  :mod:`~sssphase_core.relight.geometry`: the decoded points with the footprints' scattering shift
  removed, for 3D (relighting keeps the decoded ones);
* :mod:`~sssphase_core.relight.pipeline`: the one call that relights a view (:func:`relight_view`);
  :mod:`~sssphase_core.relight.backends`: the source a backend name gives a view (:func:`make_source`);
* :mod:`~sssphase_core.relight.calibration`: the view calibration (:func:`fit_view_mix`,
  :func:`local_mixture`); :mod:`~sssphase_core.relight.cache`: :class:`FootprintCache`;
  :mod:`~sssphase_core.relight.lowrank`: a view's footprints as eigen-footprints, a new pattern in seconds;
* :mod:`~sssphase_core.relight.transport`: the captured light transport (:class:`DotTransport`);
* :mod:`~sssphase_core.relight.sources`: where footprints come from (no scattering, a model, crops);
* :mod:`~sssphase_core.relight.views`: a session view as relighting reads it (:func:`load_view`);
* :mod:`~sssphase_core.relight.images`: relit images out, projector patterns in;
  :mod:`~sssphase_core.relight.engine`: the splat (:func:`relight`, :class:`Splatter`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what type checkers and IDEs see; at run time each name loads when first used
    from sssphase_core.processing.colour import display_scale, srgb
    from sssphase_core.processing.projector import emitted_light, sample_projector
    from sssphase_core.relight.backends import make_source, make_sources
    from sssphase_core.relight.cache import FootprintCache
    from sssphase_core.relight.calibration import (
        batched_mixture_weights,
        energy_from_white,
        fit_view_mix,
        local_mixture,
        mixed_with_no_scattering,
        mixture_weights,
        model_inputs,
        view_mix,
        view_mixture,
        white_usable,
    )
    from sssphase_core.relight.choices import (
        BLENDS,
        MODEL_FREE,
        check_backends,
        needs_checkpoint,
        uses_decoder,
    )
    from sssphase_core.relight.engine import (
        FOLD_BAND_BYTES,
        FootprintSource,
        Projection,
        Splatter,
        TransportColumns,
        crop_footprints,
        lit_pixels,
        relight,
    )
    from sssphase_core.relight.geometry import geometric_correspondence, scattering_shift
    from sssphase_core.relight.images import (
        IMAGE_FORMATS,
        RESIZE_MODES,
        check_image_formats,
        read_pattern,
        write_images,
    )
    from sssphase_core.relight.pipeline import relight_view
    from sssphase_core.relight.sources import (
        WHITE_FLOOR,
        backend_source,
        nearest_measured_source,
        no_scattering_source,
    )
    from sssphase_core.relight.transport import DotTransport, denoised_transport
    from sssphase_core.relight.views import RelightView, finest_psp_period, load_view

#: Each public name -> the module that defines it; imported on first use (PEP 562), so that a front end's
#: checks (``relight.runner``'s) do not pull torch in before they refuse bad input.
_WHERE: dict[str, str] = {
    "BLENDS": "sssphase_core.relight.choices",
    "DotTransport": "sssphase_core.relight.transport",
    "FOLD_BAND_BYTES": "sssphase_core.relight.engine",
    "FootprintCache": "sssphase_core.relight.cache",
    "FootprintSource": "sssphase_core.relight.engine",
    "IMAGE_FORMATS": "sssphase_core.relight.images",
    "MODEL_FREE": "sssphase_core.relight.choices",
    "Projection": "sssphase_core.relight.engine",
    "RESIZE_MODES": "sssphase_core.relight.images",
    "RelightView": "sssphase_core.relight.views",
    "Splatter": "sssphase_core.relight.engine",
    "TransportColumns": "sssphase_core.relight.engine",
    "WHITE_FLOOR": "sssphase_core.relight.sources",
    "backend_source": "sssphase_core.relight.sources",
    "batched_mixture_weights": "sssphase_core.relight.calibration",
    "check_backends": "sssphase_core.relight.choices",
    "check_image_formats": "sssphase_core.relight.images",
    "crop_footprints": "sssphase_core.relight.engine",
    "denoised_transport": "sssphase_core.relight.transport",
    "display_scale": "sssphase_core.processing.colour",
    "emitted_light": "sssphase_core.processing.projector",
    "energy_from_white": "sssphase_core.relight.calibration",
    "finest_psp_period": "sssphase_core.relight.views",
    "fit_view_mix": "sssphase_core.relight.calibration",
    "geometric_correspondence": "sssphase_core.relight.geometry",
    "lit_pixels": "sssphase_core.relight.engine",
    "load_view": "sssphase_core.relight.views",
    "local_mixture": "sssphase_core.relight.calibration",
    "make_source": "sssphase_core.relight.backends",
    "make_sources": "sssphase_core.relight.backends",
    "mixed_with_no_scattering": "sssphase_core.relight.calibration",
    "mixture_weights": "sssphase_core.relight.calibration",
    "model_inputs": "sssphase_core.relight.calibration",
    "nearest_measured_source": "sssphase_core.relight.sources",
    "needs_checkpoint": "sssphase_core.relight.choices",
    "no_scattering_source": "sssphase_core.relight.sources",
    "read_pattern": "sssphase_core.relight.images",
    "relight": "sssphase_core.relight.engine",
    "relight_view": "sssphase_core.relight.pipeline",
    "sample_projector": "sssphase_core.processing.projector",
    "scattering_shift": "sssphase_core.relight.geometry",
    "srgb": "sssphase_core.processing.colour",
    "uses_decoder": "sssphase_core.relight.choices",
    "view_mix": "sssphase_core.relight.calibration",
    "view_mixture": "sssphase_core.relight.calibration",
    "white_usable": "sssphase_core.relight.calibration",
    "write_images": "sssphase_core.relight.images",
}

__all__ = ["BLENDS", "DotTransport", "FOLD_BAND_BYTES", "FootprintCache", "FootprintSource", "IMAGE_FORMATS",
    "MODEL_FREE", "Projection", "RESIZE_MODES", "RelightView", "Splatter", "TransportColumns", "WHITE_FLOOR",
    "backend_source", "batched_mixture_weights", "check_backends", "check_image_formats", "crop_footprints",
    "denoised_transport", "display_scale", "emitted_light", "energy_from_white", "finest_psp_period", "fit_view_mix",
    "geometric_correspondence", "lit_pixels", "load_view", "local_mixture", "make_source", "make_sources",
    "mixed_with_no_scattering", "mixture_weights", "model_inputs", "nearest_measured_source", "needs_checkpoint",
    "no_scattering_source", "read_pattern", "relight", "relight_view", "sample_projector", "scattering_shift",
    "srgb", "uses_decoder", "view_mix", "view_mixture", "white_usable", "write_images"
]


def __getattr__(name: str) -> Any:
    try:
        module = _WHERE[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_WHERE})
