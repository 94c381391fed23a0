"""Image files in: projector patterns (values in [0, 1]) and camera frames (linear float32 RGB).

One reader per meaning, so every command normalises the same file the same way:
:func:`read_pattern` (``sss relight --pattern``, ``sss capture --reference``) and :func:`read_frame`
(``sss import``). Sizes are checked from the file's header before any pixel is decoded.
"""

from __future__ import annotations

import contextlib
import os
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import InputError

#: Frame files the importer reads.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".exr")
#: Lossy files an importer refuses by name (their 8x8 blocks and halved colour resolution corrupt fringes).
LOSSY_SUFFIXES = (".jpg", ".jpeg", ".webp")
#: How an integer frame file's codes map to light: ``linear`` (a camera's raw codes) or ``srgb`` (the sRGB
#: curve, which PNG files tagged sRGB or with an ICC profile, and JPEG data, hold); ``auto`` reads the tag
#: (:func:`declared_encoding`). A PNG's gAMA chunk gives a power law. Float files are linear whatever is asked.
ENCODINGS = ("auto", "linear", "srgb")
MAX_FRAME_PIXELS = 1 << 26  # 64 MP: larger frames are refused from their header, before decoding


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


#: Float patterns may leave [0, 1] by this much (float32 rounding of 1.0 in an image editor's arithmetic); they
#: are clipped to it.
FLOAT_SLACK = 1e-6


def read_pattern(path: Path | str, projector_size: tuple[int, int], *, resize: str | bool = "",
                 hint: str = "pass --resize fit, fill or stretch") -> np.ndarray:
    """A pattern image file -> float32 values in [0, 1], (Hp, Wp) or (Hp, Wp, 3).

    The size must match the projector unless ``resize`` is ``fit``, ``fill`` or ``stretch`` (see
    :func:`_resized`; ``True`` means ``stretch``). Palette and CMYK images are read as RGB, an alpha
    channel as opacity over black (transparent = no light, with a warning), an EXIF orientation tag applied as
    image viewers apply it (with a warning), 16-bit images divided by
    65535; multi-frame files and wider integer types (32-bit: their scale is unknown) are refused. ``hint`` ends the size-mismatch error (what the user can do).
    """
    from PIL import Image

    mode = "stretch" if resize is True else (resize or "")
    if mode and mode not in RESIZE_MODES:
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {mode!r}")
    wp, hp = projector_size
    path = Path(path)
    from sssphase_core.store.files import check_input_file

    check_input_file(path, "pattern")  # a FIFO would block the read for ever
    try:
        as_array = path.suffix.lower() in (".npy", ".exr") or _pil_cannot_decode(path) or _png_16_bit_colour(path)
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"cannot read pattern {path}: {exc}") from None
    if as_array:
        return _read_array_pattern(path, (wp, hp), mode, hint)
    try:
        with header_read():
            img = Image.open(path)  # reads the header only: the size is checked before any pixel is decoded
        w, h = img.size
        if w * h > _max_pattern_pixels(wp, hp, mode):
            img.close()
            raise InputError(f"pattern {path} is {w}x{h}, far larger than the {wp}x{hp} projector: refused "
                             f"without decoding it (scale it down first{'' if mode else ', or pass --resize'})")
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img.load()
    except InputError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise InputError(f"pattern {path} is far larger than the {wp}x{hp} projector: refused without decoding it "
                         "(scale it down first)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"cannot read pattern {path}: {exc}") from None
    if getattr(img, "n_frames", 1) > 1:  # only the first frame was used, without a word
        raise InputError(f"pattern {path} holds {img.n_frames} frames (an animation or a multi-page file): give one "
                         "image file per pattern")
    img = _as_viewers_show_it(img, path)
    img = _light_modes(img, path)
    if img.size != (wp, hp):
        if not mode:
            raise InputError(f"pattern {path} is {img.size[0]}x{img.size[1]} but the projector is {wp}x{hp} ({hint})")
        img = _resized(img, (wp, hp), mode)
    return _pil_pattern_values(img, path)


def _light_modes(img: Any, path: Path) -> Any:
    """A decoded Pillow image in a mode whose values are light: alpha composited over black (with a warning), 1-bit as
    8-bit grey, palette, CMYK and YCbCr as RGB; 8-bit grey and RGB, 16- and 32-bit integers and floats as they are."""
    if img.mode in ("LA", "RGBA", "PA") or (img.mode in ("P", "L", "RGB") and "transparency" in img.info):  # (tRNS)
        img = _over_black(img, path)
    if img.mode == "1":
        return img.convert("L")
    if img.mode not in ("L", "RGB", "F") and not img.mode.startswith("I"):
        return img.convert("RGB")  # palette (P), CMYK, YCbCr: the colours, not their codes
    return img


def _pil_pattern_values(img: Any, path: Path | str) -> np.ndarray:
    """A Pillow image of :func:`_light_modes` -> float32 values in [0, 1], (H, W) or (H, W, 3): 8-bit codes / 255,
    16-bit ones / 65535, floats as they are (refused outside [0, 1] or not finite)."""
    arr = np.asarray(img)
    if arr.dtype.kind == "f":
        scale = 1.0
    elif img.mode.startswith("I"):
        scale = 65535.0  # 16-bit PNG/TIFF (Pillow's I;16 and I modes)
        depth = code_depth(Path(path)) if Path(path).is_file() else None  # (a page of a multi-page file: a label)
        if arr.min() < 0 or arr.max() > 65535 or (depth or 16) > 16:  # 32-bit: 0..255 relit black
            raise InputError(f"pattern {path} holds {f'{depth}-bit ' if depth else ''}integers (from {arr.min()} to "
                             f"{arr.max()}), whose scale is unknown: give 8- or 16-bit unsigned values, or floats in [0, 1]")
    else:
        scale = 255.0
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():  # a single-channel float TIFF (Pillow's mode F)
        raise InputError(f"pattern {path} must hold finite values in [0, 1]: it has NaN or inf")
    if arr.dtype.kind == "f" and (arr.min() < -FLOAT_SLACK or arr.max() > 1 + FLOAT_SLACK):
        raise InputError(f"pattern {path} must hold finite values in [0, 1], got {arr.min():.7g} to {arr.max():.7g}")
    arr = arr.astype(np.float32) / scale
    if arr.ndim == 3:
        arr = arr[..., :3]
        if np.allclose(arr, arr[..., :1]):
            arr = arr[..., 0]
    return np.clip(arr, 0, 1)


#: What each EXIF orientation (tag 274) asks of the stored pixels before they are shown.
EXIF_ORIENTATIONS = {2: "mirrored left-right", 3: "rotated 180°", 4: "mirrored top-bottom",
                     5: "mirrored left-right and rotated 90° counter-clockwise", 6: "rotated 90° clockwise", 7: "mirrored left-right and rotated 90° clockwise",
                     8: "rotated 90° counter-clockwise"}


def _as_viewers_show_it(img: object, path: Path) -> object:
    """A pattern image turned as its EXIF orientation tag asks (a phone's photo stored sideways, tagged "rotate
    90°"), with a warning: every image viewer shows it turned, and that is the pattern its user chose; the
    projector's pixels are then the shown image's."""
    from PIL import ImageOps

    try:
        orientation = img.getexif().get(274, 1)  # type: ignore[attr-defined]
    except Exception:  # noqa: BLE001  (a damaged EXIF block: the pixels as stored)
        return img
    if orientation not in EXIF_ORIENTATIONS:
        return img
    warnings.warn(f"pattern {path}: its EXIF orientation tag says the stored image is shown {EXIF_ORIENTATIONS[orientation]}: "
                  "it is projected as image viewers show it", UserWarning, stacklevel=3)
    return ImageOps.exif_transpose(img)


def exif_orientation(path: Path) -> int:
    """The EXIF orientation tag (274) of an image file, from its header (1, as stored, where it has none or it does
    not read; ``.npy`` and EXR have none)."""
    from PIL import Image

    if path.suffix.lower() in (".npy", ".exr"):
        return 1
    try:
        if _pil_cannot_decode(path):
            value = (_tiff_directory(path) or {}).get(274, 1)
        else:
            with warnings.catch_warnings():  # (set before the open, which is what warns)
                warnings.simplefilter("ignore")
                with Image.open(path) as img:
                    value = img.getexif().get(274, 1)
        return int(value) if int(value) in EXIF_ORIENTATIONS else 1  # type: ignore[arg-type]
    except Exception:  # noqa: BLE001  (a damaged EXIF block or header: the pixels as stored; the reader says more)
        return 1


def shown_shape(path: Path) -> tuple[int, ...]:
    """:func:`frame_shape` of the image as viewers show it (its EXIF orientation applied: a tag that turns it by
    90° swaps its width and height)."""
    shape = frame_shape(path)
    return (shape[1], shape[0], *shape[2:]) if exif_orientation(path) in (5, 6, 7, 8) else shape


def _oriented(arr: np.ndarray, orientation: int) -> np.ndarray:
    """``arr`` (H, W[, C]) turned as EXIF ``orientation`` asks, as ``PIL.ImageOps.exif_transpose`` turns an image."""
    turned = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
              5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
              8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(turned[orientation](arr)) if orientation in turned else arr


def _max_pattern_pixels(wp: int, hp: int, resize: str) -> int:
    """The most pixels a pattern file for a ``wp`` x ``hp`` projector may have before it is decoded: 4x the
    projector (at least 4 MP) for a pattern used as it is; with ``resize``, a camera or screen image up to
    64 MP (8K x 8K), which is scaled to the projector (a decompression bomb stays refused from its header)."""
    return max(4 * wp * hp, 1 << 22) if not resize else max(4 * wp * hp, 1 << 26)


#: The most pixels a pattern read whole as an array (16-bit colour PNG, EXR, float TIFF, ``.npy``) may have with a
#: resize: an 8K UHD frame (33 MP) fits; its float32 copy is ~400 MB (8-bit images go through Pillow: 64 MP).
ARRAY_RESIZE_PIXELS = 36_000_000


def _max_array_pixels(wp: int, hp: int, resize: str) -> int:
    """:func:`_max_pattern_pixels` for a pattern read whole as an array (16-bit and float images, ``.npy``)."""
    return _max_pattern_pixels(wp, hp, "") if not resize else max(4 * wp * hp, ARRAY_RESIZE_PIXELS)


def _over_black(img: object, path: Path) -> object:
    """An image with an alpha channel as the light it asks for: transparent pixels give no light (the colour
    times its opacity, i.e. composited over black, by Pillow in 8 bits: an 8K RGBA image cost 3.5 GB as float32);
    warns when any pixel is not opaque. Grey stays grey."""
    from PIL import Image, ImageChops

    grey = img.mode == "LA"  # type: ignore[attr-defined]
    rgba = img.convert("RGBA")  # type: ignore[attr-defined]
    counts = rgba.getchannel("A").histogram()  # opacity codes 0..255
    total = sum(counts)
    _warn_not_opaque(path, 1 - counts[255] / total, counts[0] / total)
    *colour, alpha = rgba.split()
    del rgba
    colour = [ImageChops.multiply(c, alpha) for c in colour[:1 if grey else 3]]  # c * a / 255, rounded
    return colour[0] if grey else Image.merge("RGB", colour)


def _warn_not_opaque(path: Path, not_opaque: float, clear: float) -> None:
    """Warn when a share ``not_opaque`` of a pattern's pixels (``clear`` of them fully transparent) is not opaque."""
    if not_opaque > 0:
        warnings.warn(f"pattern {path}: {not_opaque:.0%} of its pixels are not fully opaque "
                      f"({clear:.0%} fully transparent): they are projected as their colour times their opacity "
                      "(transparent = no light)", UserWarning, stacklevel=4)


def _png_16_bit_colour(path: Path) -> bool:
    """Whether ``path`` is a 16-bit RGB(A) or grey-with-alpha PNG (from its IHDR chunk), which Pillow reads at 8 bits."""
    if path.suffix.lower() != ".png" or not path.is_file():
        return False
    with open(path, "rb") as f:
        head = f.read(26)
    return (len(head) == 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and head[24] == 16
            and head[25] in (2, 4, 6))


def _read_array_pattern(path: Path, projector_size: tuple[int, int], mode: str, hint: str) -> np.ndarray:
    """A pattern stored as an array (``.npy``, ``.exr``, float TIFF): (Hp, Wp) or (Hp, Wp, 3), float values
    in [0, 1] or 8- or 16-bit unsigned integers (divided by their type's maximum; wider ones are refused); the
    shape is checked from the header before the pixels are read."""
    from PIL import Image

    wp, hp = projector_size
    shape = frame_shape(path)
    channels = (1, 3) if path.suffix.lower() == ".npy" else (1, 3, 4)  # an image's fourth channel: its alpha
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in channels) or 0 in shape:
        raise InputError(f"pattern {path} must be an (H, W) or (H, W, 3) image, got shape {shape}")
    if shape[0] * shape[1] > _max_array_pixels(wp, hp, mode):  # arrays are read whole, in float32
        raise InputError(f"pattern {path} is {shape[1]}x{shape[0]}, far larger than the {wp}x{hp} projector: "
                         "refused without reading it (scale it down first"
                         f"{f'; 16-bit, float and array patterns are read whole: {ARRAY_RESIZE_PIXELS / 1e6:.0f} MP at most' if mode else ''})")
    arr = _read_pixels(path, alpha=True)
    if (orientation := exif_orientation(path)) != 1:  # (OpenCV's unchanged read ignores the tag; Pillow's does not)
        warnings.warn(f"pattern {path}: its EXIF orientation tag says the stored image is shown "
                      f"{EXIF_ORIENTATIONS[orientation]}: it is projected as image viewers show it", UserWarning, stacklevel=3)
        arr = _oriented(arr, orientation)
    if arr.dtype.kind not in "fu":
        raise InputError(f"pattern {path} must be an (H, W) or (H, W, 3) array of floats in [0, 1] or unsigned "
                         f"integers, got {arr.dtype} of shape {arr.shape}")
    if arr.dtype.kind == "u" and arr.dtype.itemsize > 2:  # divided by 2^32 - 1 or 2^64 - 1, 0..255 relit as black
        raise InputError(f"pattern {path} holds {arr.dtype} integers (from {int(arr.min())} to {int(arr.max())}), whose "
                         "scale is unknown: give uint8 (0-255), uint16 (0-65535) or floats in [0, 1]")
    data = np.asarray(arr, np.float64 if arr.dtype == np.float64 else np.float32)  # (16-bit codes exact in float32)
    if data.ndim == 3 and data.shape[2] == 4 and path.suffix.lower() != ".npy":  # an image's alpha: opacity over black
        alpha = data[..., 3:] / (np.iinfo(arr.dtype).max if arr.dtype.kind == "u" else 1.0)
        _warn_not_opaque(path, float((alpha < 1).mean()), float((alpha <= 0).mean()))
        data = data[..., :3] * np.clip(alpha, 0, 1)
    if data.ndim == 3:
        data = data[..., 0] if data.shape[2] == 1 else data
    if arr.dtype.kind == "u":
        data = data / np.iinfo(arr.dtype).max
    elif not np.isfinite(data).all():
        raise InputError(f"pattern {path} must hold finite values in [0, 1]: it has NaN or inf")
    elif data.min() < -FLOAT_SLACK or data.max() > 1 + FLOAT_SLACK:
        raise InputError(f"pattern {path} must hold finite values in [0, 1], got {data.min():.7g} to {data.max():.7g}")
    data = data.astype(np.float32)
    if data.shape[:2] != (hp, wp):
        if not mode:
            raise InputError(f"pattern {path} is {data.shape[1]}x{data.shape[0]} but the projector is {wp}x{hp} ({hint})")
        planes = [data] if data.ndim == 2 else [data[..., c] for c in range(3)]
        data = np.stack([np.asarray(_resized(Image.fromarray(np.ascontiguousarray(p, np.float32)), (wp, hp), mode)) for p in planes], axis=-1)
        data = data[..., 0] if data.shape[-1] == 1 else data
    return np.clip(data, 0, 1).astype(np.float32)


#: :func:`_tiff_directory`'s key for the offset of the file's next image directory (0: a single page)
NEXT_PAGE = -1


def _tiff_directory(path: Path) -> dict[int, object] | None:
    """The first image directory of a TIFF file (tag number -> value), read from its header only; None
    when the file is not a TIFF. Pillow opens only the TIFF layouts it can decode (not 3-channel
    float32, which renderers and cameras write), but parses any header."""
    from PIL import TiffImagePlugin

    with open(path, "rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a damaged directory: Pillow warns and reads what it can
        head = f.read(8)
        if head[:4] not in (b"II*\0", b"MM\0*"):
            return None
        try:
            ifd = TiffImagePlugin.ImageFileDirectory_v2(head)
            f.seek(ifd.next)
            ifd.load(f)
        except struct.error as exc:  # (the callers report ValueError as an unreadable file)
            raise ValueError(f"its TIFF header is cut short ({exc})") from None
        return {**dict(ifd), NEXT_PAGE: ifd.next}


def _pil_cannot_decode(path: Path) -> bool:
    """Whether ``path`` is a TIFF that Pillow cannot decode (OpenCV reads those)."""
    from PIL import Image, UnidentifiedImageError

    if path.suffix.lower() not in (".tif", ".tiff"):
        return False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a damaged TIFF directory: the header reader below says so
            with Image.open(path):
                return False
    except Image.DecompressionBombError:  # Pillow reads it; the caller refuses its size
        return False
    except UnidentifiedImageError:
        return _tiff_directory(path) is not None


def _load_npy(path: Path, **kwargs) -> np.ndarray:
    """``np.load`` of a user's ``.npy`` file (never unpickled). An empty or cut-short file, where numpy
    raises EOFError (which click would turn into a bare "Aborted"), raises ValueError: every caller
    reports it as an InputError naming the file."""
    try:
        with warnings.catch_warnings(), np.errstate(over="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)  # a header's absurd shape overflows numpy's size product
            return np.load(path, allow_pickle=False, **kwargs)
    except EOFError:
        raise ValueError("empty or truncated .npy file") from None
    except ValueError as exc:
        if "mmap length" in str(exc) or "EOF" in str(exc):  # cut short after its header
            raise ValueError("empty or truncated .npy file (the header promises more data than it holds)") from None
        if "pickle" in str(exc).lower() or "python objects" in str(exc).lower():  # numpy invites unsafe loading: never
            raise ValueError("not a numeric .npy array (pickled data, or not a .npy file at all; never loaded)") from None
        raise


@contextlib.contextmanager
def header_read() -> Iterator[None]:
    """Pillow's DecompressionBombWarning silenced around an ``Image.open`` that reads a header alone (entered before
    the open, which is what warns): the image's size is checked by its reader and refused in one line, which the
    warning preceded with a second, alarming one."""
    from PIL import Image

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        yield


def _far_too_large(path: Path) -> InputError:
    """The line for an image whose header declares more pixels than Pillow's decompression-bomb guard takes
    (2 x ``Image.MAX_IMAGE_PIXELS``, 179 MP by default; every frame and pattern limit here is below it)."""
    from PIL import Image

    limit = 2 * (Image.MAX_IMAGE_PIXELS or 0) / 1e6
    return InputError(f"{path} declares an image of over {limit:.0f} MP, far larger than any camera frame or pattern: "
                      "refused without decoding it")


def frame_shape(path: Path) -> tuple[int, ...]:
    """The pixel shape a frame file declares, read from its header only (no pixel is decoded); a file of several
    images (a multi-page TIFF, an animation) is refused."""
    from sssphase_core.store.files import check_input_file

    check_input_file(path, "frame")  # a FIFO would block the read for ever
    try:
        if path.suffix.lower() == ".npy":
            shape = tuple(_load_npy(path, mmap_mode="r").shape)
            if len(shape) < 2 or 0 in shape:  # no image size to read (a 0-d array was an IndexError in every caller)
                raise InputError(f"{path} has shape {shape}: expected (H, W) or (H, W, 3)")
            return shape
        if path.suffix.lower() == ".exr":
            from sssphase_core.store import exr

            return exr.exr_size(path)
        if _pil_cannot_decode(path):
            tags = _tiff_directory(path) or {}
            if 256 not in tags or 257 not in tags:
                raise ValueError("a TIFF header without an image size (damaged file?)")
            if tags.get(NEXT_PAGE):  # (OpenCV reads the first page only, without a word)
                raise InputError(f"{path} holds several images (a multi-page TIFF): give one image per file")
            channels = int(tags.get(277, 1))  # SamplesPerPixel
            return (int(tags[257]), int(tags[256])) + ((channels,) if channels > 1 else ())
        from PIL import Image

        try:
            with header_read(), Image.open(path) as img:  # (the callers' own limits, on the size)
                (width, height), pages = img.size, int(getattr(img, "n_frames", 1))
        except Image.DecompressionBombError:  # (Pillow's guard, left on for the whole process)
            raise _far_too_large(path) from None
    except InputError:
        raise
    except (OSError, ValueError, SyntaxError, KeyError) as exc:
        raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if pages > 1:  # only the first page was read, without a word
        raise InputError(f"{path} holds {pages} images (a multi-page or animated file): give one image per file")
    return (height, width)


def stores_integers(path: Path) -> bool:
    """Whether a frame file holds integer codes (8/16-bit PNG/TIFF or ``.npy``): its top code is
    the sensor's clipping level, so values near 1 after :func:`read_frame` are saturated. EXR and float
    files have no such level. Read from the header only."""
    suffix = path.suffix.lower()
    if suffix == ".exr":
        return False
    from PIL import Image

    try:
        if suffix == ".npy":
            dtype = _load_npy(path, mmap_mode="r").dtype
            return dtype.kind == "b" or (dtype.kind in "iu" and dtype.itemsize <= 2)  # as read_frame scales them
        if _pil_cannot_decode(path):
            formats = (_tiff_directory(path) or {}).get(339, 1)  # SampleFormat: 3 = IEEE float
            return 3 not in (formats if isinstance(formats, tuple) else (formats,))
        with Image.open(path) as img:
            return img.mode != "F"
    except Image.DecompressionBombError:
        raise _far_too_large(path) from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None


def code_depth(path: Path) -> int | None:
    """Bits per sample of a frame file's integer codes (1, 8 or 16), or None for float data; from the header
    only. Frames of one capture come out of one camera pipeline: a view mixing 8- and 16-bit files was put
    together from two, whose codes mean different light."""
    if not stores_integers(path):
        return None
    try:
        return _code_depth(path)
    except (OSError, ValueError, SyntaxError) as exc:  # a file cut short: the header is not all there
        raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__} "
                         "(a damaged or truncated file?)") from None


def _code_depth(path: Path) -> int:
    suffix = path.suffix.lower()
    if suffix == ".npy":
        dtype = _load_npy(path, mmap_mode="r").dtype
        return 1 if dtype.kind == "b" else 8 * dtype.itemsize
    with open(path, "rb") as f:
        head = f.read(26)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 26:  # IHDR: bit depth, colour type (3: palette of 8-bit colours)
        return 8 if head[25] == 3 else int(head[24])
    bits = (_tiff_directory(path) or {}).get(258)  # BitsPerSample
    if bits is not None:
        return int(bits[0] if isinstance(bits, tuple) else bits)  # type: ignore[arg-type]
    from PIL import Image

    with Image.open(path) as img:
        return 16 if img.mode.startswith("I;16") else 1 if img.mode == "1" else 8


@contextlib.contextmanager
def native_stderr_silenced(fds: tuple[int, ...] = (2,)) -> Iterator[None]:
    """Native libraries' writes to file descriptors ``fds`` (default stderr; not Python's) dropped for the
    block: the error they describe is reported once, as one line, by the caller. (OpenEXR prints some of
    its warnings on stdout: pass ``(1, 2)``.)"""
    import sys

    for stream in (sys.stdout, sys.stderr):  # Python's own pending output goes out first
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()
    saved: list[tuple[int, int]] = []
    try:
        with open(os.devnull, "wb") as null:
            for fd in fds:
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # no such stream to silence
                    continue
                os.dup2(null.fileno(), fd)
            yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


def _read_pixels(path: Path, *, alpha: bool = False) -> np.ndarray:
    """A frame file's pixels as stored (RGB order, integer codes not scaled): ``.npy`` (never
    unpickled), ``.exr``, or any PNG/TIFF that OpenCV decodes (RGBA with ``alpha``, else its alpha dropped)."""
    if path.suffix.lower() == ".npy":
        try:
            return _load_npy(path)
        except (OSError, ValueError) as exc:  # pickled object arrays are never loaded
            raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if path.suffix.lower() == ".exr":
        from sssphase_core.store import exr

        return exr.read_exr(path)
    import cv2

    with native_stderr_silenced():  # libpng/libtiff print their own "Read Error" lines on a damaged file
        arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise InputError(f"cannot read image {path} (damaged, truncated or not an image)")
    if arr.ndim == 3 and arr.shape[2] >= 3:  # BGR(A) -> RGB(A) by indexing: any depth (cvtColor refuses float64)
        order = [2, 1, 0, 3] if alpha and arr.shape[2] == 4 else [2, 1, 0]
        arr = np.ascontiguousarray(arr[..., order])
    return arr


#: Words in an ICC profile's description that name linear light (scene-linear working spaces).
LINEAR_ICC_WORDS = ("linear", "acescg", "aces2065")


def _icc_encoding(icc: bytes) -> tuple[str, str]:
    """``(encoding, why)`` of an ICC profile: linear for an XYZ profile or one whose description names linear
    light (a linear profile was read as sRGB, and 74% of a render's pixels were lost), else sRGB (assumed: the
    profile's tone curves are not read)."""
    import io

    try:
        from PIL import ImageCms

        profile = ImageCms.ImageCmsProfile(io.BytesIO(icc)).profile
        space, description = str(profile.xcolor_space).strip(), str(profile.profile_description or "")
    except Exception:  # noqa: BLE001  (no littlecms, or a damaged profile: as before)
        return "srgb", "its ICC colour profile (assumed sRGB)"
    if space == "XYZ" or any(w in description.lower() for w in LINEAR_ICC_WORDS):
        return "linear", f"its ICC colour profile ({description.strip() or space}: linear light)"
    return "srgb", f"its ICC colour profile ({description.strip() or 'unnamed'}, assumed sRGB)"


def declared_encoding(path: Path) -> tuple[str, str]:
    """``(encoding, why)``: how an integer frame file says its codes map to light, from its header:
    ``"srgb"`` for a PNG with an sRGB chunk or an ICC profile and for JPEG data (whatever the file's
    name), ``"gamma <g>"`` for a PNG's gAMA chunk (codes = light^(1/g)), else ``"linear"``; ``why`` names the
    tag. Float files and ``.npy`` arrays are ``"linear"``."""
    if path.suffix.lower() in (".npy", ".exr") or not stores_integers(path) or _pil_cannot_decode(path):
        return "linear", "no colour tag (an array or float file)"
    from PIL import Image

    try:
        with Image.open(path) as img:
            fmt, info = img.format, dict(img.info)
    except Image.DecompressionBombError:
        raise _far_too_large(path) from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if fmt == "JPEG":
        return "srgb", "JPEG data"
    if "srgb" in info:
        return "srgb", "its sRGB chunk"
    if info.get("icc_profile"):
        return _icc_encoding(info["icc_profile"])
    g = info.get("gamma")
    if isinstance(g, (int, float)) and 0.05 <= g <= 20.0:
        return ("linear", f"its gAMA chunk ({g:g})") if abs(g - 1.0) <= 0.01 else (f"gamma {1.0 / g:.4g}", f"its gAMA chunk ({g:g})")
    return "linear", "no colour tag"


def decode_codes(values: np.ndarray, encoding: str) -> np.ndarray:
    """Codes scaled to [0, 1] -> linear light, for an ``encoding`` of :func:`declared_encoding`: the sRGB
    curve (IEC 61966-2-1), ``light = code^g`` for ``"gamma <g>"``, unchanged for ``"linear"``."""
    if encoding == "linear":
        return values
    v = np.clip(values, 0.0, 1.0)
    if encoding == "srgb":
        return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)
    if encoding.startswith("gamma "):
        return (v ** np.float32(float(encoding.split()[1]))).astype(np.float32)
    raise ValueError(f"unknown encoding {encoding!r}")


def _warn_frame_alpha(path: Path, alpha: np.ndarray) -> None:
    """Warn when a frame's alpha channel is not fully opaque: a camera records no opacity, and the colour is read
    as it is (a transparent frame imported without a word)."""
    top = np.iinfo(alpha.dtype).max if alpha.dtype.kind in "iu" else 1.0
    below = alpha < top
    if below.any():
        warnings.warn(f"{path}: its alpha channel is below full opacity at {float(below.mean()):.0%} of the pixels "
                      f"(transparent at {float((alpha <= 0).mean()):.0%}): a camera frame has no opacity, so the alpha "
                      "is ignored and the colour read as it is; save the frames without alpha", UserWarning, stacklevel=3)


def read_frame(path: Path, *, finite: bool = True, encoding: str = "linear", keep_grey: bool = False) -> np.ndarray:
    """A linear image as float32 RGB (H, W, 3) (a grey file's one channel repeated; ``keep_grey``: kept (H, W)):
    8/16-bit integers (PNG, TIFF, ``.npy``) divided by the top code and decoded by ``encoding``
    (:func:`decode_codes`; ``"auto"``: the file's own tag, :func:`declared_encoding`), float ``.npy`` / ``.exr`` / TIFF
    and wider integer ``.npy`` as stored. Frames larger than ``MAX_FRAME_PIXELS`` are refused from their header.
    NaN / inf values are refused unless ``finite`` is False (the importer repairs a few: ``isp.repair_nonfinite``)."""
    shape = frame_shape(path)
    if len(shape) >= 2 and shape[0] * shape[1] > MAX_FRAME_PIXELS:
        raise InputError(f"{path} is {shape[1]}x{shape[0]}: larger than any camera frame this importer takes "
                         f"({MAX_FRAME_PIXELS // 2**20} MP)")
    arr = _read_pixels(path, alpha=True)
    if arr.ndim == 3 and arr.shape[2] == 4 and path.suffix.lower() != ".npy":  # a camera frame's alpha: dropped, told
        _warn_frame_alpha(path, arr[..., 3])
        arr = arr[..., :3]
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path} holds {arr.dtype} values, not an image")
    if arr.dtype.kind == "i" and arr.dtype.itemsize <= 2:  # divided by its top code, -128 would be negative light
        raise InputError(f"{path} holds signed {arr.dtype} codes: give a camera's unsigned 8- or 16-bit codes, or floats")
    if arr.dtype.kind in "iu" and (arr.dtype.itemsize <= 2 or path.suffix.lower() != ".npy"):
        arr = arr.astype(np.float32) / np.iinfo(arr.dtype).max  # a camera's codes, as a 16-bit PNG's
        if encoding == "auto":
            encoding = declared_encoding(path)[0]
        arr = decode_codes(arr, encoding)
    if arr.dtype.kind == "f" and arr.dtype.itemsize > 4:  # float64 beyond float32 would become inf, called broken
        top = float(np.abs(arr[np.isfinite(arr)]).max(initial=0.0))
        if top > float(np.finfo(np.float32).max) / 16:
            raise InputError(f"{path} holds values up to {top:.3g}, beyond what float32 frames hold: scale them down")
    arr = np.asarray(arr, np.float32)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] != 3) or arr.size == 0:
        raise InputError(f"{path} has shape {arr.shape}: expected (H, W) or (H, W, 3)")
    if finite and not np.isfinite(arr).all():
        raise InputError(f"{path} holds NaN or infinite values")
    return np.repeat(arr[..., None], 3, axis=-1) if arr.ndim == 2 and not keep_grey else arr
