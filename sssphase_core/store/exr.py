"""OpenEXR files through the official ``OpenEXR`` Python bindings.

Linear float32 images are written unclipped, in camera units, and read back bit-exactly. The OpenCV
wheel that installs with sssphase cannot write EXR, so this module is the one place EXR goes through.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import DataError, InputError

MISSING = ("EXR needs the OpenEXR Python bindings, which are not installed: pip install 'sssphase[exr]' "
           "(or pip install OpenEXR; a dependency of sssphase, so the install is incomplete)")


def _openexr():
    try:
        import OpenEXR
    except ImportError:
        raise InputError(MISSING) from None
    return OpenEXR


def available() -> bool:
    """Whether EXR can be read and written here."""
    try:
        _openexr()
    except InputError:
        return False
    return True


def write_exr(path: Path | str, image: np.ndarray, *, attributes: dict[str, str] | None = None) -> Path:
    """Write ``image`` (H, W) as channel ``Y``, (H, W, 3) as ``RGB`` or (H, W, C) as ``c0..``, float32, ZIP.

    Values are stored as given (no clipping, NaN kept). ``attributes`` become string header fields.
    """
    OpenEXR = _openexr()
    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if img.ndim == 2:
        channels = {"Y": img}
    elif img.ndim == 3 and img.shape[2] == 3:
        channels = {"RGB": img}
    elif img.ndim == 3:
        channels = {f"c{i:02d}": np.ascontiguousarray(img[..., i]) for i in range(img.shape[2])}
    else:
        raise InputError(f"cannot write an array of shape {img.shape} as EXR (need H x W or H x W x C)")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(attributes or {})}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from sssphase_core.store.files import atomic_path

    try:
        with atomic_path(path, ".exr") as tmp, OpenEXR.File(header, channels) as f:
            f.write(str(tmp))  # renamed once complete: a full disk leaves no truncated EXR under the name
    except (OSError, RuntimeError) as exc:  # a name too long, a full disk, a folder not writable
        raise InputError(f"could not write {path}: {_write_problem(exc)}") from None
    return path


#: Single channels read as a grey image (luminance or intensity); depth (Z), alpha (A) or others are not light.
GREY_CHANNELS = ("Y", "L", "I")


#: Words in a part's or a layer's name that mark the rendered image among others (AOVs: depth, albedo ...).
BEAUTY_WORDS = ("beauty", "combined", "rgba", "main", "image")
#: Half floats end at 65504: +inf in a half channel whose finite values reach this far is overflow, not a stray
#: sample (a renderer's units: write float32 or scale the render down).
HALF_OVERFLOW_NEAR = 1024.0


def read_exr(path: Path | str) -> np.ndarray:
    """An EXR file's image -> float32 (H, W) for a grey channel (:data:`GREY_CHANNELS`), (H, W, 3) for its
    colour: R, G, B (either case; alpha, depth and other channels dropped), or a renderer's colour layer
    (:func:`_colour_layer`). A multi-part file's image is the part that holds one, or among several the part
    named as the beauty (:data:`BEAUTY_WORDS`: an AOV written first is not the image); several unnamed are
    refused. Files without light channels (depth only, luminance/chroma), half floats that overflowed, or files
    that cannot be decoded are refused in one line."""
    from sssphase_core.store.files import check_input_file
    from sssphase_core.store.imageio import native_stderr_silenced

    if not check_input_file(path, "EXR").is_file():  # (a FIFO or a device refused by name) not "damaged": not there
        raise DataError(f"cannot read EXR {path}: {'a folder, not a file' if Path(path).is_dir() else 'no such file'}")
    OpenEXR = _openexr()
    _check_windows(path, OpenEXR)  # from the headers, before any pixel is decoded
    try:
        with native_stderr_silenced((1, 2)), OpenEXR.File(str(path), separate_channels=True) as f:  # R, G, B apart
            parts = [{name: _in_display_window(np.asarray(ch.pixels), part.header) for name, ch in part.channels.items()}
                     for part in f.parts]
            names = [str(part.name() if callable(getattr(part, "name", None)) else "") for part in f.parts]
    except (OSError, RuntimeError, ValueError, KeyError):  # the library prints its own lines; one of ours instead
        raise DataError(f"cannot read EXR {path} (damaged, truncated or not an EXR file)") from None
    if not any(parts):  # a cut-short file: the library reads no pixel and says so only on its own output
        raise DataError(f"cannot read EXR {path} (damaged or truncated: no pixel data could be read)")
    found = [(name, image) for name, channels in zip(names, parts, strict=True)
             if (image := _light(path, channels)) is not None]
    if len(found) > 1:
        named = [f for f in found if any(w in f[0].lower() for w in BEAUTY_WORDS)]
        if len(named) != 1:
            raise DataError(f"EXR {path} holds an image in several parts ({', '.join(n or '(unnamed)' for n, _ in found)}): "
                            "write the rendered image alone, or name its part beauty or combined")
        found = named
    if found:
        return _no_half_overflow(path, found[0][1])
    listed = ", ".join(sorted({name for channels in parts for name in channels})) or "none"
    raise DataError(f"EXR {path} holds no image light as R, G, B or one grey channel (Y) (its channels: {listed}"
                    + ("; luminance/chroma: write RGB" if any("RY" in c or "BY" in c for c in parts) else "") + ")")


def _light(path: Path | str, channels: dict[str, np.ndarray]) -> np.ndarray | None:
    """One part's image: its colour (:func:`_colour_layer`) as (H, W, 3), else its one grey channel as (H, W)
    (beside alpha, depth or normals), else None; channels keep their type (half floats are checked after)."""
    layer = _colour_layer(path, channels)
    if layer is not None:
        return np.stack([channels[name] for name in layer], axis=-1)
    grey = [name for name in channels if name.rsplit(".", 1)[-1] in GREY_CHANNELS]
    chroma = any(name.rsplit(".", 1)[-1] in ("RY", "BY") for name in channels)  # luminance/chroma: not grey light
    return channels[grey[0]] if len(grey) == 1 and not chroma else None


def _no_half_overflow(path: Path | str, image: np.ndarray) -> np.ndarray:
    """``image`` as float32; +inf in half floats whose finite values come near their end is refused as overflow
    (it was taken for a renderer's stray samples and "repaired", or the file called broken)."""
    if image.dtype == np.float16 and np.isposinf(image).any():
        finite = image[np.isfinite(image)]
        if finite.size and float(finite.max()) >= HALF_OVERFLOW_NEAR:
            raise DataError(f"EXR {path}: {int(np.isposinf(image).sum())} values are +inf in half floats whose others "
                            f"reach {float(finite.max()):.0f}: values above 65504 overflowed; write float32 (full "
                            "float) channels, or scale the render down")
    return image.astype(np.float32, copy=False)


def _windows(header: dict) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """(data window, display window) of an EXR header, each (x0, y0, x1, y1) inclusive."""
    (ax0, ay0), (ax1, ay1) = header["dataWindow"]
    (bx0, by0), (bx1, by1) = header.get("displayWindow", header["dataWindow"])
    return (int(ax0), int(ay0), int(ax1), int(ay1)), (int(bx0), int(by0), int(bx1), int(by1))


def _in_display_window(pixels: np.ndarray, header: dict) -> np.ndarray:
    """A channel's pixels (its data window) placed in the image's display window: a renderer's overscan is cut
    off and a region render is padded with zeros (no light), so that every frame's pixel (x, y) is the same
    camera pixel whatever window each file stores. (H, W) of the data window -> (H', W') of the display window."""
    (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = _windows(header)
    if (ax0, ay0, ax1, ay1) == (bx0, by0, bx1, by1):
        return pixels
    out = np.zeros((by1 - by0 + 1, bx1 - bx0 + 1), pixels.dtype)
    x0, y0, x1, y1 = max(ax0, bx0), max(ay0, by0), min(ax1, bx1), min(ay1, by1)
    if x0 <= x1 and y0 <= y1:
        out[y0 - by0 : y1 - by0 + 1, x0 - bx0 : x1 - bx0 + 1] = pixels[y0 - ay0 : y1 - ay0 + 1, x0 - ax0 : x1 - ax0 + 1]
    return out


def _colour_layer(path: Path | str, channels: dict[str, np.ndarray]) -> tuple[str, str, str] | None:
    """The channel names (R, G, B) of the image's colour in one part: ``R, G, B`` (or ``r, g, b``), else a
    renderer's layer (``ViewLayer.Combined.R``, ``C.r``): the one layer with the three, else the one named as the
    beauty (:data:`BEAUTY_WORDS`; multi-layer files also hold depth, normals, albedo ...); None when no layer
    has them. Ambiguous files are refused."""
    layers: dict[str, tuple[str, str, str]] = {}
    for name in channels:
        prefix, last = name[:-1], name[-1:]
        if (prefix == "" or prefix.endswith(".")) and last in ("R", "G", "B", "r", "g", "b"):
            names = tuple(prefix + c for c in ("RGB" if last.isupper() else "rgb"))
            if all(n in channels for n in names):
                layers.setdefault(prefix, names)  # type: ignore[arg-type]
    if "" in layers:  # the file's own R, G, B before any layer's
        return layers[""]
    if len(layers) > 1:
        named = [lay for lay in layers if any(w in lay.lower() for w in BEAUTY_WORDS)]
        if len(named) != 1:
            raise DataError(f"EXR {path} holds several colour layers ({', '.join(lay.rstrip('.') or '(unnamed)' for lay in sorted(layers))}): "
                            "write the image's colour alone, or as a layer named Combined or Beauty")
        return layers[named[0]]
    return next(iter(layers.values()), None)


def exr_size(path: Path | str) -> tuple[int, int]:
    """(height, width) of an EXR image (its display window, as :func:`read_exr` returns it) from its header
    alone (nothing is decoded); windows larger than any frame are refused (:func:`_check_windows`)."""

    _, (x0, y0, x1, y1) = _windows(_check_windows(path, _openexr())[0])
    return y1 - y0 + 1, x1 - x0 + 1


def _check_windows(path: Path | str, OpenEXR: Any) -> list[dict]:
    """The headers of the file's parts, refused from them alone when a part's data or display window is over
    :data:`~sssphase_core.store.imageio.MAX_FRAME_PIXELS`: the library decodes the whole data window (a 5 MB
    file with a 20000 x 20000 data window behind a 256 x 192 display took 5 GB) before it is cropped."""
    from sssphase_core.store.imageio import MAX_FRAME_PIXELS, native_stderr_silenced

    try:
        with native_stderr_silenced():
            headers = [part.header for part in OpenEXR.File(str(path), header_only=True).parts]
        windows = [w for h in headers for w in _windows(h)]
        if not headers:
            raise ValueError("no parts")
    except (OSError, RuntimeError, ValueError, KeyError, TypeError):
        raise DataError(f"cannot read EXR {path} (damaged, truncated or not an EXR file)") from None
    for x0, y0, x1, y1 in windows:
        w, h = x1 - x0 + 1, y1 - y0 + 1
        if w <= 0 or h <= 0 or w * h > MAX_FRAME_PIXELS:
            raise DataError(f"EXR {path} declares a {w}x{h} pixel window, {'empty' if w <= 0 or h <= 0 else f'over {MAX_FRAME_PIXELS >> 20} MP'}"
                            ": far larger than any camera frame or pattern; refused before decoding it")
    return headers


def _write_problem(exc: BaseException) -> str:
    """OpenEXR's or the OS's reason a write failed, in one line, without the temporary file's name."""
    import re

    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    text = str(exc).strip()
    if not text:
        return repr(exc)
    text = text.splitlines()[-1].strip("'\" ")  # ('Failed to write pixel data to image file "….tmp.exr". File too large.')
    return re.sub(r' to image file "[^"]*"', "", text)
