"""What a live view shows of the rig, computed here so that every front end (``sss view``, a notebook)
shows the same: a frame's exposure statistics, the projector patterns a user can put up, and a PSP set
decoded as it arrives (the mask, the fringe modulation against the level where decoding fails, the
reason codes).

The frames come from the daemon (:meth:`DaemonClient.capture` with the specs made here); nothing here
talks to a device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sssphase_core.capture.plan import RigSpec
from sssphase_core.errors import InputError

#: The patterns a live view projects by name: (PlannedFrame kind, params beyond the projector size).
LIVE_PATTERNS: dict[str, tuple[str, dict[str, Any]]] = {
    "white": ("white", {}),
    "black": ("black", {}),
    "grey": ("level", {"value": 0.5}),
    "checkerboard": ("ref", {"name": "checkerboard", "square": 32}),
    "stripes_x": ("ref", {"name": "stripes_x", "period": 32.0, "orientation": "x"}),
    "stripes_y": ("ref", {"name": "stripes_y", "period": 32.0, "orientation": "y"}),
    "dots": ("dots", {"spacing": 32, "shift_x": 0, "shift_y": 0}),
}
#: Histogram bins of :func:`frame_stats` over [0, 1] of the camera's range (above: the last bin).
HIST_BINS = 64


def pattern_spec(name: str, projector_size: tuple[int, int], *, exposure: float = 1.0, psp_frame: int = 0,
                 image: np.ndarray | None = None, gain: float | None = None) -> dict[str, Any]:
    """The daemon's frame spec that shows ``name`` (a :data:`LIVE_PATTERNS` name, ``psp`` (frame
    ``psp_frame`` of the capture plan's PSP set) or ``image``, an uploaded ``(H, W[, 3])`` float32 in
    [0, 1] at the projector's size) at relative ``exposure`` (and the camera's ``gain``, when given)."""
    spec = _pattern_spec(name, projector_size, exposure, psp_frame, image)
    if gain is not None:
        if not (isinstance(gain, int | float) and 0 <= gain <= 1e3):
            raise InputError(f"gain must be a number in [0, 1000] (the camera's unit), got {gain!r}")
        spec["gain"] = float(gain)
    return spec


def _pattern_spec(name: str, projector_size: tuple[int, int], exposure: float, psp_frame: int,
                  image: np.ndarray | None) -> dict[str, Any]:
    w, h = projector_size
    if not (isinstance(exposure, int | float) and 1e-3 <= exposure <= 1e3):
        raise InputError(f"exposure must be a number in [0.001, 1000] (relative to the rig's), got {exposure!r}")
    if name == "image":
        if image is None or image.shape[:2] != (h, w):
            raise InputError(f"an image to project must be {w}x{h} (the projector's size)")
        img = np.ascontiguousarray(image, np.float32)
        return {"name": "live/image", "key": "live/image", "kind": "image", "exposure": float(exposure), "params": {},
                "image": {"dtype": img.dtype.str, "shape": list(img.shape), "data": img.tobytes()}}
    if name == "psp":
        frames = psp_set(projector_size)
        if not 0 <= psp_frame < len(frames):
            raise InputError(f"the PSP set has frames 0..{len(frames) - 1}, got {psp_frame}")
        return {**frames[psp_frame], "exposure": float(exposure)}
    if name not in LIVE_PATTERNS:
        raise InputError(f"unknown pattern {name!r}; choose {', '.join([*LIVE_PATTERNS, 'psp', 'image'])}")
    kind, params = LIVE_PATTERNS[name]
    return {"name": f"live/{name}", "key": f"live/{name}", "kind": kind, "exposure": float(exposure),
            "params": {"width": w, "height": h, **params}}


def psp_set(projector_size: tuple[int, int], gamma: float | None = None) -> list[dict[str, Any]]:
    """The frame specs of one decodable set, as a capture takes it: the plan's PSP frames, white and black."""
    import json

    from sssphase_core.processing.patterns import DEFAULT_GAMMA, capture_plan

    plan = capture_plan(*projector_size, references=("white", "black"), gamma=gamma or DEFAULT_GAMMA)
    return [f for f in json.loads(plan.to_json())["frames"] if f["kind"] in ("psp", "white", "black")]


@dataclass
class FrameStats:
    """A frame's exposure at a glance: per-channel histograms over the camera's range, the clipped share."""

    mean: list[float]  # per channel, in [0, 1] of the camera's range
    histogram: list[list[int]]  # (C, HIST_BINS)
    clipped: float  # share of pixels with some channel at or above ``clip``
    clip: float  # in the frame's units (on the sensor, linear)


#: A sample this close to the camera's clipping level counts as clipped (demosaicing and the median spread a
#: clipped sample over its neighbours a little below the level).
CLIP_FRACTION = 0.98


def sensor_full_scale(rig: RigSpec) -> float:
    """Where ``rig``'s camera clips, on the sensor in linear units of the reference exposure (a frame developed
    at exposure e, times e): the rig file's ``[processing] saturation``, else the sim camera's full well, else 1
    (the developed range of a camera whose white scale is its full scale)."""
    if rig.saturation is not None:
        return float(rig.saturation)
    if rig.is_sim:
        from sssphase_core.sim import rig_preset

        return float(rig_preset(rig.options.get("preset", "cpu")).sensor.saturation(1.0))
    return 1.0


def frame_stats(image: np.ndarray, full_scale: float = 1.0) -> FrameStats:
    """``image`` (H, W, 3) linear on the sensor, clipping at ``full_scale`` -> :class:`FrameStats` (histograms
    and means in [0, 1] of that range; clipped: some channel at or above :data:`CLIP_FRACTION` of it)."""
    img = np.asarray(image, np.float32) / np.float32(full_scale)
    img = img[..., None] if img.ndim == 2 else img
    hist = [np.histogram(np.clip(img[..., c], 0, 1), bins=HIST_BINS, range=(0, 1))[0].tolist() for c in range(img.shape[-1])]
    return FrameStats([float(v) for v in img.reshape(-1, img.shape[-1]).mean(axis=0)], hist,
                      float((img >= CLIP_FRACTION).any(axis=-1).mean()), CLIP_FRACTION * float(full_scale))


def develop_live(frame: Any, rig: RigSpec) -> np.ndarray:
    """A received frame (raw Bayer or colour) -> linear RGB (H, W, 3), as the capture develops it."""
    from sssphase_core.capture.processing import develop_frame

    meta = frame.header.get("meta", {})
    return develop_frame(frame.data, rig, float(frame.header.get("exposure", 1.0)), meta.get("bayer"), meta)


@dataclass
class LiveDecode:
    """One PSP set decoded: ``mask`` (H, W) bool, ``modulation`` (H, W) fringe amplitude B, ``reason`` (H, W)
    uint8 codes (:class:`~sssphase_core.processing.psp.Reason`), the ``threshold`` under which B fails,
    per-reason pixel counts, and the projector point of each pixel (``xp``, ``yp``: (H, W) projector px, NaN
    outside ``mask``) for depth."""

    mask: np.ndarray
    modulation: np.ndarray
    reason: np.ndarray
    threshold: float
    coverage: dict[str, int]
    xp: np.ndarray
    yp: np.ndarray


def decode_set(images: dict[str, np.ndarray], projector_size: tuple[int, int], bayer: str | None = None,
               saturation: float | None = None) -> LiveDecode:
    """Decode the developed images of one :func:`psp_set` (keyed by the specs' ``key``); a pixel with a PSP sample at
    or above ``saturation`` (the images' units; None: not checked) is ``SATURATED``."""
    from sssphase_core.processing import psp
    from sssphase_core.processing.patterns import capture_plan

    plan = capture_plan(*projector_size, references=("white", "black"))
    corr = psp.decode_camera(images, plan.psp, projector_size, bayer=bayer,  # (every fringe set: the unwrapping ladder too)
                             saturation=saturation)
    threshold = 0.01  # psp.decode's min_modulation
    return LiveDecode(corr.mask.copy(), corr.modulation.astype(np.float32), corr.reason.astype(np.uint8), threshold,
                      corr.coverage(), np.where(corr.mask, corr.xp, np.nan).astype(np.float32),
                      np.where(corr.mask, corr.yp, np.nan).astype(np.float32))
