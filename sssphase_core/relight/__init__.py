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
* :mod:`~sssphase_core.relight.transport`: the captured light transport (:class:`DotTransport`);
* :mod:`~sssphase_core.relight.sources`: where footprints come from (no scattering, a model, crops);
* :mod:`~sssphase_core.relight.views`: a session view as relighting reads it (:func:`load_view`);
* :mod:`~sssphase_core.relight.images`: relit images out, projector patterns in;
  :mod:`~sssphase_core.relight.engine`: the splat (:func:`relight`, :class:`Splatter`).
"""

from sssphase_core.processing.colour import display_scale, srgb
from sssphase_core.processing.projector import emitted_light, sample_projector
from sssphase_core.relight.backends import (
    BLENDS,
    MODEL_FREE,
    check_backends,
    make_source,
    make_sources,
    needs_checkpoint,
    uses_decoder,
)
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

__all__ = [
    "BLENDS", "batched_mixture_weights", "check_backends", "denoised_transport", "local_mixture", "needs_checkpoint", "uses_decoder", "FOLD_BAND_BYTES", "IMAGE_FORMATS", "MODEL_FREE", "RESIZE_MODES", "WHITE_FLOOR", "DotTransport", "FootprintCache",
    "FootprintSource", "Projection", "TransportColumns", "RelightView", "Splatter", "backend_source", "check_image_formats",
    "crop_footprints", "display_scale", "emitted_light", "energy_from_white", "finest_psp_period", "fit_view_mix",
    "geometric_correspondence", "lit_pixels", "load_view",
    "make_source", "make_sources", "mixed_with_no_scattering", "model_inputs", "nearest_measured_source", "no_scattering_source", "read_pattern", "relight", "relight_view",
    "mixture_weights", "sample_projector", "scattering_shift", "srgb", "view_mix", "view_mixture", "white_usable",
    "write_images",
]
