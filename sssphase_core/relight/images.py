"""Relit images out (16-bit linear PNG, float32 EXR, a display PNG) and projector patterns in."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from sssphase_core.colour import display_scale, srgb
from sssphase_core.errors import InputError

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
    exposure ``scale`` or the 99.5th percentile) for looking at.
    """
    import cv2

    from sssphase_core import exr

    check_image_formats(formats)
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, np.float32)
    finite = np.nan_to_num(img)
    bgr = finite[..., ::-1] if finite.ndim == 3 else finite
    paths = []
    if "exr" in formats:
        paths.append(exr.write_exr(stem.with_suffix(".exr"), img, attributes={"units": "linear camera units"}))
    if "png" in formats:
        paths.append(stem.with_suffix(".png"))
        cv2.imwrite(str(paths[-1]), np.round(np.clip(bgr, 0, 1) * 65535).astype(np.uint16))
    s = scale if scale is not None else display_scale(finite)
    paths.append(stem.with_name(stem.name + "_display.png"))
    cv2.imwrite(str(paths[-1]), np.round(srgb(bgr / s) * 255).astype(np.uint8))
    return paths


RESIZE_MODES = ("fit", "fill", "stretch")


def _resized(img, size: tuple[int, int], mode: str):
    """A PIL image brought to ``size`` (W, H): ``stretch`` ignores the aspect ratio, ``fit`` scales it
    inside and pads with black, ``fill`` scales it to cover and crops the centre."""
    from PIL import Image

    wp, hp = size
    if mode == "stretch":
        return img.resize((wp, hp), Image.Resampling.BILINEAR)
    w, h = img.size
    k = min(wp / w, hp / h) if mode == "fit" else max(wp / w, hp / h)
    scaled = img.resize((max(1, round(w * k)), max(1, round(h * k))), Image.Resampling.BILINEAR)
    canvas = Image.new(scaled.mode, (wp, hp))
    canvas.paste(scaled, ((wp - scaled.size[0]) // 2, (hp - scaled.size[1]) // 2))
    return canvas


def read_pattern(path: Path | str, projector_size: tuple[int, int], *, resize: str | bool = "") -> np.ndarray:
    """A pattern image file -> float32 values in [0, 1], (Hp, Wp) or (Hp, Wp, 3).

    The size must match the projector unless ``resize`` is ``fit``, ``fill`` or ``stretch`` (see
    :func:`_resized`; ``True`` means ``stretch``). Palette, alpha and CMYK images are read as RGB,
    16-bit images divided by 65535.
    """
    from PIL import Image

    mode = "stretch" if resize is True else (resize or "")
    if mode and mode not in RESIZE_MODES:
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {mode!r}")
    wp, hp = projector_size
    try:
        img = Image.open(path)  # reads the header only: the size is checked before any pixel is decoded
        w, h = img.size
        if w * h > max(4 * wp * hp, 1 << 22):
            raise InputError(f"pattern {path} is {w}x{h}, far larger than the {wp}x{hp} projector: refused "
                             "without decoding it (scale it down first)")
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img.load()
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise InputError(f"pattern {path} is far larger than the {wp}x{hp} projector: refused without decoding it "
                         "(scale it down first)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"cannot read pattern {path}: {exc}") from None
    if img.mode in ("1", "LA"):
        img = img.convert("L")
    elif img.mode not in ("L", "RGB", "F") and not img.mode.startswith("I"):
        img = img.convert("RGB")  # palette (P), RGBA, CMYK, YCbCr: the colours, not their codes
    if img.size != (wp, hp):
        if not mode:
            raise InputError(f"pattern {path} is {img.size[0]}x{img.size[1]} but the projector is {wp}x{hp} "
                             "(pass --resize fit, fill or stretch)")
        img = _resized(img, (wp, hp), mode)
    arr = np.asarray(img)
    if arr.dtype.kind == "f":
        scale = 1.0
    elif img.mode.startswith("I"):
        scale = 65535.0  # 16-bit PNG/TIFF (Pillow's I;16 and I modes)
    else:
        scale = 255.0
    arr = arr.astype(np.float32) / scale
    if arr.ndim == 3:
        arr = arr[..., :3]
        if np.allclose(arr, arr[..., :1]):
            arr = arr[..., 0]
    return np.clip(arr, 0, 1)
