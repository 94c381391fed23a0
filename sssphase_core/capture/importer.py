"""Frames from another rig (a folder of files named by plan key) through the same view processor as a
capture (`sss import`)."""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core import __version__
from sssphase_core.capture.plan import CaptureRequest, RigSpec
from sssphase_core.capture.processing import ViewProcessor
from sssphase_core.errors import InputError
from sssphase_core.processing.footprints import PATCH_RANGE
from sssphase_core.processing.patterns import MAX_SHIFTS
from sssphase_core.store.imageio import (
    ENCODINGS,
    IMAGE_SUFFIXES,
    LOSSY_SUFFIXES,
    code_depth,
    declared_encoding,
    decode_codes,
    frame_shape,
    read_frame,
    read_pattern,
    stores_integers,
)
from sssphase_core.store.light import NEGATIVE_LIMIT, far_below_zero, projector_light
from sssphase_core.store.locks import session_lock
from sssphase_core.store.session import Session, check_object_name

PSP_KEY_RE = re.compile(r"^psp/([xy])/p([0-9]{1,5}(?:\.[0-9]{1,6})?)/s([0-9]{1,2})$")
DOTS_KEY_RE = re.compile(r"^dots/([0-9]{1,3})_([0-9]{1,3})$")
OTHER_KEY_RE = re.compile(r"^(white|black|(ref|pattern)/[A-Za-z0-9][A-Za-z0-9_.-]{0,63})$")
#: Projector gammas an import takes: the range a rig file's ``[projector] gamma`` and the sim rig accept.
GAMMA_RANGE = (0.3, 5.0)
#: Float frames (EXR, float TIFF, ``.npy``) have no clipping level: their units are the renderer's or
#: the pipeline's. When the white capture's 99.9th percentile lies outside this range the frames are
#: scaled to put it at 1, since the decoder's thresholds and the models work in camera units.
LINEAR_RANGE = (0.5, 2.0)  # (0.1-10 kept a render at 0.12 x camera units: 80% of its object fell below the decoder's thresholds)
MIN_FRAME_SIDE = 16


@dataclass
class _ImportedFrame:
    name: str
    data: np.ndarray
    header: dict[str, Any] = field(default_factory=dict)


#: Image files an importer does not read; one named as a frame is refused by name (it was "missing").
OTHER_IMAGE_SUFFIXES = (".gif", ".bmp", ".ppm", ".pgm", ".pfm", ".hdr", ".jp2", ".jxl", ".heic", ".dng", ".raw")
#: Every image suffix a folder of frames may hold: what the importer reads, refuses as lossy, or does not read.
ANY_IMAGE_SUFFIXES = frozenset((*IMAGE_SUFFIXES, *LOSSY_SUFFIXES, *OTHER_IMAGE_SUFFIXES))


def _is_frame_key(key: str) -> bool:
    return bool(PSP_KEY_RE.match(key) or DOTS_KEY_RE.match(key) or OTHER_KEY_RE.match(key))


#: The first word of every frame name: an image whose name starts with one but is no frame name is a misspelt
#: frame (refused, naming it); any other image beside the frames (a thumbnail, a mask, a photo of the rig) is skipped.
FRAME_WORDS = frozenset({"psp", "dots", "white", "black", "ref", "pattern"})


def _meant_as_frame(rel: Path) -> bool:
    """Whether an image at ``rel`` (relative to its view folder) was meant as a frame: its name's (or in the
    ``psp/x/p20/s0.png`` layout its top folder's) first word, up to ``_``, ``-``, ``.`` or a space, is a frame's."""
    first = re.split(r"[_\-. ]", rel.parts[0], maxsplit=1)[0].lower()
    return first in FRAME_WORDS or first.rstrip("0123456789") in FRAME_WORDS  # white0001: a renderer's frame number


#: The arrays `sss export` writes beside the frames (``corr_xp.exr``, ``footprints_crops.exr`` ...): an import
#: of the export skips them without a word, as the docs say.
EXPORTED_MAPS = ("corr", "footprints", "transport", "gt")


def exported_names(vdir: Path) -> dict[Path, str]:
    """Frame keys of a view folder `sss export` wrote (so that it imports again): each stack's files by the
    ``keys.csv`` beside them (``psp/00.exr,psp/x/p11/s0``; the unwrapping and dot frames likewise), and its
    ``ref_<name>.exr`` / ``pattern_<name>.exr`` (arrays ``ref/<name>``, ``/`` written as ``_``) once any stack's
    keys are there; {} for any other folder. A keys.csv naming no frame, or a file outside its folder, is refused."""
    names: dict[Path, str] = {}
    for table in sorted(vdir.glob("*/keys.csv")):
        try:
            rows = table.read_text().splitlines()[1:]
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{table}: cannot be read ({exc})") from None
        for row in rows:
            file, _, key = row.partition(",")
            if not re.fullmatch(r"[0-9]{2,6}\.exr", file) or not _is_frame_key(key):
                raise InputError(f"{table}: {row[:80]!r} is no 'NN.exr,<frame key>' row (as sss export writes them)")
            names[table.parent / file] = key
    if names:
        for path in vdir.iterdir():
            kind, _, rest = path.stem.partition("_")
            if path.suffix == ".exr" and kind in ("ref", "pattern") and _is_frame_key(f"{kind}/{rest}"):
                names[path] = f"{kind}/{rest}"
    return names


def frame_files(vdir: Path, *, strict: bool = True) -> dict[str, Path]:
    """Frame files of one view by plan key: ``psp__x__p20__s0.png`` or ``psp/x/p20/s0.png`` (the layout
    `sss patterns` writes) are both ``psp/x/p20/s0``. Files of other types are ignored, and so are images
    whose names are not meant as frames (a thumbnail, a mask: one warning names them); an image whose name
    starts like a frame's but is no plan key is refused, naming it (``strict=False``: skipped, for readers
    that want only some keys, e.g. `sss decode` in a folder that also holds its own outputs). A view folder
    `sss export` wrote is read by its keys (:func:`exported_names`)."""
    files: dict[str, Path] = {}
    others: list[str] = []
    exported = exported_names(vdir)
    for path in sorted(vdir.rglob("*")):
        rel = path.relative_to(vdir)
        suffix = path.suffix.lower()
        if rel.parts[0].startswith("view_"):  # another view's folder (the import reads it as its own view)
            continue
        if path in exported:  # a view `sss export` wrote: its stacks' files named by their keys.csv
            if not path.is_file():
                raise InputError(f"{path} is not a regular file: frames must be image files")
            if exported[path] in files:
                raise InputError(f"{path} and {files[exported[path]]} are both frame {exported[path]!r}")
            files[exported[path]] = path
            continue
        if strict and suffix in ANY_IMAGE_SUFFIXES and not _meant_as_frame(rel):
            if not (exported and rel.parts[0].split("_")[0] in EXPORTED_MAPS):  # (an export's maps: skipped as said)
                others.append(rel.as_posix())  # beside the frames, not one of them
            continue
        if strict and suffix in LOSSY_SUFFIXES:
            raise InputError(f"{path}: {path.suffix} frames are lossy (8 x 8 blocks, halved colour resolution), which "
                             "corrupts fringes: save the camera's frames as PNG, TIFF, EXR or .npy")
        if (strict and suffix in OTHER_IMAGE_SUFFIXES
                and _is_frame_key(rel.with_suffix("").as_posix().replace("__", "/"))):  # said "missing: white"
            raise InputError(f"{path}: {path.suffix} is not a frame format the importer reads: save it as PNG, TIFF, "
                             "EXR or .npy")
        if suffix not in IMAGE_SUFFIXES:
            continue
        if not path.is_file():
            # said "missing: white" for a white.png that cannot be read (`sss decode`: "shifts [0, 2, 3]" for a FIFO)
            if strict or _is_frame_key(rel.with_suffix("").as_posix().replace("__", "/")):
                if path.is_dir():
                    raise InputError(f"{path} is a folder, not a frame file")
                if path.is_symlink() and not path.exists():
                    raise InputError(f"{path} is a broken symbolic link (or a loop)")
                if path.exists():
                    raise InputError(f"{path} is not a regular file (a FIFO or a device): frames must be image files")
            continue
        key = rel.with_suffix("").as_posix().replace("__", "/")
        if not _is_frame_key(key):
            if not strict:
                continue
            numbered = re.fullmatch(r"(.+?)[_.-]?([0-9]{3,6})", key)  # a renderer's frame number: white0001, black_0001
            hint = (f": without the renderer's frame number {numbered.group(2)} it would be frame {numbered.group(1)!r}"
                    if numbered and _is_frame_key(numbered.group(1)) else "")
            raise InputError(f"{path}: {key!r} is no frame name (expected psp__<x|y>__p<period>__s<n>, white, black, "
                             "ref__<name>, pattern__<name> (a name of ASCII letters, digits, '_', '.' and '-', at most "
                             f"64) or dots__<sx>_<sy>; see SESSION_FORMAT.md){hint}")
        if m := PSP_KEY_RE.match(key):  # one spelling per frame: p20.0 -> p20, s01 -> s1 (the capture plan's)
            key = f"psp/{m.group(1)}/p{float(m.group(2)):g}/s{int(m.group(3))}"
        if key in files:
            raise InputError(f"{path} and {files[key]} are both frame {key!r}")
        files[key] = path
    if others and files:
        warnings.warn(f"{vdir}: skipped {len(others)} image{'s' if len(others) > 1 else ''} whose name is no frame's "
                      f"({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}); frames are named psp__<x|y>__"
                      "p<period>__s<n>, white, black, ref__<name>, pattern__<name> or dots__<sx>_<sy>", stacklevel=3)
    return files


def psp_config_from_names(vdir: Path, keys: Iterable[str]) -> Any:
    """The PSP configuration the frame names describe; every (orientation, period) needs shifts 0..N-1."""
    from sssphase_core.processing.patterns import PSPConfig

    sets: dict[tuple[str, float], set[int]] = {}
    for key in keys:
        if m := PSP_KEY_RE.match(key):
            sets.setdefault((m.group(1), float(m.group(2))), set()).add(int(m.group(3)))
    if not sets:
        raise InputError(f"{vdir}: no psp__<x|y>__p<period>__s<n> frames")
    for (o, period), shifts in sorted(sets.items()):
        if shifts != set(range(len(shifts))) or not 3 <= len(shifts) <= MAX_SHIFTS:
            raise InputError(f"{vdir}: PSP frames {o}, period {period:g} have shifts {sorted(shifts)[:8]}; every set "
                             f"needs shifts 0..N-1 with 3 <= N <= {MAX_SHIFTS}")
    most = max(sorted(sets.items()), key=lambda item: len(item[1]))
    n = len(most[1])
    for (o, period), shifts in sorted(sets.items()):  # each set complete, but of another count: a stray or lost frame
        if len(shifts) != n:
            raise InputError(f"{vdir}: PSP frames {o}, period {period:g} have {len(shifts)} shifts but {most[0][0]}, "
                             f"period {most[0][1]:g} has {n} (up to s{n - 1}): every set shares one shift count")
    periods = sorted({p for _, p in sets})
    if periods[0] <= 0:  # before the orientations: "the y orientation has no PSP frames at period 0" misled
        raise InputError(f"{vdir}: a PSP period must be positive, got {periods[0]:g} in the frame names")
    for o in ("x", "y"):
        if (o, periods[0]) not in sets:
            raise InputError(f"{vdir}: the {o} orientation has no PSP frames at period {periods[0]:g}")
    try:
        return PSPConfig(period=periods[0], n_shifts=n, unwrap_periods=tuple(periods[1:]))
    except InputError as exc:  # e.g. more unwrapping periods than any plan has
        raise InputError(f"{vdir}: its PSP frame names: {exc}") from None


#: The smallest white level (99.9th percentile of a white capture, file units) taken for light: below it
#: (denormal floats) rescaling to camera units would overflow float32.
MIN_WHITE_LEVEL = 1e-30


def read_imported(path: Path, encoding: str = "linear", *, keep_grey: bool = False) -> tuple[np.ndarray, int]:
    """``(frame, n)``: a frame file as :func:`read_frame` reads it (integer codes decoded by ``encoding``, a grey
    file (H, W) with ``keep_grey``),
    with up to ``isp.NONFINITE_LIMIT`` of its values NaN / inf (a path tracer's degenerate samples) repaired
    from their neighbours, ``n`` of them; more is refused in one line."""
    from sssphase_core.processing.isp import NONFINITE_LIMIT, repair_nonfinite

    image = read_frame(path, finite=False, encoding=encoding, keep_grey=keep_grey)
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad > NONFINITE_LIMIT * image.size:
        raise InputError(f"{path}: {bad} of its {image.size} values are NaN or infinite (more than the "
                         f"{NONFINITE_LIMIT:.1%} a path tracer's stray samples make): the file or its renderer is broken")
    if not bad:
        return image, 0
    repaired, n = repair_nonfinite(image[..., None] if image.ndim == 2 else image)
    return repaired.reshape(image.shape), n


#: A fringe frame's level (99.9th percentile) may exceed the white capture's by this factor at most (noise,
#: a firefly), and a fringe set's mean (half the white's light) fall below it by this factor at most: beyond
#: either, the frames of one view were written in different units or exposures.
FRINGE_ABOVE_WHITE, SET_BELOW_WHITE = 2.0, 0.05


class FrameLoader:
    """One view's frame files read in turn, the one reader of `sss import` and `sss decode`: each file decoded to
    light by ``encoding`` (:func:`read_frame`), with a few NaN / inf values repaired (:func:`read_imported`;
    ``repair=False``: refused, as `sss decode` does), times ``scale``, and refused unless every frame has the first's
    size and that size is a camera frame's (at least ``MIN_FRAME_SIDE`` a side), and unless all are colour or all
    grey (one camera takes a view's frames; a grey file among colour ones is an export gone wrong). Frames come
    back (H, W, 3), a grey one repeated, or with ``raw`` ``(layout, method)`` a grey one (a colour camera's raw Bayer
    samples) demosaiced by ``method`` (:func:`isp.develop`). With ``bit_depth`` each file's codes are checked against
    that camera word's top (:func:`check_codes_fit`), before demosaicing (whose filters overshoot at clipped
    edges). ``repaired`` counts the values repaired so far."""

    def __init__(self, encoding: str = "linear", scale: float = 1.0, *, repair: bool = True,
                 raw: tuple[str, str] | None = None, bit_depth: int | None = None) -> None:
        self.encoding, self.scale, self.repair, self.raw, self.bit_depth = encoding, scale, repair, raw, bit_depth
        self.first: Path | None = None
        self.shape: tuple[int, ...] | None = None
        self.grey = False  # whether the first frame was grey (set with ``first``)
        self.repaired = 0

    def read(self, path: Path) -> np.ndarray:
        if self.repair:
            image, repaired = read_imported(path, self.encoding, keep_grey=True)
            self.repaired += repaired
        else:
            image = read_frame(path, encoding=self.encoding, keep_grey=True)
        if self.raw is not None:  # raw samples a tool saved as RGB: three equal channels
            image = as_grey(image)
        grey = image.ndim == 2
        if self.first is not None and grey != self.grey:
            kind = ("grey", "colour") if grey else ("colour", "grey")
            raise InputError(f"{path} is a {kind[0]} image, the other frames ({self.first.name} ...) {kind[1]}: one "
                             "camera takes a view's frames, so write them all colour or all grey")
        if self.bit_depth is not None:
            check_codes_fit(path, image * np.float32(self.scale), self.bit_depth)
        if grey and self.raw is not None:
            image = develop_raw(path, image, *self.raw)
        image = (np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image) * np.float32(self.scale)
        if self.shape is not None and image.shape != self.shape:
            self.refuse_size(path, image.shape)
        if self.first is None:
            self.first, self.shape, self.grey = path, image.shape, grey
        if min(image.shape[:2]) < MIN_FRAME_SIDE:
            raise InputError(f"{path} is {image.shape[1]}x{image.shape[0]}: smaller than a camera frame "
                             f"(at least {MIN_FRAME_SIDE} px a side)")
        return image

    def refuse_size(self, path: Path, shape: tuple[int, ...]) -> None:
        """Raise for a frame of another size than the first (a subclass words it for its command)."""
        assert self.shape is not None
        raise InputError(f"{path} is {shape[1]}x{shape[0]}, the other frames {self.shape[1]}x{self.shape[0]}")


def develop_raw(path: Path, mosaic: np.ndarray, layout: str, method: str) -> np.ndarray:
    """A grey (H, W) frame of raw Bayer samples in ``layout`` -> (H, W, 3) float32 demosaiced by ``method`` (no
    median: the camera's samples as they came); one line naming the file for odd sides."""
    from sssphase_core.processing.isp import develop

    if mosaic.shape[0] % 2 or mosaic.shape[1] % 2:
        raise InputError(f"{path} is {mosaic.shape[1]}x{mosaic.shape[0]}: raw Bayer samples (--bayer {layout} with grey "
                         "frames) come in whole 2 x 2 cells, so both sides are even")
    return develop(mosaic, 0.0, 1.0, median=False, method=method, layout=layout)


def as_grey(image: np.ndarray) -> np.ndarray:
    """A frame whose colour channels are all equal (a tool that saved grey samples as RGB) as (H, W); others as they
    are."""
    if image.ndim == 3 and image.shape[-1] in (3, 4) and all(np.array_equal(image[..., 0], image[..., c])
                                                             for c in (1, 2)):
        return image[..., 0]
    return image


def raw_mosaic_mode(white: Path, image: np.ndarray, bayer: str | None, demosaic: str) -> tuple[str, str] | None:
    """``(layout, method)`` when a view's frames, whose ``white`` file holds ``image`` (as read, grey kept), are a
    colour camera's raw Bayer samples to demosaic: grey files with
    a layout named (``--bayer``; ``demosaic`` ``other``: Malvar). One line when grey files look like raw samples
    (:func:`isp.detect_raw_mosaic`) and ``--bayer`` is ``auto`` (which of the two non-green sites is red the samples
    cannot tell), or a named layout puts the greens where the samples do not; None for colour files and
    monochrome ones."""
    from sssphase_core.processing.isp import GREEN_DIAGONAL, detect_raw_mosaic

    image = as_grey(image)
    if image.ndim != 2 or bayer is None or bayer.lower() == "none":
        return None
    diagonal, why = detect_raw_mosaic(image)
    if bayer.lower() == "auto":
        if diagonal is None:
            return None  # a monochrome camera's
        layouts = [k for k, d in GREEN_DIAGONAL.items() if d == diagonal]
        raise InputError(f"{white}: a grey frame whose {why.removeprefix('its ')}: a colour camera's raw Bayer samples? "
                         f"give its layout ({' or '.join(layouts)}) with --bayer to demosaic them, or --bayer none for "
                         "a monochrome camera")
    layout = bayer.upper()
    if diagonal is not None and GREEN_DIAGONAL[layout] != diagonal:
        raise InputError(f"{white}: --bayer {layout} puts green on the {GREEN_DIAGONAL[layout]} diagonal of each 2 x 2 "
                         f"cell, but these raw samples hold it on the {diagonal} one ({why.split('(')[-1].rstrip(')')}): "
                         f"{' or '.join(k for k, d in GREEN_DIAGONAL.items() if d == diagonal)}?")
    return layout, "malvar" if demosaic == "other" else demosaic


def check_one_camera(views: Sequence[tuple[Path, dict[str, Path]]], encoding: str, bayer: str | None,
                     demosaic: str) -> tuple[str, str] | None:
    """:func:`raw_mosaic_mode` of an import's views, which come from one camera: one line when their whites are of
    different kinds (grey or colour files, raw samples or a monochrome camera's; the first view's decided for all,
    and a colour view after a monochrome one imported its mosaic as grey light)."""
    kinds = []
    for _, files in views:
        white = read_imported(files["white"], encoding, keep_grey=True)[0]
        mode = raw_mosaic_mode(files["white"], white, bayer, demosaic)
        kinds.append((files["white"], "raw Bayer samples" if mode else "grey frames" if white.ndim == 2 else
                      "colour frames", mode))
    first = kinds[0]
    for other in kinds[1:]:
        if other[1] != first[1]:
            raise InputError(f"{other[0]} holds {other[1]}, {first[0]} {first[1]}: the views of one import come from "
                             "one camera (import them separately, with the options each needs)")
    return first[2]


#: A white capture whose 99.9th percentile is above this many times that of its 3 x 3 median holds fireflies
#: (:func:`white_levels` warns). Specular highlights give 1.05-3.7 on the Mitsuba renders' whites; 80 fireflies at
#: 1000 in a 256 x 192 white, 2,600.
FIREFLY_RATIO = 8.0


def _check_fringe_level(path: Path, image: np.ndarray, white_level: float, *, mean: bool = False) -> None:
    """Refuse fringe frames (or a set's mean, ``mean``) in other units or exposure than the view's white."""
    level = float(np.percentile(image, 99.9))
    if not mean and level > FRINGE_ABOVE_WHITE * white_level:
        level = _median_level(image)  # a path tracer's fireflies set the percentile: its level without them
    if not mean and level > FRINGE_ABOVE_WHITE * white_level:
        raise InputError(f"{path}: {level / white_level:.3g}x brighter than the white capture (99.9th percentiles "
                         f"{level:.3g} and {white_level:.3g}): a view's frames must share one exposure and units")
    if mean and level < SET_BELOW_WHITE * white_level:
        raise InputError(f"{path}*: the fringe set's mean is {level / white_level:.2g}x the white capture's level "
                         f"({level:.3g} and {white_level:.3g}), where it is about 0.5x: a view's frames must share "
                         "one exposure and units")


def _median_level(image: np.ndarray) -> float:
    """The 99.9th percentile of an (H, W[, C]) image's 3 x 3 median (per colour): its level without isolated pixels."""
    import cv2

    img = np.ascontiguousarray(image, np.float32)
    return float(np.percentile(cv2.medianBlur(img, 3) if img.ndim == 2 or img.shape[-1] in (1, 3, 4) else img, 99.9))


def white_levels(whites: Iterable[Path], encoding: str = "linear", blacks: Iterable[Path | None] = ()) -> list[float]:
    """Each white capture's level (its 99.9th percentile, file units); one line naming a white capture that
    holds no light (black, negative, denormal) instead of a view where nothing decodes, or, when the view's black
    (``blacks``, one per white) holds far more light, one saying that the two look swapped."""
    levels = []
    for path, black in itertools.zip_longest(whites, blacks):
        white = read_imported(path, encoding)[0]
        level = float(np.percentile(white, 99.9))
        try:
            if not level >= MIN_WHITE_LEVEL:
                raise InputError(f"{path}: the white capture holds no light (99.9th percentile {level:.3g}): it must be "
                                 "a linear image of the object under the projector's full white")
            check_not_negative(path, white, level)  # a negated white: its noise sets the level, the black gets the blame
        except InputError:
            dark = read_imported(black, encoding)[0] if black is not None else None
            # the black holds more light than the white holds in magnitude (not a negated white): swapped
            if dark is not None and _median_level(dark) > float(np.percentile(np.abs(white), 99.9)):
                check_black_below_white(black, dark, max(level, 0.0))  # (noise around zero in the white)
            raise
        robust = _median_level(white)
        if level > FIREFLY_RATIO * max(robust, 0.0):  # a refusal that followed named the fringes, not the fireflies
            times = f"{level / robust:.0f}x its 3 x 3 median's" if robust > 0 else "its 3 x 3 median's being"
            use = robust >= MIN_WHITE_LEVEL
            warnings.warn(f"{path}: its level (99.9th percentile {level:.3g}) is set by isolated bright pixels, "
                          f"{times} ({robust:.3g}): a renderer's fireflies? "
                          + ("the frames are compared with and scaled by the median's level instead; render with more "
                             "samples to be rid of them" if use else
                             "every frame is compared with and scaled by this level: repair them, or render with more "
                             "samples"), UserWarning, stacklevel=2)
            if use:  # 0.1% of the pixels at 100x the light set the 99.9th percentile: scaled by it, nothing decoded
                level = robust
        levels.append(level)
    return levels


#: The white captures of one import's views may differ in level by this factor at most (one exposure, one unit).
VIEW_LEVEL_RATIO = 100.0


def frame_scale(whites: Iterable[Path], levels: Iterable[float]) -> float:
    """The factor an import multiplies its frames by: 1 for integer files (their top code is the
    camera's range) and for float frames whose white level (:func:`white_levels`, highest over views) is
    within :data:`LINEAR_RANGE`, else ``1 / level``."""
    if any(stores_integers(p) for p in whites):
        return 1.0
    level = max(levels)
    return 1.0 if LINEAR_RANGE[0] <= level <= LINEAR_RANGE[1] else 1.0 / level


#: The camera words ``--bit-depth`` accepts (codes of that many bits, stored in the files' low bits).
BIT_DEPTHS = (8, 10, 12, 14, 16)


def codes_scale(bit_depth: int, file_depth: int | None, encoding: str) -> float:
    """The factor that puts a ``bit_depth``-bit camera's codes, stored in the low bits of ``file_depth``-bit files
    (read as code / the file's top code), at 1 for the camera's top code: ``(2^file_depth - 1) / (2^bit_depth - 1)``.
    One line for a depth no camera word has, float files, a depth above the files', or gamma-encoded codes."""
    if bit_depth not in BIT_DEPTHS:
        raise InputError(f"--bit-depth must be one of {', '.join(map(str, BIT_DEPTHS))} (the camera's bits per sample), "
                         f"got {bit_depth}")
    if file_depth is None:
        raise InputError("--bit-depth is for integer frame files (PNG, TIFF, .npy of integers): these frames are "
                         "float, light already; leave it out")
    if bit_depth > file_depth:
        raise InputError(f"--bit-depth {bit_depth} is more bits than the files hold ({file_depth}-bit)")
    if encoding != "linear" and bit_depth < file_depth:
        raise InputError(f"--bit-depth {bit_depth} reads linear codes in the files' low bits, but the frames are "
                         f"{encoding}-encoded: give --encoding linear if the codes are light")
    return float((2 ** file_depth - 1) / (2 ** bit_depth - 1))


def check_codes_fit(path: Path, image: np.ndarray, bit_depth: int) -> None:
    """Refuse a frame (camera units: the ``bit_depth``-bit top code reads 1) with codes above that top: the files
    hold wider codes, or codes already shifted to the top of their words."""
    peak = float(np.nanmax(image)) if image.size else 0.0
    if peak > 1 + 0.5 / (2 ** bit_depth - 1):
        raise InputError(f"{path} holds codes up to {peak * (2 ** bit_depth - 1):,.0f}, above a {bit_depth}-bit camera's "
                         f"top code {2 ** bit_depth - 1:,}: the codes are wider or already shifted to the top of the "
                         "16-bit words (then leave --bit-depth out)")


#: 16-bit files whose white stays below this share of their range get a hint: a camera of fewer bits, whose codes sit
#: in the words' low bits (a 14-bit camera's top is 0.25), read as light far below white and scored against 1.
LOW_CODES_LEVEL = 0.25


def _warn_low_codes(white: Path, level: float) -> None:
    """One line when 16-bit files' white level (99.9th percentile, read as code / 65535) is below
    :data:`LOW_CODES_LEVEL`, naming the camera word its codes would fit (``--bit-depth``)."""
    if not 0 < level < LOW_CODES_LEVEL:
        return
    fits = next((b for b in BIT_DEPTHS[1:] if level * 65535 < 2 ** b), 16)
    warnings.warn(f"{white}: the white's level is {level:.3g} of the 16-bit files' range ({level * 65535:,.0f} of "
                  f"65,535): if the camera gives {fits}-bit codes in the words' low bits, import with --bit-depth {fits} "
                  "(else its frames are read as light far below white: the decoder drops faint pixels and relit PSNR "
                  "is measured against a white it never reaches); if the camera is 16-bit, expose it longer",
                  UserWarning, stacklevel=3)


def check_not_negative(path: Path, image: np.ndarray, white_level: float, scale: float = 1.0) -> None:
    """Refuse a frame with many values far below zero (:data:`~sssphase_core.store.light.NEGATIVE_LIMIT` of the
    view's white level, in more than :data:`~sssphase_core.store.light.NEGATIVE_SHARE` of its values): a black
    level subtracted twice, a signed format read wrongly. Noise around zero passes. ``image`` and ``white_level``
    are in camera units, the file's values times ``scale`` (the message gives the file's)."""
    far = far_below_zero(image, white_level)
    if far:
        raise InputError(f"{path}: {100 * far:.3g}% of its values are below -{NEGATIVE_LIMIT:g} x the white "
                         f"capture's level (down to {float(image.min()) / scale:.3g}, the white's level "
                         f"{white_level / scale:.3g}): frames must be linear light, at most noise below zero")


def check_black_below_white(path: Path, black: np.ndarray, white_level: float, scale: float = 1.0) -> None:
    """Refuse a black capture brighter than the view's white (99.9th percentiles, the black's of its 3 x 3 median;
    camera units, the file's values times ``scale``): the two files swapped, or the black taken with the projector on."""
    level = _median_level(black)  # (a path tracer's fireflies are no light of the projector's)
    if level > white_level:
        raise InputError(f"{path}: the black capture is brighter than the white one (99.9th percentiles "
                         f"{level / scale:.3g} and {white_level / scale:.3g}): are white and black swapped? black is "
                         "the scene under the projector's black, white under its full white")


def frames_encoding(files: Iterable[Path], encoding: str = "auto") -> tuple[str, str]:
    """``(encoding, why)`` of one import's integer frame files (:func:`imageio.decode_codes`): ``encoding``
    as given, or for ``"auto"`` the files' own tags (:func:`imageio.declared_encoding`), which must agree
    (one line naming two that do not). Float frames are linear whatever is asked."""
    encoding = str(encoding).lower()
    if encoding not in ENCODINGS:
        raise InputError(f"--encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    seen: dict[str, tuple[Path, str]] = {}
    depths: dict[int, Path] = {}  # bit depth -> a file of it: one depth per import
    for path in files:
        depth = code_depth(path)  # None: float data, nothing to decode
        if depth is not None:
            if depths and depth not in depths:
                (other, first), = depths.items()
                raise InputError(f"{first} holds {other}-bit codes but {path} holds {depth}-bit ones: an import's frames "
                                 "come from one camera pipeline (the same bit depth and encoding); re-save them alike")
            depths[depth] = path
            enc, why = declared_encoding(path)
            if why == "JPEG data":  # whatever the file's name says
                raise InputError(f"{path} holds JPEG data, which is lossy (8 x 8 blocks, halved colour resolution) and "
                                 "corrupts fringes: save the camera's frames as PNG, TIFF, EXR or .npy")
            seen.setdefault(enc, (path, why))
    if not depths:  # no integer codes: nothing to decode, whatever was asked
        return "linear", "float frames"
    if encoding != "auto":
        return encoding, f"as --encoding {encoding} asked"
    if len(seen) > 1:
        (e1, (p1, w1)), (e2, (p2, w2)) = list(seen.items())[:2]
        raise InputError(f"{p1} is {e1} ({w1}) but {p2} is {e2} ({w2}): an import's frames share one encoding; "
                         "re-save them alike or give --encoding linear or srgb")
    return next(((e, why) for e, (_, why) in seen.items()), ("linear", "float frames"))


#: Linear frames of a fringe set average this share of the white capture's light (both above black) at every
#: pixel, whatever the light transport: the patterns' mean light is half the white's. An import warns beyond
#: the tolerance (gamma-encoded files, or a projector whose gamma is not the one the patterns were made for).
FRINGE_MEAN_SHARE, FRINGE_MEAN_TOLERANCE = 0.5, 0.1


def fringe_mean_share(sets: Iterable[np.ndarray], white: np.ndarray, black: np.ndarray, mask: np.ndarray) -> float:
    """The fringe sets' mean light as a share of the white's, both above black, colours summed: the median over
    decoded pixels (``mask``, (H, W)) lit above a fifth of their median white; NaN when none is. ``sets``: each
    (N, H, W, C) or (N, H, W) the shifts of one fringe set."""
    lit = (white - black).reshape(*white.shape[:2], -1).sum(-1)
    keep = mask & (lit > max(0.2 * float(np.median(lit[mask])), 0.0)) if mask.any() else mask  # (> 0: no division by 0)
    if not keep.any():
        return float("nan")
    shares = [((np.mean(s, axis=0) - black).reshape(*white.shape[:2], -1).sum(-1)[keep] / lit[keep]) for s in sets]
    return float(np.median(np.concatenate(shares)))


#: A fringe set averaging this share of the white's light or more is refused: another exposure than the white's
#: (twice it gives 1.00; sRGB codes read as linear give about 0.73, a projector gamma of 0.45 about 0.6, and both are
#: warned of instead).
FRINGE_MEAN_REFUSE = 0.85


def check_fringe_exposure(vdir: Path, proc: ViewProcessor, config: Any, input_share: float) -> None:
    """Refuse a view whose fringe sets (the learning inputs' ``input_share``, then each unwrapping set's) average
    :data:`FRINGE_MEAN_REFUSE` of the white's light or more (:func:`fringe_mean_share`): frames at twice the
    white's exposure imported with a warning about sRGB files and relit 6 dB low; unwrapping sets so exposed were
    blamed on the shifts' order."""
    white, black, mask = proc.images["white"], proc.images["black"], proc.corr.mask
    inputs = {key.rsplit("/", 1)[0] for key in config.input_keys}  # (their share is ``input_share``)
    sets: dict[str, list[np.ndarray]] = {}
    for key, image in proc.psp.items():
        if key.rsplit("/", 1)[0] not in inputs:
            sets.setdefault(key.rsplit("/", 1)[0], []).append(image)
    shares = {"the fringe frames": input_share}
    shares.update({f"{vdir / k.replace('/', '__')}__s*": fringe_mean_share([np.stack(f)], white, black, mask)
                   for k, f in sets.items()})
    for what, share in shares.items():
        if share >= FRINGE_MEAN_REFUSE:
            where = f"{vdir}: the fringe frames" if what == "the fringe frames" else what
            raise InputError(f"{where} average {share:.2f} of the white capture's light (above black, median over "
                             f"decoded pixels), where fringes of the white's exposure give {FRINGE_MEAN_SHARE:.2f}: they "
                             f"are about {share / FRINGE_MEAN_SHARE:.1f}x as exposed as the white; give every frame the "
                             "same exposure and units")


def untagged_encoding(files: dict[str, Path]) -> tuple[str, str] | None:
    """``(encoding, why)`` for integer frame files without a colour tag, from one view's fringes (``files`` by
    plan key): ``"srgb"`` when read as linear codes the first fringe set averages a share of the white's light
    (:func:`fringe_mean_share`, on the lit, unclipped pixels) outside :data:`FRINGE_MEAN_TOLERANCE` of
    :data:`FRINGE_MEAN_SHARE` and read as sRGB codes within it and nearer (a renderer's or a webcam's PNGs,
    saved without their sRGB chunk); ``None`` (keep them linear) otherwise."""
    sets = sorted({k.rsplit("/", 1)[0] for k in files if k.startswith("psp/")})
    if not sets:
        return None
    keys = [*sorted(k for k in files if k.startswith(sets[0] + "/")), "white", "black"]
    if not all(stores_integers(files[k]) for k in keys):  # float frames are light: nothing to tell
        return None
    codes = [read_frame(files[k], finite=False) for k in keys[:-2]]
    white, black = read_frame(files["white"], finite=False), read_frame(files["black"], finite=False)
    unclipped = (white < 0.999).all(-1) & (np.max(codes, axis=0) < 0.999).all(-1)
    keep = unclipped & projector_light(white, black)[1]
    if not keep.any():
        return None
    shares = {enc: fringe_mean_share([np.stack([decode_codes(c, enc) for c in codes])], decode_codes(white, enc),
                                     decode_codes(black, enc), keep) for enc in ("linear", "srgb")}
    off = {enc: abs(share - FRINGE_MEAN_SHARE) for enc, share in shares.items()}
    if not (off["linear"] > FRINGE_MEAN_TOLERANCE >= off["srgb"]) or off["srgb"] >= off["linear"]:
        return None
    return "srgb", (f"no colour tag; its fringes average {shares['srgb']:.2f} of the white's light read as sRGB codes, "
                    f"{shares['linear']:.2f} read as linear ones, where light gives {FRINGE_MEAN_SHARE:.2f}")


#: The projector's light (white less black, colours summed; its 99.9th percentile) must reach this share of
#: the white capture's level (three colours): a black frame as bright as the white one (a copy, the wrong
#: file, lights left on) decoded without a word.
PROJECTOR_LIGHT_SHARE = 0.05


def check_white_above_black(vdir: Path, white: np.ndarray, black: np.ndarray, white_level: float) -> None:
    """Refuse a view whose white capture is hardly brighter than its black one (:data:`PROJECTOR_LIGHT_SHARE`)."""
    light = float(np.percentile((white - black).reshape(-1, white.shape[-1] if white.ndim == 3 else 1).sum(-1), 99.9))
    if not light > PROJECTOR_LIGHT_SHARE * 3 * white_level:
        raise InputError(f"{vdir}: the white capture is hardly brighter than the black one (white - black reaches "
                         f"{light:.3g} where the white reaches {3 * white_level:.3g}, colours summed): black is the scene "
                         "under the projector's black, white under its full white")


#: Opposite shifts of a fringe set (n and n + N/2) sum to the same light at every pixel, whatever the transport,
#: the projector's gamma or the exposure: a pair of a set whose sum differs from another pair's by more than this
#: share of the larger holds a dropped, constant or foreign frame.
PAIR_SUM_TOLERANCE = 0.25


def check_opposite_shifts(vdir: Path, pair_sums: dict[str, list[np.ndarray]], white: np.ndarray, black: np.ndarray) -> None:
    """Refuse a fringe set whose opposite-shift pairs do not hold the same light (:data:`PAIR_SUM_TOLERANCE`).
    ``pair_sums``: set key (``psp/x/p20``) -> per pair n (0 <= n < N/2) the sum of frames n and n + N/2, (H, W, C)."""
    light, lit = projector_light(white, black)
    if not lit.any():
        return
    for set_key, sums in pair_sums.items():
        shares = [float(np.median(((np.asarray(t, np.float64) - 2 * black).reshape(*lit.shape, -1).sum(-1))[lit]
                                  / light[lit])) for t in sums]
        if len(shares) > 1 and max(shares) - min(shares) > PAIR_SUM_TOLERANCE * max(abs(v) for v in shares):
            n = len(shares)
            pairs = ", ".join(f"s{i} + s{i + n} hold {v:.2f}" for i, v in enumerate(shares))
            raise InputError(f"{vdir / set_key.replace('/', '__')}*: opposite shifts of a fringe set hold the same light "
                             f"at every pixel, but here {pairs} of the white's (above black, median over lit pixels): a "
                             "frame of the set is missing light, a copy of another frame, or from another exposure")


#: A full dot grid (``dots__{sx}_{sy}`` for every offset) lights every projector pixel once, so its frames
#: above black hold the white's light: beyond ``DOTS_LIGHT_REFUSE`` (a factor) the dot frames are refused,
#: beyond ``DOTS_LIGHT_WARN`` an import warns (another exposure, or a projector whose brightness follows the
#: image's content).
DOTS_LIGHT_REFUSE, DOTS_LIGHT_WARN = 2.0, 1.25


#: Float32 RGB copies of each held frame at the peak of a view's processing (the frame, its repaired and
#: demosaiced versions, the decode's stacks), and frames' worth of working memory beyond them: 26 frames of
#: 2400x1800 (52 MB each) peaked at 4.65 GB RSS, 3.1 copies each (`/usr/bin/time -f %M sss import ...`).
VIEW_COPIES_PER_FRAME = 3
VIEW_WORKING_FRAMES = 8


def check_view_memory(vdir: Path, files: dict[str, Path]) -> None:
    """Refuse, from the first frame's header, a view whose frames cannot be held in memory: the fringe, white,
    black and reference frames are kept as float32 RGB until the view is processed (dot grids stream), so
    frames that compress to almost nothing (a decompression bomb, or a 60 MP camera's) would otherwise end
    in the kernel's out-of-memory kill, not in a message."""
    from sssphase_core.compute import available_memory

    held = sum(1 for k in files if not k.startswith(("dots/", "pattern/")))
    shape = frame_shape(files["white"])
    need = (VIEW_COPIES_PER_FRAME * held + VIEW_WORKING_FRAMES) * shape[0] * shape[1] * 3 * 4
    free = available_memory()
    if free is not None and need > free:
        raise InputError(f"{vdir}: its {held} frames of {shape[1]}x{shape[0]} need about {need / 2**30:.1f} GiB to import, "
                         f"more than the {free / 2**30:.1f} GiB free: bin the frames (2x2 quarters it), "
                         "crop them to the object, or import on a machine with more memory")


def _import_order(key: str) -> tuple[int, ...]:
    """The order an import reads a view's frames in: the others as named, then the dot frames as a capture takes
    them (rows of shifts: sy, then sx), so that footprint crops are stored in capture order."""
    if m := DOTS_KEY_RE.match(key):
        sx, sy = (int(v) for v in m.groups())
        return (1, sy, sx)
    return (0,)


def check_dot_frames(vdir: Path, files: dict[str, Path], planned: int | None = None) -> tuple[int, int]:
    """``(spacing, stride)`` of a view's dot grid ((0, 1) without dot frames); one line naming the missing frames of
    an incomplete grid. A sparse grid (`sss capture --dot-stride S`: every S-th shift along x and y) has offsets
    that are multiples of the stride (their greatest common divisor); its spacing is the ``planned`` one (the
    plan.json beside the frames), else the last offset plus the stride."""
    offsets = [tuple(int(v) for v in m.groups()) for k in files if (m := DOTS_KEY_RE.match(k))]
    if not offsets:
        return 0, 1
    stride = math.gcd(*(v for o in offsets for v in o)) or 1
    last = max(v for o in offsets for v in o)
    spacing = int(planned) if planned and planned > last else last + (stride if stride > 1 else 1)
    if stride >= spacing:  # one frame (dots__0_0) or offsets beyond a plan's spacing: a whole grid of that spacing
        stride = 1
    lattice = range(0, spacing, stride)
    missing = sorted({(sx, sy) for sx in lattice for sy in lattice} - set(offsets), key=lambda o: (o[1], o[0]))
    if missing:
        named = ", ".join(f"dots__{sx}_{sy}" for sx, sy in missing[:4]) + (" ..." if len(missing) > 4 else "")
        grid = f"{spacing} x {spacing} dot grid" + (f" at dot stride {stride}" if stride > 1 else "")
        raise InputError(f"{vdir}: {len(missing)} of the {len(lattice) ** 2} frames of a {grid} are "
                         f"missing ({named}): a grid's frames together light every projector pixel once; give them "
                         "all, or none")
    return spacing, stride


def planned_dot_spacing(folder: Path) -> int | None:
    """The dot grids' spacing the ``plan.json`` in ``folder`` names (`sss patterns` and `sss export` write one),
    or None."""
    from sssphase_core.capture.psp_folder import read_plan

    path = folder / "plan.json"
    if not path.is_file():
        return None
    spacings = {f.get("params", {}).get("spacing") for f in read_plan(path).get("frames", []) if f.get("kind") == "dots"}
    return next((int(v) for v in spacings if isinstance(v, int) and not isinstance(v, bool) and v > 0), None)


#: :class:`DotPlacement`: a dot frame's light must fall within this many projector px (along x and y, modulo the
#: spacing) of its name's dots at the decoded points (the sim apple's frames at spacing 8: within 0.03 px; a frame
#: named dots__<sy>_<sx>, or another frame's copy, is whole pixels off; half a pixel is left to another tool's idea of
#: where a projector pixel's centre lies) ...
DOT_PLACE_TOLERANCE = 0.75
#: ... where its light is concentrated enough to say (the resultant length of its phase modulo the spacing: 0.48-0.51
#: for the apple at spacing 8; light spread wider than the spacing says nothing) ...
DOT_PLACE_MIN_CONCENTRATION = 0.2
#: ... and hold at least this share of a grid frame's light (the white's, above black, over the spacing squared).
DOT_FRAME_MIN_LIGHT = 0.25
#: A dot frame's light counts at a pixel up to this many times the white's there (noise; a firefly counts no more).
DOT_LIGHT_CAP = 1.5


class DotPlacement:
    """Where an imported dot frame's light falls in projector coordinates, against where its name puts the dots:
    frames named the other way round (``dots__<sy>_<sx>``), copied, or holding no light imported as footprints of
    the wrong pixels, and the grid's light summed over all frames could not tell.

    ``xp``, ``yp``, ``mask`` (H, W): the view's decoded correspondences; ``light`` (H, W): the white above black
    (colours summed); ``spacing``: the grid's."""

    def __init__(self, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray, light: np.ndarray, spacing: int) -> None:
        self.mask, self.spacing = np.asarray(mask, bool), int(spacing)
        turn = 2j * np.pi / self.spacing
        self.ex = np.exp(turn * np.asarray(xp, np.float64)[self.mask]).astype(np.complex64)  # (M,) a pixel's x phase
        self.ey = np.exp(turn * np.asarray(yp, np.float64)[self.mask]).astype(np.complex64)
        lit = np.clip(np.asarray(light, np.float32)[self.mask], 0, None)
        self.frame_light = float(lit.sum()) / self.spacing ** 2  # a grid frame's
        # no pattern lights a pixel more than full white does: above it, a path tracer's firefly (not yet repaired)
        self.cap = DOT_LIGHT_CAP * lit + float(np.percentile(lit, 99)) * 0.01

    def check(self, path: Path, sx: int, sy: int, dots: np.ndarray) -> None:
        """One line unless the ``dots`` (H, W[, 3], above black) of frame ``(sx, sy)`` light its own dots."""
        w = np.clip(dots.reshape(*self.mask.shape, -1).sum(-1)[self.mask], 0, self.cap).astype(np.float32)
        total = float(w.sum())
        if not total >= DOT_FRAME_MIN_LIGHT * self.frame_light:
            raise InputError(f"{path}: holds {total / max(self.frame_light, 1e-30):.2f} of the light a dot frame of this "
                             f"{self.spacing} x {self.spacing} grid gives at the decoded points (the white's over "
                             f"{self.spacing ** 2}): an empty or black frame? give the frame the projector showed")
        found = []
        for e, shift in ((self.ex, sx), (self.ey, sy)):
            z = complex(np.dot(w, e)) * np.exp(-2j * np.pi * shift / self.spacing) / total
            found.append((np.angle(z) * self.spacing / (2 * np.pi), abs(z)))
        if min(r for _, r in found) < DOT_PLACE_MIN_CONCENTRATION or all(abs(o) <= DOT_PLACE_TOLERANCE for o, _ in found):
            return
        at = [round(shift + o) % self.spacing for shift, (o, _) in zip((sx, sy), found, strict=True)]
        why = ("x and y swapped in the dot frames' names? (dots__<sx>_<sy>: sx the dots' projector column, sy their row)"
               if at == [sy, sx] else "a mislabelled or copied dot frame?")
        raise InputError(f"{path}: its light falls on projector column {at[0]} and row {at[1]} of each "
                         f"{self.spacing} x {self.spacing} cell (at the decoded points), where dots__{sx}_{sy} lights "
                         f"column {sx} and row {sy}: {why}")


def check_dots_light(vdir: Path, dot_sum: np.ndarray, n_dots: int, white: np.ndarray, black: np.ndarray) -> float:
    """The dot frames' light (summed, above black) as a share of the white's (median over lit pixels), refused
    or warned about beyond :data:`DOTS_LIGHT_REFUSE` / :data:`DOTS_LIGHT_WARN`; returned for the view's record."""
    light, lit = projector_light(white, black)
    if not lit.any():
        return float("nan")
    share = float(np.median((dot_sum - n_dots * np.asarray(black, np.float64)).reshape(*lit.shape, -1).sum(-1)[lit]
                            / light[lit]))
    what = (f"{vdir}: the {n_dots} dot-grid frames together hold {share:.2f} of the white capture's light (above black, "
            "median over lit pixels), where a full grid lights every projector pixel once and gives 1.00")
    if not 1 / DOTS_LIGHT_REFUSE <= share <= DOTS_LIGHT_REFUSE:
        raise InputError(f"{what}: they are not dot grids of this view at its exposure (the white's, the black's or "
                         "other files, or another exposure)")
    if not 1 / DOTS_LIGHT_WARN <= share <= DOTS_LIGHT_WARN:
        warnings.warn(f"{what}: the measured transport will be {share:.2f}x too bright (another exposure than the "
                      "white's, or a projector whose brightness follows the image's content)", stacklevel=3)
    return share


#: Integer frames with more than this share of their fringe values at the top code are called clipped when
#: nothing decodes (a saturated fringe has no modulation, which the decoder reports as low modulation).
CLIPPED_SHARE = 0.25


def nothing_decoded(vdir: Path, coverage: dict[str, int], clipped: float = 0.0, period: float | None = None,
                    white_level: float | None = None) -> str:
    """One line for a view where no camera pixel decoded, with the reasons' shares; ``clipped``: the share of
    the fringe frames' values at an integer file's top code; ``period``: the finest fringes' (projector px);
    ``white_level``: the white's (99.9th percentile, camera units), said when far below a camera's exposure."""
    if clipped > CLIPPED_SHARE:
        return (f"{vdir}: no camera pixel decoded: {100 * clipped:.0f}% of the fringe frames' values sit at the files' "
                "top code (the camera clipped them, so no fringe is left): capture with a shorter exposure")
    total = max(1, sum(coverage.values()))
    reasons = ", ".join(f"{100 * n / total:.0f}% {name.lower().replace('_', ' ')}"
                        for name, n in sorted(coverage.items(), key=lambda kv: -kv[1]) if n)
    fine = coverage.get("LOW_MODULATION", 0) >= 0.2 * total  # lit (not shadow) pixels whose fringes are gone
    if white_level is not None and white_level < EXPOSED_LEVEL:  # (an underexposed view was told only "linear images")
        return (f"{vdir}: no camera pixel decoded ({reasons}): the white's level is {white_level:.3g} in camera units "
                f"where white is about 1, below the decoder's thresholds: {DIM_ADVICE}")
    return (f"{vdir}: no camera pixel decoded ({reasons}): the frames must be linear images of the patterns "
            "their names give (`sss patterns` writes them), with fringes above the noise"
            + (f"; lit pixels without fringes: the finest period ({period:g} projector px) may be too fine for the "
               "object's scattering or the camera's resolution (`sss patterns --period` makes coarser ones)"
               if fine and period else ""))


#: Shares of a view's decoded pixels beyond which an import warns: mapped outside the projector (a wrong
#: --projector, or fringes of another convention: shifts numbered from another phase origin moved every point by
#: a quarter of the coarsest period and put 15.5% outside, shifts numbered the other way 13%, x and y swapped 3.4%;
#: 361 views of simulated captures and imports: at most 0.08%), or at an integer file's top code (clipped light,
#: underestimated).
OUTSIDE_WARN, CLIPPED_WARN = 0.02, 0.01
#: A pixel holds light above this share of the white's level (measured: 0-1% of those decode as too faint on every
#: Mitsuba and demo view, 80% on a 16-bit capture exposed at 0.12); a warning when more than DIM_WARN of them decode as
#: too faint (LOW_MODULATION, SHADOW).
DIM_LIT, DIM_WARN = 0.05, 0.2
#: A reference capture's light over what the white and its pattern give (:func:`reference_match`) outside this
#: range is warned of (Mitsuba renders' references: 0.99-1.00; twice the exposure: 1.9, half: 0.5; far brighter than
#: full white could make it is refused before: capture.processing.OUTLIER_MAX_SHARE).
REFERENCE_BRIGHTNESS = (0.67, 1.5)
#: A reference with more than this share of its lit values replaced by the outlier repair is warned of (fireflies
#: are a few in 10^4; a reference at 2x the white's exposure had 1,152 of 9,216 replaced, 12%).
REFERENCE_REPAIR_WARN = 0.01
#: Warn when more than this share of the decodable pixels failed to unwrap (frames out of order, wrong periods).
UNWRAP_WARN = 0.2


#: Decoded pixels whose white (above black) is below this share of the view's median white are left out of the
#: reference checks (:func:`reference_match`).
WHITE_SHARE_FOR_REFERENCE = 0.05
#: Below this correlation between a reference capture and its pattern at the decoded points, an import warns.
REFERENCE_MATCH_WARN = 0.3


def reference_match(proc: ViewProcessor, frames: list[dict[str, Any]], gamma: float,
                    brightness: dict[str, float] | None = None) -> dict[str, float]:
    """Per reference capture of a decoded view: the correlation, over decoded pixels, between its light (above
    black, relative to the white's) and the light its pattern sends to each pixel's decoded projector point.

    Scattering blurs but keeps it high (the demo's and the stand-ins' references: see the tests); a pattern
    made for another projector size (a wrong ``--projector``) or another image gives about 0. ``brightness``,
    when given, gets each capture's mean light over the mean its pattern sends: scattering moves light but
    keeps its sum, so about 1 (a correlation cannot see a reference of another exposure or units).
    """
    from sssphase_core.processing.patterns import PlannedFrame
    from sssphase_core.processing.projector import emitted_light

    m = proc.corr.mask.copy()
    lit = (proc.images["white"] - proc.images["black"]).mean(-1)
    # decoded pixels whose white is (nearly) black: a ratio to it is noise over noise (6 such pixels of 5,803, their
    # ratios up to 3e4, made a reference 27x too bright and uncorrelated with its pattern)
    if m.any():
        m &= lit > WHITE_SHARE_FOR_REFERENCE * float(np.median(lit[m]))
    white = lit[m]
    found = {}
    for f in frames:
        name = f["name"].removeprefix("ref/")
        if name in ("white", "black") or f["name"] not in proc.images:
            continue
        pattern = proc.patterns.get(f["name"]) if f["kind"] == "image" else PlannedFrame(f["key"], f["kind"], f["params"], 1.0).pattern()
        if pattern is None:
            continue
        light = emitted_light(np.asarray(pattern, np.float32)[None], gamma)[0]
        light = light.mean(-1) if light.ndim == 3 else light
        ix = np.clip(np.round(proc.corr.xp[m]).astype(int), 0, light.shape[1] - 1)
        iy = np.clip(np.round(proc.corr.yp[m]).astype(int), 0, light.shape[0] - 1)
        seen = (proc.images[f["name"]] - proc.images["black"])[m].mean(-1) / white
        sent = light[iy, ix]
        if seen.std() > 0 and sent.std() > 0:
            found[name] = float(np.corrcoef(seen, sent)[0, 1])
        if brightness is not None and sent.mean() > 0:  # the reference as it came: the outlier repair clips a
            # brighter exposure towards the white's level (2x the white read 1.3x after it, and was not warned of)
            raw = (proc.unrepaired.get(f["name"], proc.images[f["name"]]) - proc.images["black"])[m].mean(-1) / white
            brightness[name] = float(_trimmed_mean(raw) / sent.mean())
    return found


#: The brightest share of a reference's pixels its brightness leaves out (a path tracer's fireflies: a few in 10^4).
BRIGHTNESS_TRIM = 0.002


def _trimmed_mean(values: np.ndarray) -> float:
    """The mean of ``values`` (N,) with the brightest :data:`BRIGHTNESS_TRIM` of them left out."""
    drop = int(BRIGHTNESS_TRIM * values.size)
    return float(np.partition(values, values.size - drop - 1)[:values.size - drop].mean()) if drop else float(values.mean())


#: A white level (camera units) at or above which a view's dropped pixels are not for want of exposure.
EXPOSED_LEVEL = 0.3
#: What to do about a white far below 1 (frames read as their type's fraction: a 12-bit camera's codes in 16-bit
#: files read as at most 1/16, and were told to expose longer).
DIM_ADVICE = ("expose the camera longer; if the files hold a 10-, 12- or 14-bit camera's codes in 16 bits, import with "
              "--bit-depth 10, 12 or 14; scale a render's frames so that its white is about 1")


def _warn_dim_view(vdir: Path, white: np.ndarray, reason: np.ndarray, period: float | None = None) -> None:
    """One line when many well-lit pixels were dropped as too faint (the decoder's thresholds are in camera units:
    frames exposed far below their top code, or a render in its own units, lose most of their object quietly), or
    when, well exposed, they lost their fringes (the finest ``period``, projector px, too fine for the scattering)."""
    from sssphase_core.processing.psp import Reason

    grey = np.asarray(white, np.float32).reshape(*reason.shape, -1).mean(-1)
    lit = grey > DIM_LIT * float(np.percentile(grey, 99.9))
    level = float(np.percentile(white, 99.9))  # the white's level as every other line of the import gives it
    faint = lit & np.isin(reason, (int(Reason.LOW_MODULATION), int(Reason.SHADOW)))
    if not (lit.any() and faint.sum() > DIM_WARN * lit.sum()):
        return
    share = f"{vdir}: {100 * faint.sum() / lit.sum():.0f}% of the pixels holding light were dropped"
    if level >= EXPOSED_LEVEL and period:  # exposed as a camera should be: the fringes, not the light, are missing
        warnings.warn(f"{share}: well exposed (this white's level is {level:.3g}), their fringes show too little "
                      f"modulation: the finest period ({period:g} projector px) may be too fine for the object's "
                      "scattering or the camera's resolution (`sss patterns --period` makes coarser ones; relighting "
                      "and scores leave those pixels out)", stacklevel=3)
        return
    warnings.warn(f"{share} as too faint for the decoder (fringe modulation or light below its thresholds, in camera "
                  f"units where white is about 1; this white's level is {level:.3g}): {DIM_ADVICE}", stacklevel=3)


def _warn_suspect_view(vdir: Path, coverage: dict[str, int], size: tuple[int, int], fringes_clipped: float,
                       white: np.ndarray, mask: np.ndarray, top: float | None, mean_share: float = 0.5,
                       gamma: float = 2.2, encoding: str = "linear") -> None:
    """One warning line each for what an import cannot refuse but the user should know: many pixels mapped
    outside the projector, clipped fringes or white (integer files; ``top`` the white's top code), or
    fringes whose mean is not half the white's light (``mean_share``, :func:`fringe_mean_share`)."""
    if abs(mean_share - FRINGE_MEAN_SHARE) > FRINGE_MEAN_TOLERANCE and fringes_clipped <= CLIPPED_WARN:  # (clipping: below)
        hint = ("if the files are gamma-encoded (sRGB), import with --encoding srgb; " if encoding == "linear" else
                f"the files were decoded as {encoding}: if they are linear, import with --encoding linear; ")
        warnings.warn(f"{vdir}: the fringe frames average {mean_share:.2f} of the white capture's light (above black, "
                      f"median over decoded pixels) where linear frames give {FRINGE_MEAN_SHARE:.2f}: {hint}if the "
                      f"projector's gamma is not {gamma:g} (a renderer that takes pattern values as light has gamma 1), "
                      "make the patterns for the right one (`sss patterns --gamma`) and import with that --gamma; the "
                      "white and the fringes must share one exposure",
                      stacklevel=3)
    valid, outside = coverage.get("VALID", 0), coverage.get("OUTSIDE", 0)
    inconsistent = coverage.get("UNWRAP_INCONSISTENT", 0)
    if inconsistent > UNWRAP_WARN * (valid + inconsistent):
        warnings.warn(f"{vdir}: {100 * inconsistent / (valid + inconsistent):.0f}% of the fringe-lit pixels did not "
                      "unwrap consistently over the fringe periods and were dropped: are the shifts s0, s1, ... in the "
                      "order they were projected, and the periods in the file names the projected ones?", stacklevel=3)
    if outside > OUTSIDE_WARN * (valid + outside):
        warnings.warn(f"{vdir}: {100 * outside / (valid + outside):.0f}% of the decoded pixels map outside the "
                      f"{size[0]}x{size[1]} projector: is --projector right? (else the fringes' conventions: shifts "
                      "numbered the other way or from another phase origin, x and y swapped; `sss patterns` writes the "
                      "frames a renderer should project)", stacklevel=3)
    if fringes_clipped > CLIPPED_WARN:
        warnings.warn(f"{vdir}: {100 * fringes_clipped:.1f}% of the fringe frames' values sit at the files' top code "
                      "(clipped): their light and modulation are underestimated; capture with a shorter exposure",
                      stacklevel=3)
    if top is not None and mask.any():
        clipped = float((white[mask] >= 0.999 * top).any(axis=-1).mean())
        if clipped > CLIPPED_WARN:
            warnings.warn(f"{vdir}: the white capture is clipped at {100 * clipped:.1f}% of the decoded pixels (its "
                          "top code): their light is underestimated; capture it with a shorter exposure", stacklevel=3)


#: How far the decoded map must lean to the swapped axes before an import says x and y look swapped: the product of
#: the x coordinate's change down the camera's rows and the y coordinate's across its columns, over the product of x's
#: across and y's down (median steps between decoded neighbours). Upright rigs: 0.002 to 0.09 over 391 simulated and
#: imported views on this machine (0.43 with clipped fringes); the x and y frames swapped: 73; frames of noise: 1.3.
SWAPPED_AXES_RATIO = 4.0


def _median_step(coordinate: np.ndarray, mask: np.ndarray, axis: int) -> float:
    """Median |change| of a decoded projector coordinate (H, W) between neighbours along ``axis`` (both decoded)."""
    step = np.abs(np.diff(np.where(mask, coordinate, np.nan), axis=axis))
    step = step[np.isfinite(step)]
    return float(np.median(step)) if step.size else float("nan")


def warn_swapped_axes(vdir: Path, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray) -> None:
    """One warning when the decoded map (``xp``, ``yp``, ``mask``: (H, W)) leans to the swapped axes, the x fringes'
    projector columns changing down the camera's rows and the y fringes' rows across its columns (by
    :data:`SWAPPED_AXES_RATIO`): the psp__x and psp__y frames swapped, which decode every pixel inside the projector
    and match a symmetric reference (a checkerboard), or a camera turned by 90 degrees."""
    x_down, x_across = _median_step(xp, mask, 0), _median_step(xp, mask, 1)
    y_down, y_across = _median_step(yp, mask, 0), _median_step(yp, mask, 1)
    if x_down * y_across > SWAPPED_AXES_RATIO * x_across * y_down:  # (False with NaN: too few decoded neighbours)
        warnings.warn(f"{vdir}: the x fringes' projector columns change down the camera's rows ({x_down:.2g} projector "
                      f"px per row against {x_across:.2g} per column) and the y fringes' rows across its columns: are the "
                      "psp__x and psp__y frames swapped? (vertical fringes, psp__x, encode the projector's columns; if the "
                      "camera is turned 90 degrees against the projector, ignore this)", stacklevel=3)


#: How a camera that demosaics its own Bayer frames did it, for ``sss import --demosaic``: the methods
#: ``isp.demosaic`` reproduces, or ``other`` (unknown: only the silhouette's bleed is dropped).
IMPORT_DEMOSAIC = ("malvar", "opencv", "other")


def check_distinct_orientations(vdir: Path, sets: list[np.ndarray]) -> None:
    """Refuse a view whose y fringe frames are its x ones (``sets``: one (N, H, W, C) set per orientation): vertical
    and horizontal fringes cannot give the same images, and a folder of the x frames copied as the y ones decoded
    every pixel's y from its x without a word."""
    if len(sets) == 2 and sets[0].shape == sets[1].shape:
        scale = float(np.abs(sets[0]).max(initial=0.0))
        if scale > 0 and float(np.abs(sets[0] - sets[1]).max(initial=0.0)) <= 1e-6 * scale:
            raise InputError(f"{vdir}: the y fringe frames (psp__y__*) hold the same images as the x ones (psp__x__*): "
                             "vertical and horizontal fringes cannot; write each orientation's own frames (`sss "
                             "patterns` names them)")


def _input_sets(proc: ViewProcessor, config: Any) -> list[np.ndarray]:
    """The view's learning inputs as fringe sets, each (N, H, W, 3): one per orientation (as captured)."""
    keys, n = config.input_keys, config.n_shifts
    return [np.stack([proc.psp[k] for k in keys[i:i + n]]) for i in range(0, len(keys), n)]


def _lit_white(proc: ViewProcessor) -> tuple[np.ndarray, np.ndarray]:
    """The view's white above black (H, W, C) and its well-lit pixels (H, W): colours summed above a quarter of
    their 99th percentile (the pixels the Bayer readings use)."""
    white = proc.images["white"] - proc.images.get("black", 0)
    lit = white.sum(-1, dtype=np.float64)  # (a stray 3e38 overflows float32)
    return white, lit > 0.25 * float(np.percentile(lit, 99))


def _noise_layout(proc: ViewProcessor, config: Any) -> tuple[str | None, str]:
    """The Bayer layout the view's noise shows, and why (:func:`isp.detect_bayer_layout`)."""
    from sssphase_core.processing.isp import detect_bayer_layout

    white, lit = _lit_white(proc)
    return detect_bayer_layout(_input_sets(proc, config), white, lit)


def _detect_bayer(proc: ViewProcessor, config: Any, demosaic: str) -> str:
    """Set ``proc.camera_isp`` to the Bayer layout the view's frames show (:func:`_noise_layout`, on the lit pixels
    of the white) before anything decodes them; returns the reason either way."""
    layout, why = _noise_layout(proc, config)
    if layout is not None:
        proc.camera_isp = {"bayer": layout, "demosaic": demosaic, "median": False}
    return f"{layout}: {why}" if layout else f"none: {why}"


def _check_named_layout(vdir: Path, proc: ViewProcessor, config: Any, layout: str) -> None:
    """Warn when the Bayer layout the view's noise shows (:func:`_noise_layout`) is not the ``--bayer`` one: frames
    a GRBG camera demosaiced, imported as RGGB, relit 9 dB low without a word."""
    found, why = _noise_layout(proc, config)
    if found is not None and found != layout:
        warnings.warn(f"{vdir}: --bayer {layout}, but {why}: is the camera's layout {found}? "
                      "(relighting compares its relit fringes through the layout named)", UserWarning, stacklevel=3)


def _detect_demosaic(proc: ViewProcessor, config: Any) -> str | None:
    """For a view with a Bayer layout (given or found) whose demosaicing was not said (``--demosaic other``): the
    method its finest fringes show (:func:`isp.detect_demosaic`), set in ``proc.camera_isp`` so that relighting
    compares relit fringes through it; returns the reason either way (None: no layout)."""
    from sssphase_core.processing.isp import detect_demosaic

    if not proc.camera_isp or not proc.camera_isp.get("bayer"):
        return None
    method, why = detect_demosaic(_input_sets(proc, config)[0], proc.camera_isp["bayer"], _lit_white(proc)[1])
    if method is not None:
        proc.camera_isp = {**proc.camera_isp, "demosaic": method}
    return f"{method or 'other'}: {why}"


def check_plan_file(folder: Path, size: tuple[int, int], gamma: float, config: Any) -> None:
    """Refuse an import whose options or frame names disagree with the ``plan.json`` beside its frames (as `sss
    patterns` writes it): the projector size, its gamma, the PSP periods and shifts (a plan of a 320x240
    projector beside frames imported as 256x192 was ignored in silence). No plan.json: nothing to check."""
    from sssphase_core.capture.psp_folder import psp_from_plan, read_plan

    path = folder / "plan.json"
    if not path.is_file():
        return
    plan = read_plan(path)
    if tuple(plan["projector"]) != tuple(size):
        raise InputError(f"{path} is the plan of a {plan['projector'][0]}x{plan['projector'][1]} projector, but "
                         f"--projector says {size[0]}x{size[1]}: give the size its patterns were made for")
    if "gamma" in plan and abs(float(plan["gamma"]) - gamma) > 1e-6:
        raise InputError(f"{path} made its patterns for a projector gamma of {float(plan['gamma']):g}, but --gamma says "
                         f"{gamma:g}: pass --gamma {float(plan['gamma']):g}")
    if plan.get("psp"):
        planned = psp_from_plan(plan, path)
        said = (planned.period, planned.n_shifts, tuple(sorted(planned.unwrap_periods)))
        named = (config.period, config.n_shifts, tuple(sorted(config.unwrap_periods)))
        if said != named:
            raise InputError(f"{path} plans PSP period {said[0]:g}, {said[1]} shifts, unwrapping periods "
                             f"{', '.join(f'{v:g}' for v in said[2]) or 'none'}, but the frame names say period "
                             f"{named[0]:g}, {named[1]} shifts, unwrapping {', '.join(f'{v:g}' for v in named[2]) or 'none'}: "
                             "are these frames of that plan?")


def import_folder(folder: Path, root: Path, name: str, projector_size: tuple[int, int], *, patch: int = 32,
                  gamma: float = 2.2, encoding: str = "auto", bayer: str | None = "auto",
                  demosaic: str = "other", angles: Sequence[float] | None = None,
                  bit_depth: int | None = None) -> Session:
    """:func:`_import_folder` holding the session's lock (:func:`~sssphase_core.store.locks.session_lock`): a
    second import (or capture) into the same session is refused while this one runs."""
    with session_lock(Path(root), check_object_name(name)):
        return _import_folder(folder, root, name, projector_size, patch=patch, gamma=gamma, encoding=encoding,
                              bayer=bayer, demosaic=demosaic, angles=angles, bit_depth=bit_depth)


def _import_folder(folder: Path, root: Path, name: str, projector_size: tuple[int, int], *, patch: int = 32,
                   gamma: float = 2.2, encoding: str = "auto", bayer: str | None = "auto",
                   demosaic: str = "other", angles: Sequence[float] | None = None,
                   bit_depth: int | None = None) -> Session:
    """Import frames captured by another rig into a session, processed by the capture engine's
    :class:`ViewProcessor` exactly like a capture.

    ``folder/view_NNN/`` (or ``folder`` itself for one view) holds one image per plan key, with '/'
    written as '__' or as folders (``psp__x__p20__s0.png`` or ``psp/x/p20/s0.png``, ``white.png``,
    ``black.png``, ``ref__checkerboard.png``, optionally ``dots__{sx}_{sy}.png``); PNG/TIFF (8/16-bit),
    ``.npy``, float TIFF or EXR; float frames far from camera units are rescaled (:func:`frame_scale`,
    recorded as the rig's ``frame_scale``); integer codes are decoded to light by ``encoding``
    (:func:`frames_encoding`: ``auto`` reads the files' sRGB / ICC / gAMA tags, and untagged files' fringes,
    :func:`untagged_encoding`; recorded as the rig's
    ``frame_encoding``). ``bayer``: the frames were demosaiced from a Bayer sensor of that layout (by
    ``demosaic``, :data:`IMPORT_DEMOSAIC`), recorded as each view's ``camera_isp``: silhouette pixels that only
    demosaicing lit are dropped (``psp.demosaic_bleed``), and with a known method the view calibration compares
    relit fringes through it (``isp.through_camera``); ``"auto"`` (default): each view's layout as its noise
    shows it (:func:`isp.detect_bayer_layout`, the reason in the view's ``bayer_detected``), else none;
    ``None`` or ``"none"``: none. A reference that is not a named pattern needs its projected
    image as ``pattern__<name>.png``. ``angles``: each view's turntable angle (degrees, view order), recorded as a
    capture records it (`sss geometry` merges the views with them). A view where nothing decodes is refused; a failed import leaves
    nothing behind; an interrupted one (Ctrl-C, SIGTERM) keeps its complete views, and the same import run again
    continues from them (after a SIGKILL too: the view it was in is redone).
    """
    from sssphase_core.processing.patterns import (
        REFERENCE_NAMES,
        CapturePlan,
        _reference_params,
        capture_plan,
    )

    if not PATCH_RANGE[0] <= patch <= PATCH_RANGE[1]:
        raise InputError(f"--patch (the footprint crop size K) must be {PATCH_RANGE[0]} to {PATCH_RANGE[1]} px, got {patch}")
    if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:  # NaN fails too
        raise InputError(f"--gamma (the projector's gamma) must be a number in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}] "
                         f"(as a rig file's), got {gamma}")
    camera_isp = None
    demosaic = str(demosaic).lower()
    if demosaic not in IMPORT_DEMOSAIC:
        raise InputError(f"--demosaic must be one of {', '.join(IMPORT_DEMOSAIC)}, got {demosaic!r}")
    auto_bayer = bayer is not None and bayer.lower() == "auto"
    if (bayer is None or bayer.lower() == "none") and demosaic != "other":  # it was ignored without a word
        raise InputError(f"--demosaic {demosaic} says how the camera demosaiced Bayer frames, and --bayer none says "
                         "there were none: name the layout with --bayer (or auto), or leave --demosaic out")
    if bayer is not None and bayer.lower() not in ("auto", "none"):
        from sssphase_core.processing.isp import check_layout

        camera_isp = {"bayer": check_layout(bayer.upper()), "demosaic": demosaic, "median": False}
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    w, h = (int(v) for v in projector_size)
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise InputError(f"projector size must be positive and at most 16384, got {w}x{h}")
    view_dirs = sorted((p for p in folder.glob("view_*") if p.is_dir()),  # view_2 before view_10
                       key=lambda p: (int(p.name[5:]) if p.name[5:].isdigit() else float("inf"), p.name)) or [folder]
    odd = [p.name for p in view_dirs if p != folder and not p.name[5:].isdigit()]
    near = sorted(p.name for p in folder.iterdir() if p.is_dir() and re.fullmatch(r"(?i)view[\W_]*\d+", p.name)
                  and not re.fullmatch(r"view_\d+", p.name))  # View_001, view-001, 'view 001': left out in silence
    if odd or near:  # (a view_x was imported as the next view, renumbered in silence)
        raise InputError(f"{folder / (odd or near)[0]} is no view folder: name view folders view_NNN (NNN a number), "
                         "or move it out")
    if view_dirs != [folder]:  # another folder that holds frames beside the views was left out in silence
        stray = sorted(p.name for p in folder.iterdir() if p.is_dir() and p not in view_dirs
                       and frame_files(p, strict=False))
        if stray:
            raise InputError(f"{folder / stray[0]} holds frames but is no view folder: name it view_NNN, or move it out")
    if view_dirs != [folder] and frame_files(folder, strict=False):  # one view's frames left out (said first)
        raise InputError(f"{folder} holds frames beside its view_NNN folders: move them into a view folder of their "
                         "own (e.g. view_000) or import them separately")
    numbers = [int(p.name[5:]) for p in view_dirs if p != folder]
    if numbers and numbers != list(range(len(numbers))):  # sessions number views 0..N-1
        as_views = "view 0" if len(numbers) == 1 else f"views 0 to {len(numbers) - 1} in that order"
        warnings.warn(f"{folder}: view folder{'s' if len(numbers) > 1 else ''} {', '.join(p.name for p in view_dirs)} "
                      f"{'are' if len(numbers) > 1 else 'is'} imported as {as_views}", stacklevel=2)
    angles = check_angles(angles, len(view_dirs))
    # the unwrapping frames are kept: the session is then whole without the folder (`sss export` of it imports again)
    req = CaptureRequest(check_object_name(name), views=len(view_dirs), out=Path(root), keep_unwrap=True)
    views = [(vdir, frame_files(vdir)) for vdir in view_dirs]  # refuse bad names before writing anything
    grids: list[tuple[int, int]] = []  # each view's dot grid (spacing, stride)
    for (vdir, files) in views:
        if not files:
            raise InputError(f"{vdir} holds no frame files (psp__x__p<period>__s<n>, white, black ...: see SESSION_FORMAT.md)")
        missing = [k for k in ("white", "black") if k not in files]
        if missing:
            raise InputError(f"{vdir}: needs white, black and psp__x__p<period>__s<n> frames (missing: {', '.join(missing)})"
                             + ("; a render without the projector's black light has an all-zero black frame"
                                if missing == ["black"] else ""))
        grids.append(check_dot_frames(vdir, files, planned_dot_spacing(vdir if (vdir / "plan.json").is_file()
                                                                       else folder)))
        for key in (k for k in files if k.startswith("ref/")):
            ref = key.removeprefix("ref/")
            if ref not in REFERENCE_NAMES and f"pattern/{ref}" not in files:
                raise InputError(f"{files[key]}: reference {ref!r} is no named pattern ({', '.join(REFERENCE_NAMES)}), so "
                                 f"the image projected for it is needed as pattern__{ref}.png to relight and evaluate it")
    configs = [psp_config_from_names(vdir, files) for vdir, files in views]
    for (vdir, _), config in zip(views[1:], configs[1:], strict=True):  # (a view short of a whole period imported)
        if config != configs[0]:
            said = [f"periods {', '.join(f'{p:g}' for p in sorted((c.period, *c.unwrap_periods)))} with {c.n_shifts} shifts"
                    for c in (config, configs[0])]
            raise InputError(f"{vdir}: its PSP frames have {said[0]}, but {views[0][0]} has {said[1]}: the views of "
                             "an import share one plan (a view lacks frames the others have, or holds extra ones)")
    for (vdir, _), config in zip(views, configs, strict=True):
        if not config.unwrap_periods and config.period < max(w, h):  # (it decoded nothing, "is --projector right?")
            raise InputError(f"{vdir}: PSP frames of one period ({config.period:g} px) and none of a longer period to "
                             f"unwrap them, which a {w}x{h} projector needs (an `sss export` of a session captured "
                             "without --keep-unwrap holds only the 8 decoded-from frames: it does not import again)")
    for (vdir, _), config in zip(views, configs, strict=True):
        check_plan_file(vdir if (vdir / "plan.json").is_file() else folder, (w, h), gamma, config)
    for vdir, files in views:
        check_view_memory(vdir, files)
    encoding, encoding_tag = frames_encoding((p for _, files in views for k, p in files.items()
                                              if not k.startswith("pattern/")), encoding)
    if encoding_tag == "no colour tag":  # asked auto, and no file says: the fringes tell sRGB codes from light
        encoding, encoding_tag = untagged_encoding(views[0][1]) or (encoding, encoding_tag)
    levels = white_levels((files["white"] for _, files in views), encoding, (files.get("black") for _, files in views))
    if max(levels) > VIEW_LEVEL_RATIO * min(levels):
        hi, lo = int(np.argmax(levels)), int(np.argmin(levels))
        raise InputError(f"{views[hi][1]['white']} is {max(levels) / min(levels):.3g}x as bright as {views[lo][1]['white']} "
                         "(99.9th percentiles): an import's views share one exposure and units (the frames are scaled "
                         "together)")
    scale = frame_scale([files["white"] for _, files in views], levels)
    raw = check_one_camera(views, encoding, bayer, demosaic)  # grey raw Bayer samples: demosaiced here
    if raw is not None:
        demosaic, camera_isp = raw[1], {"bayer": raw[0], "demosaic": raw[1], "median": False}
    depth = code_depth(views[0][1]["white"])
    top_code = scale  # an integer file's top code in camera units: 1, or a camera word's top with --bit-depth
    if bit_depth is not None:
        scale, top_code = codes_scale(bit_depth, depth, encoding), 1.0
    elif depth == 16:
        _warn_low_codes(views[0][1]["white"], max(levels))
    path = Path(root) / name
    frames: list[dict[str, Any]] = []
    given = {k for _, files in views for k in files if k.startswith("pattern/")}  # the projected images the user gives
    for key in sorted({k for _, files in views for k in files if k.startswith("ref/")}):
        ref = key.removeprefix("ref/")
        named = ref in REFERENCE_NAMES and f"pattern/{ref}" not in given  # a given image wins over our pattern of that name
        k, kind, params = _reference_params(ref, w, h) if named else (key, "image", {"file": ref})
        frames.append({"name": key, "key": key, "kind": kind, "params": {"width": w, "height": h, **params},
                       "exposure": 1.0})
    psp_frames = json.loads(capture_plan(w, h, psp=configs[0], gamma=gamma).to_json())["frames"]  # as a capture lists them
    plan_json = {"projector": [w, h], "gamma": float(gamma), "psp": asdict(configs[0]), "frames": psp_frames + frames}
    settings = {"n_views": len(view_dirs), "imported_from": str(folder.resolve()),
                "rig": {"camera": "import", "projector_size": [w, h], "patch": patch, "imported": True,
                        "frame_scale": scale, "frame_encoding": encoding, "frame_encoding_from": encoding_tag,
                        **({"frame_bit_depth": bit_depth} if bit_depth is not None else {}),
                        # integer files hold codes 0 .. top: what a camera model's images are clipped to (relighting)
                        # (raw samples demosaiced here keep the filters' overshoot, as the frames stored do)
                        **({"frame_codes_range": [0.0, top_code]} if depth is not None and raw is None else {})},
                "plan": plan_json, "import_options": {"bayer": str(bayer).lower(), "demosaic": demosaic,
                                                      **({"angles": angles} if angles else {})},
                "imported_frames": [frames_fingerprint(files) for _, files in views]}  # frames replaced: not resumed
    resume = path.exists() and _continues_unfinished_import(path, folder, settings)
    session = Session.create(root, name, resume=resume, **settings, software={"sssphase": __version__})
    done = set(session.views())
    if done:
        warnings.warn(f"{path}: continuing the unfinished import of {folder}: view{'s' if len(done) > 1 else ''} "
                      f"{', '.join(map(str, sorted(done)))} already imported {'are' if len(done) > 1 else 'is'} kept",
                      UserWarning, stacklevel=2)
    try:
        for view, ((vdir, files), config, level) in enumerate(zip(views, configs, levels, strict=True)):
            if view in done:
                continue
            spacing, stride = max(1, grids[view][0]), grids[view][1]
            plan = CapturePlan(w, h, config, (), gamma)
            writer = session.begin_view(view)
            try:  # (a sparse grid's crops are kept per pixel, as its capture keeps them: no light transport)
                proc = ViewProcessor(writer, plan, spacing, patch, RigSpec(camera="import", turntable=None),
                                     replace(req, dot_stride=stride), 0, camera_isp)
                proc.sources = {k: str(p) for k, p in files.items()}
                loader, top, fringe_values = FrameLoader(encoding, scale, raw=raw, bit_depth=bit_depth), 0, 0
                set_sums: dict[str, np.ndarray] = {}  # each fringe set's sum: its mean is half the white's light
                pair_sums: dict[str, list[np.ndarray]] = {}  # opposite shifts' sums per set (even N): all equal
                dot_sum, n_dots = None, 0  # the dot frames' sum: a full grid holds the white's light
                detected = None
                placement = None  # where each dot frame's light falls (once the view has decoded)
                for key in sorted((k for k in files if not k.startswith("pattern/")), key=_import_order):
                    if auto_bayer and detected is None and key.startswith("dots/"):  # before the decode the dots start
                        detected = _detect_bayer(proc, config, demosaic)
                    image = loader.read(files[key])
                    if key.startswith("psp/") and stores_integers(files[key]):  # the top code reads top_code
                        top += int(np.count_nonzero(image >= 0.999 * top_code))
                        fringe_values += image.size
                    if key == "black":
                        check_black_below_white(files[key], image, level * scale, scale)
                    check_not_negative(files[key], image, level * scale, scale)
                    if key.startswith("psp/"):  # (after the size checks: sets are summed)
                        _check_fringe_level(files[key], image, level * scale)
                        set_key = key.rsplit("/", 1)[0]
                        set_sums[set_key] = set_sums.get(set_key, 0) + image
                        if config.n_shifts % 2 == 0:
                            half, shift = config.n_shifts // 2, int(key.rsplit("/s", 1)[1])
                            sums = pair_sums.setdefault(set_key, [np.zeros(image.shape, np.float64) for _ in range(half)])
                            sums[shift % half] += image
                    elif key.startswith("dots/"):
                        dot_sum = image.astype(np.float64) if dot_sum is None else dot_sum + image
                        n_dots += 1
                    proc.add(_ImportedFrame(key, image), {"name": key, "key": key, "exposure": 1.0})
                    if key.startswith("dots/"):  # (the first dot frame decoded the view)
                        if placement is None:
                            corr = proc.decode()
                            placement = DotPlacement(corr.xp, corr.yp, corr.mask, projector_light(
                                proc.images["white"], proc.images["black"])[0], spacing)
                        sx, sy = (int(v) for v in key.removeprefix("dots/").split("_"))
                        placement.check(files[key], sx, sy, image - proc.images["black"])
                for key in (k for k in files if k.startswith("pattern/")):
                    proc.patterns[f"ref/{key.removeprefix('pattern/')}"] = read_pattern(
                        files[key], (w, h), hint="the image projected for a reference is the projector's size (--projector)")
                for set_key, total in set_sums.items():
                    _check_fringe_level(vdir / set_key.replace("/", "__"), total / config.n_shifts, level * scale, mean=True)
                if auto_bayer and detected is None:
                    detected = _detect_bayer(proc, config, demosaic)
                elif camera_isp and raw is None:  # a layout named: the frames' noise may say another
                    _check_named_layout(vdir, proc, config, camera_isp["bayer"])
                found_demosaic = _detect_demosaic(proc, config) if demosaic == "other" else None
                try:
                    info = {**proc.finish(), "nonfinite_repaired": loader.repaired}
                except InputError as exc:  # (the decoder's "4 PSP frames missing, e.g. ..." named no view)
                    raise InputError(f"{vdir}: {exc}" if str(vdir) not in str(exc) else str(exc)) from None
                if loader.repaired:  # `sss decode` refuses them: say what the import did instead
                    warnings.warn(f"{vdir}: {loader.repaired} NaN or infinite values (a renderer's stray samples?) were "
                                  "repaired from their neighbours (recorded as the view's nonfinite_repaired)",
                                  UserWarning, stacklevel=2)
                if auto_bayer:
                    info["bayer_detected"] = detected
                if found_demosaic is not None:
                    info["demosaic_detected"] = found_demosaic
                if raw is not None:
                    info["raw_bayer"] = f"{raw[0]}: demosaiced by {raw[1]}"
                try:
                    check_opposite_shifts(vdir, pair_sums, proc.images["white"], proc.images["black"])
                except InputError as exc:  # (linear frames a tool tagged gAMA or sRGB were blamed on a missing frame)
                    if encoding == "linear":
                        raise
                    raise InputError(f"{exc}; or the files hold linear light but were decoded as {encoding} "
                                     f"({encoding_tag}): then import with --encoding linear") from None
                if dot_sum is not None:
                    info["dots_light_share"] = round(check_dots_light(vdir, dot_sum * stride ** 2, n_dots * stride ** 2,
                                                                      proc.images["white"], proc.images["black"]), 4)
                    if stride > 1:
                        info["dot_stride"] = stride
                if not info["coverage"].get("VALID"):
                    raise InputError(nothing_decoded(vdir, info["coverage"], top / max(1, fringe_values), config.period,
                                                     level * scale))
                check_distinct_orientations(vdir, _input_sets(proc, config))  # (fringes decoded: they are not flat)
                check_white_above_black(vdir, proc.images["white"], proc.images["black"], level * scale)
                share = fringe_mean_share(_input_sets(proc, config), proc.images["white"], proc.images["black"],
                                          proc.corr.mask)
                if share < FRINGE_MEAN_SHARE - 0.4:  # fringes hardly above (or below) black: the black frame is wrong
                    raise InputError(f"{files['black']}: the fringe frames average {share:.2f} of the white's light above "
                                     "this black frame, where they give 0.50: it is brighter than the scene under the "
                                     "projector's black (the wrong file, or light left on)")
                check_fringe_exposure(vdir, proc, config, share)
                _warn_suspect_view(vdir, info["coverage"], (w, h), top / max(1, fringe_values),
                                   proc.images["white"], proc.corr.mask, top_code if stores_integers(files["white"]) else None,
                                   share, gamma, encoding)
                _warn_dim_view(vdir, proc.images["white"], np.asarray(proc.corr.reason), config.period)
                warn_swapped_axes(vdir, np.asarray(proc.corr.xp), np.asarray(proc.corr.yp), np.asarray(proc.corr.mask))
                info["fringe_mean_share"] = round(share, 4) if np.isfinite(share) else None
                bright: dict[str, float] = {}
                match = reference_match(proc, frames, gamma, bright)
                info["reference_match"] = {k: round(v, 3) for k, v in match.items()}
                info["reference_brightness"] = {k: round(v, 3) for k, v in bright.items()}
                off = {ref: b for ref, b in bright.items() if not REFERENCE_BRIGHTNESS[0] <= b <= REFERENCE_BRIGHTNESS[1]}
                repaired = {ref: proc.repaired[f"ref/{ref}"] for ref in bright if f"ref/{ref}" in proc.repaired}
                if repaired:
                    info["reference_repaired"] = repaired
                heavy = {ref: n for ref, n in repaired.items() if n > REFERENCE_REPAIR_WARN * max(proc.lit_values, 1)}
                said = {ref: f"{ref} ({b:.2f}x" + (f", {heavy[ref]:,} values clipped" if ref in heavy else "") + ")"
                        for ref, b in off.items()}
                if off:  # relit against it, every model scored 12-13 dB
                    warnings.warn(f"{vdir}: the reference capture{'s' if len(off) > 1 else ''} "
                                  f"{', '.join(said.values())} hold{'' if len(off) > 1 else 's'} "
                                  "another amount of light than the white capture and the pattern give at the decoded "
                                  "points (1.00x): another exposure, gain or units than the white and the fringes?",
                                  UserWarning, stacklevel=2)
                if stray := {ref: n for ref, n in heavy.items() if ref not in off}:
                    warnings.warn(f"{vdir}: the reference capture{'s' if len(stray) > 1 else ''} "
                                  f"{', '.join(f'{ref} ({n:,} values, {n / max(proc.lit_values, 1):.1%} of the lit ones)' for ref, n in stray.items())} "
                                  "held light brighter than full white could make it, replaced by the neighbours' median "
                                  "(relighting is scored against the repaired image): light the projector did not give "
                                  "(room light, a reflection) or another exposure in part of the frame?",
                                  UserWarning, stacklevel=2)
                astray = {ref: r for ref, r in match.items() if r < REFERENCE_MATCH_WARN}
                if astray:
                    warnings.warn(f"{vdir}: the reference capture{'s' if len(astray) > 1 else ''} "
                                  f"{', '.join(f'{ref} (correlation {r:.2f})' for ref, r in astray.items())} do"
                                  f"{'' if len(astray) > 1 else 'es'} not follow the pattern at the decoded points: is "
                                  f"--projector right ({w}x{h})? the patterns are made at that size (else the decoded "
                                  "points are wrong: see the fringes' conventions in `sss patterns`)", UserWarning,
                                  stacklevel=2)
            except BaseException:
                writer.abort()
                session.set_view(view, {"status": "interrupted"})
                raise
            writer.commit({"source": str(vdir), **info, **({"angle": angles[view]} if angles else {})})
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the complete views stay, and the same import continues from them
        if not session.views():
            _remove(session.path)
        raise
    except BaseException:
        _remove(session.path)  # a failed import leaves nothing behind, and nothing half-imported blocks the name
        raise
    return session


def frames_fingerprint(files: dict[str, Path]) -> str:
    """A short digest of one view's frame files (key, size, modification time): an unfinished import whose frames
    were replaced or edited since is made again, not continued with views decoded from the old frames."""
    import hashlib

    digest = hashlib.sha256()
    for key in sorted(files):
        stat = files[key].stat()
        digest.update(f"{key}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]


def parse_angles(text: str) -> list[float]:
    """``--angles`` ("0,90,180,270": degrees) -> the numbers; one line naming what does not read."""
    try:
        return [float(part) for part in text.split(",")]
    except ValueError:
        raise InputError(f"--angles must be the views' turntable angles in degrees, comma-separated (0,90,180,270), "
                         f"got {text[:60]!r}") from None


def check_angles(angles: Sequence[float] | None, n_views: int) -> list[float] | None:
    """``angles`` as floats when there is one finite angle per view, else refused in one line."""
    if angles is None:
        return None
    angles = [float(a) for a in angles]
    if len(angles) != n_views:
        raise InputError(f"--angles gives {len(angles)} angle{'s' if len(angles) != 1 else ''} for {n_views} "
                         f"view{'s' if n_views != 1 else ''}: give one per view, in view order")
    if not all(np.isfinite(a) and abs(a) <= 36000 for a in angles):
        raise InputError(f"--angles must be finite numbers of degrees, got {', '.join(f'{a:g}' for a in angles)}")
    return angles


def _continues_unfinished_import(path: Path, folder: Path, settings: dict[str, Any]) -> bool:
    """Whether an import into the existing session ``path`` continues it: an unfinished import of the same ``folder``
    (interrupted, or killed mid-view) made with the same ``settings`` (the manifest entries an import writes: views,
    rig, plan and options, so its views and the new ones are alike) keeps its complete views. Made otherwise, or with
    no complete view, it is removed with a warning (its frames are still in ``folder``: nothing is lost); anything
    else at ``path`` is refused."""
    try:
        old = Session.open(path)
        unfinished = old.imported and len(old.views()) < int(old.manifest.get("n_views", 0))
        same = str(old.manifest.get("imported_from")) == settings["imported_from"]
    except Exception:  # not a session, or a damaged one: nothing to decide from; refused below
        unfinished = same = False
    if not (unfinished and same):
        raise InputError(f"{path} already exists: import into another --out or choose another --object")
    if not old.views():
        why = "none of its views was complete"
    elif all(old.manifest.get(k) == json.loads(json.dumps(v)) for k, v in settings.items()):
        return True
    else:
        why = "it was made with other settings (options, frames or units)"
    warnings.warn(f"{path}: an unfinished import of {folder} is replaced: {why}", UserWarning, stacklevel=3)
    _remove(path)
    return False


def _remove(path: Path, tries: int = 20) -> None:
    """Remove a session folder; a chunk a writer's thread was still flushing may land after the first pass (seen on a
    full disk), so it is tried again for up to a second."""
    import time

    for _ in range(tries):
        shutil.rmtree(path, ignore_errors=True)
        if not path.exists():
            return
        time.sleep(0.05)
