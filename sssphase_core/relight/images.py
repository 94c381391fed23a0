"""Relit images out (16-bit linear PNG, float32 EXR, a display PNG); patterns in: :mod:`sssphase_core.store.imageio`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.processing.colour import display_scale, srgb
from sssphase_core.store.imageio import RESIZE_MODES, read_pattern

__all__ = ["IMAGE_FORMATS", "RESIZE_MODES", "check_image_formats", "read_pattern", "write_images"]

IMAGE_FORMATS = ("png", "exr")


def check_image_formats(formats: tuple[str, ...]) -> tuple[str, ...]:
    """``formats`` if each is one of :data:`IMAGE_FORMATS` (and there is one), else an InputError."""
    unknown = sorted(set(formats) - set(IMAGE_FORMATS)) or ([] if formats else ["(none)"])
    if unknown:
        raise InputError(f"unknown image format {', '.join(unknown)}: choose png, exr or png,exr")
    return formats


def write_images(stem: Path | str, image: np.ndarray, *, scale: float | None = None,
                 formats: tuple[str, ...] = ("png",)) -> list[Path]:
    """Write the relit ``image`` (H, W, 3) linear camera units; returns the paths.

    ``png``: ``stem.png``, 16-bit linear (65535 = 1.0 camera unit, brighter values clip);
    ``exr``: ``stem.exr``, float32 unclipped (OpenEXR bindings). Always ``stem_display.png`` (sRGB,
    exposure ``scale``, e.g. one per view from its white capture so that its patterns compare, or else
    the image's own 99.5th percentile) for looking at.
    """
    from sssphase_core.store import exr

    check_image_formats(formats)
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, np.float32)
    finite = np.nan_to_num(img)
    bgr = finite[..., ::-1] if finite.ndim == 3 else finite
    paths = []
    if "exr" in formats:  # stem + ".exr", not with_suffix: a dot in an object or pattern name is no suffix
        paths.append(exr.write_exr(stem.with_name(stem.name + ".exr"), img, attributes={"units": "linear camera units"}))
    if "png" in formats:
        paths.append(_imwrite(stem.with_name(stem.name + ".png"), np.round(np.clip(bgr, 0, 1) * 65535).astype(np.uint16)))
    s = scale if scale is not None else display_scale(finite)
    paths.append(_imwrite(stem.with_name(stem.name + "_display.png"), np.round(srgb(bgr / s) * 255).astype(np.uint8)))
    return paths


def _imwrite(path: Path, image: np.ndarray) -> Path:
    """Encode ``image`` in memory (``cv2.imencode``, the format from ``path``'s suffix) and write it under a
    temporary name renamed once complete; a failed write (a full disk, a name too long, no permission) is one line
    naming the file and the cause (no libpng message on stderr: nothing is encoded into a file)."""
    import cv2

    from sssphase_core.store.files import write_bytes

    try:
        ok, encoded = cv2.imencode(path.suffix, image)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(f"could not encode {path.name} as {path.suffix} ({image.dtype}, shape {image.shape})")
    try:
        write_bytes(path, encoded.tobytes())  # a full disk leaves the old file (or none), never half of one
    except OSError as exc:
        raise InputError(f"could not write {path}: {exc.strerror or exc}") from None
    return path
