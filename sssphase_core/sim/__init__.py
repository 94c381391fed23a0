"""Physically based simulated projector-camera rig (numpy/scipy only; never imports torch).

A pinhole camera and a verged pinhole projector look at a procedural object on a turntable.
Surfaces are sphere-traced signed-distance functions with spatially varying materials; light
transport is a per-pixel Christensen-Burley normalized-diffusion footprint (or, per rig, the
directional dipole, whose footprints depend on the incidence direction) plus a direct term, so
one linear operator renders any projector pattern and the exact footprints are available.

Modules: ``rig`` (pinholes, poses, presets), ``geometry`` (SDF primitives, sphere tracing),
``materials`` (Jensen 2001 -> Burley), ``dipole`` (the directional dipole), ``objects`` (the
catalogue), ``transport`` (footprints, splatting), ``sensor`` (noise, Bayer, bit depth), ``scene`` (:class:`SimScene`), ``bench`` (speed).
"""

from sssphase_core.errors import UnknownObjectError
from sssphase_core.sim.materials import JENSEN_2001, MATERIAL_NAMES, MATERIALS, Material
from sssphase_core.sim.objects import (
    CALIBRATION_OBJECTS,
    CATALOGUE,
    EXTRA_OBJECTS,
    TRAIN_OBJECTS,
    UNSEEN_OBJECTS,
    MaterialSample,
    SimObject,
    get_object,
)
from sssphase_core.sim.rig import (
    ANISOTROPY_RANGE,
    MAX_VIEWS,
    RANDOMISED_RANGES,
    TRANSPORTS,
    Pinhole,
    ProjectorModel,
    RigConfig,
    anisotropy_option,
    make_rig,
    randomised_rig_options,
    rig_from_options,
    rig_preset,
    session_rig_calibration,
    stereo_calibration,
    with_projector_response,
    with_transport,
)
from sssphase_core.sim.scene import SimScene
from sssphase_core.sim.sensor import SensorConfig

__all__ = [
    "CATALOGUE",
    "CALIBRATION_OBJECTS",
    "EXTRA_OBJECTS",
    "JENSEN_2001",
    "MATERIALS",
    "MATERIAL_NAMES",
    "ANISOTROPY_RANGE",
    "MAX_VIEWS",
    "TRAIN_OBJECTS",
    "UNSEEN_OBJECTS",
    "Material",
    "MaterialSample",
    "RANDOMISED_RANGES",
    "TRANSPORTS",
    "anisotropy_option",
    "Pinhole",
    "ProjectorModel",
    "RigConfig",
    "SensorConfig",
    "SimObject",
    "SimScene",
    "UnknownObjectError",
    "get_object",
    "make_rig",
    "randomised_rig_options",
    "rig_from_options",
    "rig_preset",
    "session_rig_calibration",
    "stereo_calibration",
    "with_projector_response",
    "with_transport",
]
