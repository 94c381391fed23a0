"""One pixel of a session view as a front end shows it when a user clicks it: its PSP patch (what the
model sees) and its footprint from every source the view has (the captured crop, the analytic model, the
decoder, the simulator's exact one), each the model's own (not calibrated to the view)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sssphase_core.errors import InputError


@dataclass
class PixelProbe:
    """``patch``: (8, K, K, 3) the PSP frames around the pixel; ``footprints``: source name -> (K, K, 3)
    linear light around it; ``skipped``: source name -> why it has none here."""

    pixel: tuple[int, int]  # (y, x)
    valid: bool
    projector: tuple[float, float]  # decoded (xp, yp), NaN where invalid
    patch: np.ndarray
    footprints: dict[str, np.ndarray] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)


def probe_pixel(rv: object, pixel: tuple[int, int], *, checkpoint: Path | str | None = None,
                sources: dict[str, object] | None = None) -> PixelProbe:
    """``rv`` a :class:`~sssphase_core.relight.views.RelightView`; ``sources`` caches the model sources
    made for it (name -> footprint source), so that the next pixel costs one footprint each."""
    from sssphase_core.relight.backends import make_source
    from sssphase_core.relight.engine import footprint_array

    y, x = (int(v) for v in pixel)
    h, w = rv.proj.shape  # type: ignore[attr-defined]
    if not (0 <= y < h and 0 <= x < w):
        raise InputError(f"pixel ({x}, {y}) is outside the {w}x{h} view")
    k = int(rv.patch)  # type: ignore[attr-defined]
    psp = np.asarray(rv.psp, np.float32)  # type: ignore[attr-defined]  (8, H, W, 3)
    pad = k // 2
    padded = np.pad(psp, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    patch = padded[:, y:y + k, x:x + k]
    valid = bool(rv.proj.mask[y, x])  # type: ignore[attr-defined]
    out = PixelProbe((y, x), valid, (float(rv.proj.xp[y, x]), float(rv.proj.yp[y, x])), patch)  # type: ignore[attr-defined]
    crop = _captured_crop(rv, y, x)
    if crop is not None:
        out.footprints["captured"] = crop
    else:
        out.skipped["captured"] = "the view holds no dot-grid crop of this pixel"
    cache = sources if sources is not None else {}
    names = ["analytic", *(["torch"] if checkpoint is not None else []), *(["exact"] if rv.sim is not None else [])]  # type: ignore[attr-defined]
    if checkpoint is None:
        out.skipped["torch"] = "no decoder checkpoint given"
    for name in names:
        if not valid and name != "exact":
            out.skipped[name] = "the pixel has no decoded correspondence"
            continue
        if name not in cache:
            cache[name] = make_source(name, rv, checkpoint=checkpoint, calibrate=False)  # type: ignore[arg-type]
        source, size = cache[name]  # type: ignore[misc]
        fp = footprint_array(source(np.array([[y, x]])))[0]
        out.footprints[name] = _centre(fp, size, k)
    return out


def _captured_crop(rv: object, y: int, x: int) -> np.ndarray | None:
    session, view = rv.session, rv.view  # type: ignore[attr-defined]
    if "footprints/crops" not in session.arrays(view):
        return None
    pixels = np.asarray(session.load(view, "footprints/pixels"), np.int64)
    rows = np.flatnonzero((pixels[:, 0] == y) & (pixels[:, 1] == x))
    if not len(rows):
        return None
    return np.asarray(session.read(view, "footprints/crops")[int(rows[0])], np.float32)


def _centre(fp: np.ndarray, size: int, k: int) -> np.ndarray:
    """A footprint of ``size`` brought to ``k`` x ``k`` around its centre (cropped or zero-padded)."""
    if size == k:
        return fp
    if size > k:
        o = (size - k) // 2
        return fp[o:o + k, o:o + k]
    o = (k - size) // 2
    out = np.zeros((k, k, fp.shape[-1]), np.float32)
    out[o:o + size, o:o + size] = fp
    return out
