"""Session store: one folder per object, a JSON manifest and chunked, compressed zarr v3 arrays.

Layout (see SESSION_FORMAT.md)::

    <root>/<object>/manifest.json       rig, devices, plugin versions, plan, timestamps, views
    <root>/<object>/view_000/<name>/    one zarr array per name: psp, white, black, corr/xp, ...

Every write is atomic: a view's arrays are written into ``.view_NNN.partial`` and renamed into
place once complete, then the manifest (with each array's SHA-256) is replaced atomically. An
interrupted capture therefore leaves only complete views plus a partial folder that ``resume``
discards. ``FAULT_HOOK`` (tests) is called before every array write, e.g. to inject ENOSPC.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import re
import shutil
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import DataError, InputError
from sssphase_core.store.imageio import MAX_FRAME_PIXELS
from sssphase_core.store.light import holds_light, light_problem, white_level

FORMAT = "sssphase-session"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
ARRAY_RE = re.compile(r"^[a-z][a-z0-9_]*(/[A-Za-z0-9][A-Za-z0-9_.-]*){0,2}$")
REQUIRED = ("psp", "white", "black", "corr/xp", "corr/yp", "corr/mask", "corr/reason")
#: The states a view passes through in a manifest (``complete``: every array written and checked).
VIEW_STATES = ("pending", "capturing", "interrupted", "complete")
FAULT_HOOK: Callable[[str], None] | None = None


def check_object_name(name: str) -> str:
    """Refuse names that could escape the session root (``../``, separators, absolute paths)."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name) or name in (".", ".."):  # fullmatch: "$" allows "\n"
        shown = repr(name) if not isinstance(name, str) or len(name) <= 80 else repr(name[:80]) + f"... ({len(name)} characters)"
        raise InputError(f"object name {shown} is not allowed: use ASCII letters (a-z, A-Z), digits, '_', '-', '.', "
                         "starting with a letter or digit (no path separators, no '..', at most 64 characters)")
    return name


MAX_VIEWS = 10_000


def manifest_problem(manifest: dict[str, Any]) -> str | None:
    """What makes a manifest unusable (wrong types, array names that leave the view folder), or None."""
    n = manifest.get("n_views", 0)
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= MAX_VIEWS:
        return f"n_views must be an integer in [0, {MAX_VIEWS}], got {n!r}"
    views = manifest.get("views")
    if not isinstance(views, dict):
        return "it has no views table"
    for key, entry in views.items():
        if not (isinstance(key, str) and key.isdigit() and int(key) < MAX_VIEWS) or not isinstance(entry, dict):
            return f"view {key!r} is not a view number with an entry"
        arrays = entry.get("arrays", {})
        if not isinstance(arrays, dict):
            return f"view {key}: arrays is not a table"
        for name, meta in arrays.items():
            if not isinstance(name, str) or not ARRAY_RE.fullmatch(name):
                return f"view {key}: array name {name!r} is not allowed"
            if not (isinstance(meta, dict) and isinstance(meta.get("shape"), list)
                    and all(isinstance(d, int) and d >= 0 for d in meta["shape"])
                    and isinstance(meta.get("dtype"), str) and isinstance(meta.get("checksum"), str)
                    and isinstance(meta.get("chunks", 0), int)):
                return f"view {key}: array {name} lacks its shape, dtype or checksum"
        problem = camera_isp_problem(entry.get("camera_isp"))
        if problem:
            return f"view {key}: {problem}"
    problem = plan_problem(manifest.get("plan", {})) or rig_problem(manifest.get("rig", {}))
    if problem:
        return problem
    try:  # the object names output files and folders: it must not lead out of them
        check_object_name(manifest.get("object"))  # type: ignore[arg-type]
    except InputError as e:
        return str(e)
    return None


def view_dir_name(view: int) -> str:
    return f"view_{view:03d}"


def array_checksum(arr: np.ndarray) -> str:
    """SHA-256 of the array's bytes in C order (an empty array hashes no bytes)."""
    data = np.ascontiguousarray(arr)
    return "sha256:" + hashlib.sha256(memoryview(data).cast("B") if data.size else b"").hexdigest()


def _chunks(shape: tuple[int, ...], itemsize: int, target: int = 2**21) -> tuple[int, ...]:
    """Chunks of about ``target`` bytes: trailing dims whole, split the leading ones (1 image, N rows)."""
    chunks = list(shape)
    for i, n in enumerate(shape):
        rest = int(np.prod(shape[i + 1:], dtype=np.int64)) * itemsize
        chunks[i] = int(min(n, max(1, target // max(rest, 1))))
        if chunks[i] > 1 or rest <= target:
            break
    return tuple(max(1, c) for c in chunks)


#: The largest turntable angle a session may record, in degrees (ten turns either way: the daemon's own bound).
MAX_ANGLE = 3600.0


def angle_problem(angle: object) -> str | None:
    """What is wrong with a view's recorded turntable ``angle`` (degrees), or None."""
    if isinstance(angle, bool) or not isinstance(angle, int | float) or not math.isfinite(angle):
        return f"{str(angle)[:40]!r} is not a number of degrees"
    if abs(angle) > MAX_ANGLE:
        return f"{angle:g} is beyond {MAX_ANGLE:g} degrees (ten turns): not a turntable's"
    return None


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write ``obj`` as JSON to ``path`` atomically; on failure (disk full, read-only folder) the old file
    stays, no temporary file is left, and the error names the file."""
    from sssphase_core.store.files import atomic_path

    existed = path.exists()
    try:
        with atomic_path(path) as tmp, open(tmp, "w") as f:
            json.dump(obj, f, indent=1, sort_keys=True)  # (atomic_path syncs it before the rename)
    except OSError as exc:
        kept = " (the previous version is kept)" if existed else ""
        raise DataError(f"cannot write {path}: {exc.strerror or exc}{kept}") from None


def _codec(dtype: np.dtype) -> list:
    """Blosc with byte shuffle, then a CRC32C per chunk: every read verifies what it reads, so a damaged
    chunk is an error naming the array, not silently wrong training data (the SHA-256 of ``sss
    validate`` reads whole arrays). LZ4 for float32 images (noisy floats barely compress: speed matters
    most); zstd for float16 arrays, the footprint stores, whose noise floor is zeroed (9% of float32 vs
    17% with LZ4 on the soap's transport, ``sss bench store``)."""
    from zarr.codecs import BloscCodec, BloscShuffle, Crc32cCodec

    shuffle = BloscShuffle.shuffle if np.dtype(dtype).itemsize > 1 else BloscShuffle.noshuffle
    cname = "zstd" if np.dtype(dtype) == np.float16 else "lz4"
    return [BloscCodec(cname=cname, clevel=5 if cname == "lz4" else 3, shuffle=shuffle), Crc32cCodec()]


def _chunk_count(shape: tuple[int, ...], chunks: tuple[int, ...]) -> int:
    return int(np.prod([-(-n // c) for n, c in zip(shape, chunks, strict=True)])) if all(shape) else 0


#: The codecs of a session array, in order: sssphase writes ``bytes``, ``blosc`` and ``crc32c`` (earlier versions
#: without the checksum). Others (a gzip stream unpacking a 3 MB chunk to gigabytes) are not read.
ARRAY_CODECS = ("bytes", "blosc", "crc32c")

#: The largest chunk sssphase writes is a few frames of a 1080p view (tens of MB); a chunk declared larger
#: than this is refused before it is allocated.
MAX_CHUNK_BYTES = 1 << 30


def _check_array_metadata(folder: Path, where: str) -> int:
    """Refuse an array's ``zarr.json`` that is no regular file of at most 1 MiB (a link to /dev/zero was read
    without end, a FIFO hung), that names codecs sssphase does not write, or chunks over :data:`MAX_CHUNK_BYTES`;
    the chunks' size in bytes."""
    from sssphase_core.store.files import read_json_input

    try:
        meta = read_json_input(folder / "zarr.json", "its metadata", 1 << 20)
    except FileNotFoundError:
        raise DamagedArray(where, "missing or unreadable (no zarr.json)") from None
    except InputError as exc:
        said = str(exc).replace(str(folder / "zarr.json"), "zarr.json")  # (its folder is in ``where``)
        raise DamagedArray(where, f"missing or unreadable ({said.strip()[:160]})") from None
    try:
        codecs = [c["name"] if isinstance(c, dict) else c for c in meta["codecs"]]
        chunk = [int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"]]
        itemsize = np.dtype(str(meta["data_type"])).itemsize
    except (KeyError, TypeError, ValueError):
        raise DamagedArray(where, "missing or unreadable (its zarr.json is not a zarr v3 array's)") from None
    if not codecs or codecs[0] != "bytes" or any(c not in ARRAY_CODECS for c in codecs) or len(set(codecs)) != len(codecs):
        raise DamagedArray(where, f"damaged (its codecs are {', '.join(map(str, codecs))[:120]}; sssphase writes "
                                  f"{', '.join(ARRAY_CODECS)})")
    nbytes = float(np.prod(chunk, dtype=np.float64)) * itemsize
    if any(n <= 0 for n in chunk) or nbytes > MAX_CHUNK_BYTES:
        raise DamagedArray(where, f"damaged (chunks of {'x'.join(map(str, chunk))} {meta['data_type']}: "
                                  f"{nbytes / 2**20:,.0f} MiB each, more than the {MAX_CHUNK_BYTES >> 20} MiB sssphase writes)")
    return int(nbytes)


def _checked_chunk_files(folder: Path, where: str, chunk_bytes: int) -> int:
    """How many chunk files (:func:`_chunk_files`) an array folder holds, each checked: one longer than its chunk
    could compress to (a 10 GB sparse file was read whole), or that is no regular file (a link to /dev/zero), is
    refused; a broken link is not counted (a missing chunk)."""
    import stat

    limit = chunk_bytes + (chunk_bytes >> 6) + (1 << 16)  # blosc's worst case: 16 bytes a block over the data
    found = 0
    for p in _chunk_files(folder):
        try:
            st = os.stat(p)
        except OSError:
            continue  # (a broken link)
        if not stat.S_ISREG(st.st_mode) or st.st_size > limit:
            what = "not a regular file" if not stat.S_ISREG(st.st_mode) else f"{st.st_size:,} bytes for a chunk of {chunk_bytes:,}"
            raise DamagedArray(where, f"damaged (chunk {p.relative_to(folder)} is {what})")
        found += 1
    return found


def _chunk_files(folder: Path) -> list[Path]:
    """An array folder's chunk files (links and other non-folders included, for :func:`_check_chunk_files`):
    zarr's ``c/<i>/<j>/...`` keys only, so that a file that something else left there (``.DS_Store``,
    ``notes.txt``) is not counted as a chunk."""
    root = folder / "c"
    if not root.is_dir():
        return [root] if root.exists() or root.is_symlink() else []  # a 0-d array's one chunk
    return [p for p in root.rglob("*") if not p.is_dir() and all(part.isdigit() for part in p.relative_to(root).parts)]


def _zarr_write(path: Path, data: np.ndarray) -> None:
    import zarr

    data = np.ascontiguousarray(data)
    arr = zarr.create_array(store=str(path), shape=data.shape, dtype=data.dtype, chunks=_chunks(data.shape, data.dtype.itemsize),
                            compressors=_codec(data.dtype), fill_value=0, zarr_format=3, overwrite=True,
                            config={"write_empty_chunks": True})  # every chunk on disk: a missing one is damage
    if data.size:
        arr[...] = data


class ViewWriter:
    """Writes one view's arrays into a partial folder; ``commit`` renames it into place atomically."""

    def __init__(self, session: Session, view: int) -> None:
        self.session, self.view = session, view
        self.final = session.path / view_dir_name(view)
        self.partial = session.path / f".{view_dir_name(view)}.partial"
        shutil.rmtree(self.partial, ignore_errors=True)
        self.partial.mkdir(parents=True)
        self.arrays: dict[str, dict[str, Any]] = {}

    def write(self, name: str, data: np.ndarray) -> None:
        if not ARRAY_RE.fullmatch(name):
            raise InputError(f"bad array name {name!r}")
        try:
            if FAULT_HOOK is not None:
                FAULT_HOOK(name)
            _zarr_write(self.partial / name, data)
        except OSError as exc:
            self.abort()
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise DataError(f"disk full while writing {name} of view {self.view} in {self.session.path}: "
                                f"free some space and {self.session.rerun}") from exc
            if exc.errno == errno.EFBIG:  # (a file-size limit: `ulimit -f`, or a file system's largest file)
                raise DataError(f"a file of {name} of view {self.view} in {self.session.path} outgrew the largest file "
                                f"this process may write (ulimit -f): raise the limit and {self.session.rerun}") from exc
            raise DataError(f"cannot write {name} of view {self.view} in {self.session.path}: "
                            f"{exc.strerror or exc} ({self.session.rerun})") from exc
        self.arrays[name] = {"shape": list(data.shape), "dtype": np.dtype(data.dtype).str, "checksum": array_checksum(data),
                             "chunks": _chunk_count(data.shape, _chunks(data.shape, np.dtype(data.dtype).itemsize))}

    def stream_array(self, name: str, count: int) -> StreamedArray:
        """An array of ``count`` equal-shape frames written one at a time (raw dot grids)."""
        return StreamedArray(self, name, count)

    def growing_array(self, name: str, row_shape: tuple[int, ...], dtype: np.dtype,
                      chunk_bytes: int = 2**21) -> GrowingArray:
        """An array of rows appended in blocks, its length known only at the end (footprint crops)."""
        return GrowingArray(self, name, row_shape, dtype, chunk_bytes)

    def abort(self) -> None:
        shutil.rmtree(self.partial, ignore_errors=True)

    def commit(self, info: dict[str, Any] | None = None) -> None:
        """Rename the partial folder into place once its chunks are on the disk, then record the view
        as complete in the manifest (a power cut before the manifest leaves the view to redo)."""
        from sssphase_core.store.files import sync, sync_tree

        sync_tree(self.partial)
        shutil.rmtree(self.final, ignore_errors=True)
        os.replace(self.partial, self.final)
        sync(self.session.path)
        self.session.set_view(self.view, {"status": "complete", "arrays": self.arrays, "completed": time.time(),
                                          **(info or {})})


class StreamedArray:
    """``(count, *frame.shape)`` frames written one at a time (raw dot grids): a :class:`GrowingArray`
    of one frame per chunk, made at the first frame, that must end with exactly ``count`` frames."""

    def __init__(self, writer: ViewWriter, name: str, count: int) -> None:
        self.writer, self.name, self.count = writer, name, count
        self.frames: GrowingArray | None = None
        self.index = 0

    def append(self, frame: np.ndarray) -> None:
        frame = np.ascontiguousarray(frame)
        if self.frames is None:
            self.frames = GrowingArray(self.writer, self.name, frame.shape, frame.dtype, chunk_bytes=max(frame.nbytes, 1))
        self.frames.extend(frame[None])
        self.index += 1

    def close(self) -> None:
        if self.index != self.count or self.frames is None:
            raise DataError(f"{self.name}: got {self.index} of {self.count} frames")
        self.frames.close()


class GrowingArray:
    """``(N, *row_shape)`` zarr array of rows appended in blocks of any length, N not known in advance
    (footprint crops as dot frames arrive). Rows are held until a whole chunk is full, so each chunk is
    written once and memory stays at one chunk plus the block being added."""

    def __init__(self, writer: ViewWriter, name: str, row_shape: tuple[int, ...], dtype: np.dtype,
                 chunk_bytes: int = 2**21) -> None:
        import zarr

        if not ARRAY_RE.fullmatch(name):
            raise InputError(f"bad array name {name!r}")
        if FAULT_HOOK is not None:
            FAULT_HOOK(name)
        self.writer, self.name, self.dtype = writer, name, np.dtype(dtype)
        self.rows = _chunks((1 << 40, *row_shape), self.dtype.itemsize, chunk_bytes)[0]
        self.arr = zarr.create_array(store=str(writer.partial / name), shape=(0, *row_shape), dtype=self.dtype,
                                     chunks=(self.rows, *row_shape), fill_value=0, zarr_format=3,
                                     compressors=_codec(self.dtype), config={"write_empty_chunks": True})
        self.held: list[np.ndarray] = []
        self.n_held = 0
        self.hash = hashlib.sha256()

    def extend(self, rows: np.ndarray) -> None:
        """Append ``rows`` (n, *row_shape), cast to the array's dtype."""
        rows = np.ascontiguousarray(rows, self.dtype)
        if rows.shape[1:] != self.arr.shape[1:]:
            raise DataError(f"{self.name}: rows of shape {rows.shape[1:]}, expected {self.arr.shape[1:]}")
        self.held.append(rows)
        self.n_held += len(rows)
        if self.n_held >= self.rows:
            self._flush(whole_chunks=True)

    def _flush(self, whole_chunks: bool) -> None:
        if not self.n_held:
            return
        block = np.concatenate(self.held) if len(self.held) > 1 else self.held[0]
        n = len(block) - len(block) % self.rows if whole_chunks else len(block)
        start = self.arr.shape[0]
        self.arr.resize((start + n, *self.arr.shape[1:]))
        self.arr[start:start + n] = block[:n]
        self.hash.update(memoryview(np.ascontiguousarray(block[:n])).cast("B"))
        self.held = [block[n:]] if n < len(block) else []
        self.n_held = len(block) - n

    def close(self) -> None:
        self._flush(whole_chunks=False)
        shape = tuple(self.arr.shape)
        self.writer.arrays[self.name] = {"shape": list(shape), "dtype": self.dtype.str,
                                         "checksum": "sha256:" + self.hash.hexdigest(),
                                         "chunks": _chunk_count(shape, (self.rows, *shape[1:]))}


class DamagedArray(DataError):
    """A session array that cannot be read as its manifest says: ``detail`` says how ("missing or unreadable
    (...)", "damaged (...)"); ``checksum``: a chunk failed its CRC32C (or did not decode)."""

    def __init__(self, where: str, detail: str, *, checksum: bool = False) -> None:
        super().__init__(f"{where} is {detail}; `sss validate` lists the damage")
        self.detail, self.checksum = detail, checksum


def _whole(index: Any) -> bool:
    """Whether an index (``...``, ``:``, ``()``, or a tuple of those) selects a whole array."""
    parts = index if isinstance(index, tuple) else (index,)
    return all(p is Ellipsis or (isinstance(p, slice) and p == slice(None)) for p in parts)  # (an index array too)


class CheckedArray:
    """A read-only zarr array whose reads fail with a :class:`DataError` naming it when a chunk is damaged, and
    whose whole reads are held to the manifest's ``checksum`` too (data rewritten with valid chunks: another
    program's write, an array folder linked to another session's)."""

    def __init__(self, array: Any, where: str, checksum: str | None = None) -> None:
        self.array, self.where, self.checksum = array, where, checksum
        self.shape, self.dtype, self.ndim = array.shape, array.dtype, array.ndim

    def __len__(self) -> int:
        return int(self.shape[0])

    def __getitem__(self, index: Any) -> np.ndarray:
        data = self._checked(lambda: self.array[index])
        if self.checksum and _whole(index) and array_checksum(data) != self.checksum:
            raise DamagedArray(self.where, "corrupt (its data do not match the manifest's checksum: changed since "
                                           "they were written)")
        return data

    @property
    def oindex(self) -> Any:
        """Orthogonal indexing (rows by an index array), checked like ``[]``."""
        outer = self

        class _OIndex:
            def __getitem__(self, index: Any) -> np.ndarray:
                return outer._checked(lambda: outer.array.oindex[index])

        return _OIndex()

    def _checked(self, read: Any) -> np.ndarray:
        try:
            return read()
        except Exception as exc:  # zarr/numcodecs raise several types for a checksum or decoding failure
            reason = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
            if "checksum" in reason.lower():  # zarr's words end in both checksums as raw bytes
                reason = "a chunk's CRC32C checksum does not match its data"
            raise DamagedArray(self.where, f"damaged ({reason})", checksum=True) from None

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return np.asarray(self[...], dtype=dtype)


def clip_levels(frames: list[dict], saturation: float | None) -> tuple[float | None, float | None]:
    """Clipping levels (linear units) of a session's PSP and white images from the rig's level at exposure
    1: a frame developed at exposure e clips at saturation / e; HDR-merged frames clip only where the shortest
    exposure did."""
    if not saturation:
        return None, None

    def level(kind: str) -> float | None:
        exposures = [float(f.get("exposure", 1.0)) for f in frames if f.get("kind") == kind]
        return float(saturation) / min(exposures) if exposures else None

    return level("psp"), level("white")


def _number(value: Any, low: float = 0.0, high: float = float("inf")) -> bool:
    """Whether ``value`` is a finite real number (not a bool) in [low, high]."""
    import math

    return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and low <= value <= high)


#: The rig's numbers a manifest may leave null, with their ranges: what relighting and training read.
RIG_NUMBERS = {"projector_black": (0.0, 0.999), "black_level": (0.0, float("inf")), "saturation": (1e-6, float("inf")),
               "white_scale": (1e-12, float("inf")), "gamma": (0.05, 20.0)}


def camera_isp_problem(isp: Any) -> str | None:
    """What makes a view's ``camera_isp`` record (how a Bayer camera's frames were demosaiced) unusable, or None."""
    from sssphase_core.processing.isp import BAYER_LAYOUTS

    if isp is None:
        return None
    if not isinstance(isp, dict):
        return f"camera_isp must be a table or null, got {isp!r}"
    if "bayer" in isp and isp["bayer"] not in BAYER_LAYOUTS:
        return f"camera_isp.bayer must be one of {', '.join(BAYER_LAYOUTS)}, got {isp['bayer']!r}"
    if "demosaic" in isp and not isinstance(isp["demosaic"], str):
        return f"camera_isp.demosaic must be a name, got {isp['demosaic']!r}"
    if "median" in isp and not isinstance(isp["median"], bool):
        return f"camera_isp.median must be true or false, got {isp['median']!r}"
    return None


#: What a session without its ``rig`` record loses (validate's problem, relight's warning).
RIG_UNKNOWN = ("the camera, its saturation level and the footprint crop size it was captured with are unknown "
               "(relighting would assume an unclipped camera and 32-pixel crops)")


def rig_problem(rig: Any) -> str | None:
    """What makes a manifest's rig record unusable (a number of the wrong type or range, a footprint crop size
    beyond :data:`~sssphase_core.processing.footprints.PATCH_RANGE`, options that are not a table), or None."""
    from sssphase_core.processing.footprints import PATCH_RANGE

    if not isinstance(rig, dict):
        return f"rig must be a table, got {rig!r}"
    if not isinstance(rig.get("options", {}), dict):
        return f"rig.options must be a table, got {rig['options']!r}"
    for name, (low, high) in RIG_NUMBERS.items():
        if rig.get(name) is not None and not _number(rig[name], low, high):
            span = f"in [{low:g}, {high:g}]" if high < float("inf") else f"at least {low:g} (finite)"
            return f"rig.{name} must be null or a number {span}, got {rig[name]!r}"
    patch = rig.get("patch")
    if patch is not None and not (isinstance(patch, int) and not isinstance(patch, bool)
                                  and PATCH_RANGE[0] <= patch <= PATCH_RANGE[1]):
        return f"rig.patch (the footprint crop size) must be a whole number from {PATCH_RANGE[0]} to {PATCH_RANGE[1]}, got {patch!r}"
    for name in ("camera", "projector"):
        if rig.get(name) is not None and not isinstance(rig[name], str):
            return f"rig.{name} must be a device name, got {rig[name]!r}"
    if str(rig.get("camera", "")).startswith("sim:") and rig.get("options"):  # the sim rig relight and geometry rebuild
        from sssphase_core.sim import rig_from_options

        try:
            rig_from_options(rig["options"])
        except InputError as exc:
            return f"rig.options: {exc}"
    return camera_isp_problem({k: rig[k] for k in ("bayer", "median") if rig.get(k) is not None})


def plan_problem(plan: Any) -> str | None:
    """What makes a manifest's capture plan unusable (its projector size, gamma or frames of the wrong type
    or range: a manifest edited by hand or by another program), or None."""
    import math

    from sssphase_core.processing.patterns import MAX_PROJECTOR_PIXELS, MAX_SIDE

    if not isinstance(plan, dict):
        return "plan is not a table"
    if "projector" in plan:
        size = plan["projector"]
        if not (isinstance(size, list) and len(size) == 2
                and all(isinstance(d, int) and not isinstance(d, bool) and 1 <= d <= MAX_SIDE for d in size)):
            return f"plan.projector must be [width, height] in whole pixels, 1 to {MAX_SIDE}, got {size!r}"
        if size[0] * size[1] > MAX_PROJECTOR_PIXELS:  # every relit pattern is one (16384 x 16384: 4 GB a frame)
            return (f"plan.projector {size[0]}x{size[1]} is larger than any projector (at most "
                    f"{MAX_PROJECTOR_PIXELS >> 20} MP)")
    if "gamma" in plan:
        gamma = plan["gamma"]
        if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not (math.isfinite(gamma) and 0.05 <= gamma <= 20):
            return f"plan.gamma (the projector's gamma) must be a number in [0.05, 20], got {gamma!r}"
    frames = plan.get("frames", [])
    if not isinstance(frames, list) or not all(
            isinstance(f, dict) and isinstance(f.get("key"), str) and isinstance(f.get("kind"), str)
            and isinstance(f.get("params", {}), dict) for f in frames):
        return "plan.frames must be a list of frames, each with a key, a kind and params"
    from sssphase_core.processing.patterns import frame_params_problem

    size = plan.get("projector")
    for f in frames:  # what each frame's pattern is drawn from (a reference relit under it, a plan resumed)
        problem = frame_params_problem(f["kind"], f.get("params", {}))
        if problem:
            return f"plan frame {f['key']!r}: {problem}"
        exposure = f.get("exposure", 1.0)  # where the frame clips: relighting and training read it
        if isinstance(exposure, bool) or not isinstance(exposure, (int, float)) or not (math.isfinite(exposure) and exposure > 0):
            return f"plan frame {f['key']!r}: exposure must be a positive number, got {exposure!r}"
        params = f.get("params", {})
        if size is not None and [params.get("width"), params.get("height")] != size:  # every frame fills the projector
            return (f"plan frame {f['key']!r} is {params.get('width')}x{params.get('height')}, but the projector "
                    f"(plan.projector) is {size[0]}x{size[1]}")
    return None


@dataclass
class Session:
    """A session folder. ``Session.open(path)`` to read; ``Session.create(root, name, ...)`` to write."""

    path: Path
    manifest: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def _holds_no_view(path: Path) -> bool:
        """Whether the session folder ``path`` has a readable manifest with no view, and nothing beside it but
        partial views (so that starting it afresh loses no data)."""
        try:
            from sssphase_core.store.files import read_json_input

            manifest = read_json_input(path / MANIFEST, "the session manifest", max_bytes=1 << 26)
        except (OSError, ValueError, InputError):
            return False
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(manifest.get("views", {}), dict):
            return False
        complete = [v for v in manifest.get("views", {}).values() if not isinstance(v, dict) or v.get("status") == "complete"]
        extra = [p for p in path.iterdir() if p.name != MANIFEST and not p.name.startswith(".view_")]
        return not complete and not extra

    @classmethod
    def create(cls, root: Path, name: str, *, resume: bool = False,
               check_resume: Callable[[Session], None] | None = None, **info: Any) -> Session:
        """New session ``root/name``; with ``resume`` reopen an existing one (its partial views dropped), once
        ``check_resume(session)`` (which raises to refuse it) has passed: a refused resume changes nothing."""
        path = Path(root) / check_object_name(name)
        refuse_inside_session(root, "--out")  # a session inside another's folders, which validate then lists
        if Path(root).exists() and not Path(root).is_dir():
            raise InputError(f"--out {root} is a file: give the folder that holds sessions")
        if path.is_symlink():
            raise InputError(f"{path} is a symbolic link: a session is written only inside its --out folder")
        if (path / MANIFEST).exists() and cls._holds_no_view(path):  # a capture that failed before its first view
            warnings.warn(f"{path} holds no complete view (an earlier capture stopped before one): starting it afresh",
                          UserWarning, stacklevel=2)
            for partial in path.glob(".view_*.partial"):
                shutil.rmtree(partial, ignore_errors=True)
            (path / MANIFEST).unlink()
        if (path / MANIFEST).exists():
            if not resume:
                raise InputError(f"session {path} already exists: pass --resume to continue it or choose --out")
            session = cls.open(path)
            if check_resume is not None:
                check_resume(session)
            for partial in path.glob(".view_*.partial"):
                shutil.rmtree(partial, ignore_errors=True)
            session.manifest.update({k: v for k, v in info.items() if k not in session.manifest})
            session.manifest["resumed"] = [*session.manifest.get("resumed", []), time.time()]
            session.save()
            return session
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"cannot create the session folder {path}: {exc.strerror or exc}") from None
        session = cls(path, {"format": FORMAT, "format_version": FORMAT_VERSION, "object": name,
                             "created": time.time(), "views": {}, **info})
        session.save()
        return session

    @classmethod
    def open(cls, path: Path | str) -> Session:
        path = Path(path)
        if path.is_file():  # was "PATH/manifest.json is corrupt: ... Not a directory"
            raise DataError(f"{path} is a file, not a session folder")
        try:
            from sssphase_core.store.files import check_nesting, read_input_text

            manifest = json.loads(read_input_text(path / MANIFEST, "the session manifest", max_bytes=1 << 26))
            check_nesting(manifest, f"the session manifest {path / MANIFEST}")
        except RecursionError:
            raise DataError(f"{path / MANIFEST} is corrupt: it nests deeper than a manifest can") from None
        except FileNotFoundError:
            if not path.exists():
                raise DataError(f"{path} does not exist") from None
            inside = sorted(p.name for p in path.iterdir() if (p / MANIFEST).is_file()) if path.is_dir() else []
            raise DataError(f"{path} is not a session (no {MANIFEST})" + (  # a folder of sessions given for one
                f"; it holds the sessions {', '.join(inside[:5])}{', ...' if len(inside) > 5 else ''}: give one of "
                f"them ({path / inside[0]})" if inside else "")) from None
        except NotADirectoryError:
            raise DataError(f"{path} is a file, not a session folder") from None
        except ValueError as exc:
            raise DataError(f"{path / MANIFEST} is corrupt: {exc}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(manifest.get("format_version", 0), int) \
                or manifest.get("format_version", 0) > FORMAT_VERSION:
            raise DataError(f"{path} is not a version-{FORMAT_VERSION} sssphase session")
        problem = manifest_problem(manifest)
        if problem:
            raise DataError(f"{path / MANIFEST} is damaged: {problem}")
        return cls(path, manifest)

    def save(self) -> None:
        self.manifest["updated"] = time.time()
        write_json_atomic(self.path / MANIFEST, self.manifest)

    # ---- views -----------------------------------------------------------------------------
    def set_view(self, view: int, entry: dict[str, Any]) -> None:
        self.manifest["views"][str(view)] = entry
        self.save()

    @property
    def imported(self) -> bool:
        """Whether ``sss import`` made the session (from a folder of frames) rather than ``sss capture``."""
        return bool(self.manifest.get("rig", {}).get("imported"))

    @property
    def rerun(self) -> str:
        """What completes an unfinished view: ``rerun with --resume``, or for an import (which has no --resume)
        ``run the import again``."""
        return "run the import again" if self.imported else "rerun with --resume"

    def completes_it(self) -> str:
        """How a user completes this session's unfinished views: ``sss capture ... --resume``, or for an import
        (which has no --resume: its frames are still in their folder) the import run again."""
        return ("`sss import` of its folder again completes it (it replaces an unfinished import)" if self.imported
                else "`sss capture ... --resume` completes it")

    def status(self, view: int) -> str:
        """``pending``, ``capturing`` (``importing`` in an imported session), ``interrupted`` or ``complete``;
        anything else a manifest holds is named as such (it is printed in messages: no markup or control
        characters from a file reach the terminal)."""
        status = self.manifest["views"].get(str(view), {}).get("status", "pending")
        if status == "capturing" and self.imported:
            return "importing"
        return status if status in VIEW_STATES else "an unknown status"

    def views(self) -> list[int]:
        """Complete views, in order."""
        return sorted(int(v) for v, e in self.manifest["views"].items() if e.get("status") == "complete")

    def begin_view(self, view: int) -> ViewWriter:
        self.set_view(view, {"status": "capturing", "started": time.time()})
        return ViewWriter(self, view)

    # ---- reading ---------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return str(self.manifest["object"])

    @property
    def objects(self) -> list[str]:
        """Object names in this session (one per session folder); their index is the class label."""
        return [self.name]

    def clip_levels(self) -> tuple[float | None, float | None]:
        """Where this session's PSP and white images clip (linear units; None: unknown or never), from the
        rig's saturation level and the plan's exposures (:func:`clip_levels`)."""
        return clip_levels(self.manifest.get("plan", {}).get("frames", []), self.manifest.get("rig", {}).get("saturation"))

    def projector_black(self, view: int, white: np.ndarray | None = None, mask: np.ndarray | None = None) -> float:
        """The projector's black level relative to white for ``view``: calibrated (``sss calibrate
        projector``), else the sim rig's, else the median black / white ratio of the view's black frame
        over the decoded mask (``white``, ``mask``: the view's, if already loaded), else 0."""
        rig = self.manifest.get("rig", {})
        opts = rig.get("options", {})
        if rig.get("projector_black") is not None:
            return float(rig["projector_black"])
        if str(rig.get("camera", "")).startswith("sim:"):
            from sssphase_core.sim import rig_preset

            return float(opts.get("projector_black", rig_preset(opts.get("preset", "cpu")).projector.black))
        if "black" not in self.arrays(view):
            return 0.0
        white = np.asarray(self.load(view, "white"), np.float32) if white is None else white
        mask = np.asarray(self.load(view, "corr/mask"), bool) if mask is None else mask
        blk, wl = np.asarray(self.load(view, "black"), np.float32).mean(axis=-1), white.mean(axis=-1)
        ok = mask & (wl > 0.05)
        return float(np.clip(np.median(blk[ok] / wl[ok]), 0, 0.5)) if ok.any() else 0.0

    def arrays(self, view: int) -> list[str]:
        return sorted(self.manifest["views"].get(str(view), {}).get("arrays", {}))

    def read(self, view: int, name: str) -> CheckedArray:
        """The array lazily (index it, or ``np.asarray`` it, to load numpy data; every chunk read is verified)."""
        import zarr

        if name not in self.arrays(view):
            raise DataError(f"view {view} of {self.path} has no array {name!r} (has: {', '.join(self.arrays(view))})")
        where = f"array {name} of view {view} of {self.path}"
        folder = self.path / view_dir_name(view) / name
        if not folder.parent.is_dir():  # (each of its arrays was said to be missing, never the folder)
            raise DamagedArray(f"view {view} of {self.path}", f"missing its folder {view_dir_name(view)} (renamed or "
                                                               "deleted?)")
        frame = _frame_size(name, tuple(self.manifest["views"][str(view)]["arrays"][name].get("shape") or ()))
        if frame is not None and frame[0] * frame[1] > MAX_FRAME_PIXELS:  # 30000 x 30000 of zeros was allocated
            raise DamagedArray(where, f"damaged (laid out on {frame[1]}x{frame[0]} pixels, more than any camera frame "
                                      f"sssphase reads: {MAX_FRAME_PIXELS >> 20} MP)")
        chunk_bytes = _check_array_metadata(folder, where)
        try:
            array = zarr.open_array(str(folder), mode="r")
        except Exception as exc:  # missing or unreadable metadata
            raise DamagedArray(where, f"missing or unreadable ({type(exc).__name__})") from None
        found = _checked_chunk_files(folder, where, chunk_bytes)  # (one walk of the chunk files: checked, counted)
        meta = self.manifest["views"][str(view)]["arrays"][name]
        if meta.get("shape") is not None and list(array.shape) != list(meta["shape"]):
            raise DamagedArray(where, f"damaged (shape {tuple(array.shape)} where the manifest says {tuple(meta['shape'])})")
        if meta.get("dtype") is not None and array.dtype.str != meta["dtype"]:  # its chunks would not decode
            raise DamagedArray(where, f"damaged (its metadata says {array.dtype.str} where the manifest says {meta['dtype']})")
        expected = meta.get("chunks")  # older sessions: not recorded
        if expected is not None:
            if found < expected:  # zarr would read a missing chunk as zeros
                raise DamagedArray(where, f"damaged ({expected - found} of {expected} chunks missing)")
            if found > expected:  # written again with other chunks: not the array the manifest describes
                raise DamagedArray(where, f"damaged ({found} chunks stored where the manifest says {expected})")
        return CheckedArray(array, where, meta.get("checksum"))

    def load(self, view: int, name: str) -> np.ndarray:
        """The whole array as numpy (refused, naming it, when it is larger than the memory this machine has free)."""
        array = self.read(view, name)
        from sssphase_core.compute import available_memory

        need, free = int(np.prod(array.shape, dtype=np.float64) * array.dtype.itemsize), available_memory()
        if free is not None and need > free:
            raise DataError(f"{array.where} is {need / 2**30:.1f} GiB ({'x'.join(map(str, array.shape))} {array.dtype}), "
                            f"more than the {free / 2**30:.1f} GiB of memory free: it is not read whole")
        return np.asarray(array[...])

    def iter_views(self) -> Iterator[tuple[int, dict[str, Any]]]:
        for v in self.views():
            yield v, self.manifest["views"][str(v)]

    # ---- checking --------------------------------------------------------------------------
    def validate(self, *, expected_views: int | None = None) -> list[str]:
        """Problems found (empty when the session is complete and intact); reads every array. Intact arrays of light
        (and footprint crops) are also held to :func:`~sssphase_core.store.light.light_problem`: what the readers refuse,
        a session another program wrote with matching checksums may hold."""
        problems = []
        if "projector" not in self.manifest.get("plan", {}):  # what relighting reads first (relight.views.load_view)
            problems.append("the manifest has no capture plan (plan.projector): the patterns its frames were captured "
                            "under are unknown, so it cannot be relit")
        if "rig" not in self.manifest:  # every writer records it: without it the readers fall back on defaults
            problems.append(f"the manifest has no rig record (rig): {RIG_UNKNOWN}")
        projector = _projector_size(self.manifest)
        declared = self.manifest.get("n_views", 0)
        if "n_views" in self.manifest and declared == 0 and self.manifest.get("views"):  # (views recorded, and 0
            # of them declared, passed in silence; a manifest without the key is one the library wrote untold)
            problems.append("the manifest's n_views is 0: the number of views, a whole number >= 1")
        n = expected_views if expected_views is not None else declared
        for v in range(n):
            if self.status(v) != "complete":
                problems.append(f"view {v}: {self.status(v)} (not {'imported' if self.imported else 'captured'} "
                                f"completely; {self.rerun})")
        for v, entry in self.iter_views():
            if "angle" in entry and (problem := angle_problem(entry["angle"])) is not None:  # (1e300 passed, and
                problems.append(f"view {v}: its turntable angle {problem}")  # `sss geometry` merged without the view)
            if not (self.path / view_dir_name(v)).is_dir():
                problems.append(f"view {v}: its folder {view_dir_name(v)} is missing (renamed or deleted?): the manifest "
                                f"lists {len(entry.get('arrays', {}))} arrays there")
                continue
            for name in REQUIRED:
                if name not in entry.get("arrays", {}):
                    problems.append(f"view {v}: required array {name} missing from the manifest")
            before, read = len(problems), {}
            level = None  # the view's white level, for the other images' test (the white is read first)
            for name, meta in sorted(entry.get("arrays", {}).items(), key=lambda item: item[0] != "white"):
                try:
                    data = self.load(v, name)
                except DamagedArray as exc:  # a chunk failed its CRC32C, chunks or files are gone, the shape differs
                    inner = exc.detail.removeprefix("damaged (")[:-1]
                    what = (f"corrupt ({inner if 'CRC32C' in inner else f'a chunk does not decode: {inner}'})"
                            if exc.checksum else exc.detail)  # (the checksum: "corrupt (its data do not match ...)")
                    problems.append(f"view {v}: array {name} is {what}")
                    continue
                except Exception as exc:
                    problems.append(f"view {v}: array {name} missing or unreadable ({type(exc).__name__}: {str(exc)[:80]})")
                    continue
                if name in CONSISTENCY_ARRAYS:
                    read[name] = data
                if list(data.shape) != meta["shape"] or data.dtype.str != meta["dtype"]:
                    problems.append(f"view {v}: array {name} is {data.shape} {data.dtype.str}, manifest says "
                                    f"{tuple(meta['shape'])} {meta['dtype']}")
                elif holds_light(name) or name in ("footprints/crops", "transport/crops"):  # intact, but is it light?
                    if name == "white":
                        level = white_level(data)
                    problem = light_problem(f"array {name}", data, level)  # (crops: in the white's units too)
                    if problem:
                        problems.append(f"view {v}: {problem}")
            if len(problems) == before:  # every array intact: do they belong together?
                problems += [f"view {v}: {p}" for p in view_consistency(entry.get("arrays", {}), read, projector)]
        listed = {view_dir_name(int(k)) for k in self.manifest.get("views", {})}
        for stray in sorted(p.name for p in self.path.glob("view_*") if p.is_dir() and p.name not in listed):
            problems.append(f"{stray}: a view folder the manifest does not list (copied in from another session, or "
                            "renamed?): no command reads it")
        return problems


def _projector_size(manifest: dict) -> tuple[int, int] | None:
    """The capture plan's projector (width, height), or None where the manifest gives none that is usable (said
    elsewhere)."""
    size = manifest.get("plan", {}).get("projector")
    if (isinstance(size, (list, tuple)) and len(size) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x > 0
                                                                      for x in size)):
        return int(size[0]), int(size[1])
    return None


def _frame_size(name: str, shape: tuple[int, ...]) -> tuple[int, ...] | None:
    """The (H, W) camera frame an array is laid out on (the PSP stack, decoded maps, images of light), else None."""
    return shape[1:3] if name == "psp" else shape[:2] if name.startswith("corr/") or holds_light(name) else None


#: The arrays :func:`view_consistency` reads (small: maps and pixel lists).
CONSISTENCY_ARRAYS = ("corr/mask", "corr/xp", "corr/yp", "footprints/pixels")


def coordinates_problem(name: str, coord: np.ndarray, mask: np.ndarray, side: int) -> str | None:
    """What is wrong with decoded projector coordinates ``coord`` (H, W) on the ``mask``-ed pixels of a projector
    ``side`` px across (``corr/xp``: its width, ``corr/yp``: its height), else None: a decoded point lies on the
    projector, give or take a projector's width (a coordinate of 1e30 is finite and still no point of it)."""
    if mask.any() and not (np.abs(coord[mask] - side / 2) <= 1.5 * side).all():
        return f"{name} holds projector coordinates far outside the projector's 0 to {side} px"
    return None


def view_consistency(arrays: dict[str, dict], read: dict[str, np.ndarray],
                     projector: tuple[int, int] | None = None) -> list[str]:
    """What the readers would refuse in a view whose arrays are each intact: sizes that disagree with the decoded
    mask's (H, W) (maps (H, W), images (H, W, 3), the PSP stack (8, H, W, 3)), projector coordinates that are not
    finite on the decoded pixels or (given the ``projector``'s (width, height)) far off it, footprint pixels outside
    the image or not one per crop. ``arrays``: the view's manifest entries; ``read``: its
    :data:`CONSISTENCY_ARRAYS` as :meth:`Session.validate` read them."""
    import collections

    sizes = [_frame_size(name, tuple(meta["shape"])) for name, meta in arrays.items()]
    votes = collections.Counter(x for x in sizes if x is not None and len(x) == 2)
    if "corr/mask" not in arrays or not votes:
        return []
    h, w = votes.most_common(1)[0][0]  # the size most of the view's arrays share: the odd ones out are named
    out = []
    for name, meta in sorted(arrays.items()):
        shape = tuple(meta["shape"])
        want = ((h, w) if name.startswith("corr/") else (8, h, w, 3) if name == "psp"
                else (h, w, 3) if holds_light(name) else None)
        if want is not None and shape != want:
            out.append(f"array {name} is {shape} where the view's other arrays ask for {want} (height, width"
                       f"{', colour' if len(want) > 2 else ''}): the view's arrays do not belong together")
    if out:
        return out
    mask = np.asarray(read["corr/mask"], bool)
    for i, name in enumerate(("corr/xp", "corr/yp")):
        if name not in read:
            continue
        if bad := int((~np.isfinite(np.asarray(read[name])[mask])).sum()):
            out.append(f"array {name} holds {bad} NaN or infinite values on the decoded pixels")
        elif projector is not None and (problem := coordinates_problem(name, np.asarray(read[name]), mask, projector[i])):
            out.append(f"array {problem}")
    if "footprints/pixels" in arrays:
        px, crops = tuple(arrays["footprints/pixels"]["shape"]), tuple(arrays.get("footprints/crops", {}).get("shape", ()))
        if len(px) != 2 or px[1] != 2:
            out.append(f"array footprints/pixels is {px}, not (N, 2) pixels")
        else:
            pixels = np.asarray(read["footprints/pixels"], np.int64)
            if len(pixels) and not ((pixels >= 0).all() and (pixels[:, 0] < h).all() and (pixels[:, 1] < w).all()):
                out.append(f"array footprints/pixels holds pixels outside the {w}x{h} image")
            if crops and crops[0] != len(pixels):
                out.append(f"array footprints/crops holds {crops[0]} crops for {len(pixels)} footprint pixels")
    return out


def session_around(path: Path | str) -> Path | None:
    """The session folder that ``path`` is, or lies inside (a folder with a session manifest), else None:
    outputs must not be written into a session's own folders."""
    try:
        real = Path(path).resolve()
    except (OSError, RuntimeError) as exc:  # a symbolic link loop on the way
        raise InputError(f"{path} cannot be followed: {exc}") from None
    for folder in (real, *real.parents):
        if (folder / MANIFEST).is_file():
            return folder
    return None


def refuse_inside_session(path: Path | str, what: str = "--out") -> None:
    """Raise :class:`InputError` when ``path`` is, or lies inside, a session folder: results stay beside
    the data, never in it (a session's folders hold only what its manifest lists)."""
    inside = session_around(path)
    if inside is not None:
        raise InputError(f"{what} {path} would write into the session {inside}: choose a location outside it")


def check_output_folder(path: Path | str, what: str = "--out") -> None:
    """Refuse an output folder that is an existing file, or lies inside a session (:func:`refuse_inside_session`),
    in one line before any work."""
    if Path(path).is_symlink() and not Path(path).exists():  # it said "File exists" when asked to make the folder
        try:
            os.stat(path)
            kind = "a symbolic link that cannot be followed"
        except OSError as exc:
            kind = ("a symbolic link loop" if exc.errno == errno.ELOOP else
                    f"a broken symbolic link (to {os.readlink(path)}, which does not exist)")
        raise InputError(f"{what} {path} is {kind}: give a folder")
    if Path(path).exists() and not Path(path).is_dir():
        raise InputError(f"{what} {path} is a file: give a folder")
    refuse_inside_session(path, what)


def session_folders(root: Path | str) -> list[Path]:
    """The session folders a folder holds, unopened: the folder itself when it is a session, else every folder
    directly under it with a manifest, by name (possibly none)."""
    root = Path(root)
    return [root] if (root / MANIFEST).exists() else sorted(m.parent for m in root.glob(f"*/{MANIFEST}"))


def sessions_at(root: Path | str) -> list[Session]:
    """The sessions a folder holds (:func:`session_folders`), opened."""
    return [Session.open(folder) for folder in session_folders(root)]


#: the file in an output folder that names the session each object's outputs there came from
OUTPUT_SOURCES = "sources.json"


def _has_outputs(out: Path, obj: str) -> bool:
    """Whether ``out`` holds outputs of ``obj``: its folder (OUT/<object>/view_NNN) or files named OBJECT_vN..."""
    if (out / obj).exists():
        return True
    named = re.compile(re.escape(obj) + r"_v\d+_")  # OBJECT_v<view>_PATTERN_BACKEND... (an object crab_v2's match crab's too)
    try:
        return any(named.match(p.name) for p in out.iterdir())
    except OSError:
        return False


def claim_output(out: Path | str, sessions: Iterable[Session]) -> None:
    """Make ``out`` the place of these sessions' outputs, refusing (before any work) one that holds another
    session's outputs of the same object: every command names its outputs by object (OUT/<object>/...,
    OUT/<object>_v<view>_...), so a re-capture or a copy would silently replace them. The owners are
    recorded in ``OUT/sources.json`` (object -> session folder)."""
    out = Path(out)
    record = out / OUTPUT_SOURCES
    known: dict[str, str] = {}
    if record.exists() or record.is_symlink():
        try:
            from sssphase_core.store.files import read_json_input

            data = read_json_input(record, "the output record")
        except (OSError, InputError) as e:
            raise InputError(f"{record} cannot be read ({getattr(e, 'strerror', None) or e}): it names the session "
                             "behind each object's outputs there; remove it, or choose another --out") from None
        if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
            raise InputError(f"{record} is not a map of object names to session folders: remove it, or choose another --out")
        known = {str(k): v for k, v in data.items()}
    claims = {s.name: str(s.path.resolve()) for s in sessions}
    for obj, here in claims.items():
        if obj not in known and _has_outputs(out, obj):  # files of these names that no command of ours recorded
            raise InputError(f"--out {out} holds files named as the outputs of {obj!r} ({obj}/ or {obj}_v<view>_...) that "
                             f"no sssphase command wrote there (its {OUTPUT_SOURCES} does not name them): they would be "
                             "replaced; choose another --out")
        if known.get(obj, here) != here and _has_outputs(out, obj):
            raise InputError(f"--out {out} holds outputs of {obj!r} from another session ({known[obj]}); this session "
                             f"({here}) would overwrite them: choose another --out")
    names = sorted({*claims, *(k for k in known if _has_outputs(out, k))})  # a record whose outputs are gone is no clash
    for obj in names:  # OBJECT_v<view>_PATTERN_...: objects a and a_v0_b name a's pattern b_v0_c and a_v0_b's c alike
        prefix = re.compile(re.escape(obj) + r"_v\d+_")
        clash = next((other for other in names if other != obj and prefix.match(other)), None)
        if clash is not None:
            raise InputError(f"--out {out} would hold outputs of the objects {obj!r} and {clash!r}, whose file names "
                             f"({obj}_v<view>_<pattern>_...) can be the same: give them separate --out folders")
    if all(known.get(k) == v for k, v in claims.items()):
        return
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(record, {**known, **claims})


def by_object(sessions: Iterable[Session], *, purpose: str) -> dict[str, Session]:
    """The sessions keyed by their object name; two sessions of one object (a re-capture, a copy) are one
    InputError, since every result is named by the object. ``purpose`` says what would go wrong."""
    found: dict[str, Session] = {}
    for s in sessions:
        other = found.setdefault(s.name, s)
        if other.path.resolve() != s.path.resolve():
            raise InputError(f"two sessions hold the object {s.name!r} ({other.path} and {s.path}): {purpose}")
    return found


def find_sessions(paths: Iterable[Path | str]) -> list[Session]:
    """Each path is a session folder or a root of session folders; every session found, in order."""
    found: list[Session] = []
    for p in paths:
        found += sessions_at(p)
    unique: dict[Path, Session] = {}  # a session named twice (itself and its parent folder) counts once
    for s in found:
        unique.setdefault(s.path.resolve(), s)
    found = list(unique.values())
    if not found:
        missing = [str(p) for p in paths if not Path(p).exists()]
        if missing:
            raise InputError(f"{', '.join(missing)} does not exist")
        deeper = sorted({m.parent.parent for p in paths for m in Path(p).glob(f"*/*/*/{MANIFEST}")} |
                        {m.parent.parent for p in paths for m in Path(p).glob(f"*/*/{MANIFEST}")})
        hint = (f"; folders of sessions below it: {', '.join(str(d) for d in deeper[:6])}"
                f"{' ...' if len(deeper) > 6 else ''} (name one: sessions are read one folder down only)") if deeper else ""
        raise InputError(f"no sessions under {', '.join(map(str, paths))}{hint or inside_session_hint(paths)}")
    return found


def inside_session_hint(paths: Iterable[Path | str]) -> str:
    """``"; X is inside the session S: name S or the folder holding it"`` for the first path that lies inside
    a session (a view folder given where sessions are read), else ``""``."""
    for p in paths:
        inside = session_around(p)
        if inside is not None and Path(p).resolve() != Path(inside).resolve():
            return f"; {p} is inside the session {inside}: name the session, or the folder holding it"
    return ""


def list_sessions(root: Path | str) -> list[Session]:
    """Every session folder directly under ``root`` (the learning data set), by object name."""
    return [Session.open(p.parent) for p in sorted(Path(root).glob(f"*/{MANIFEST}"))]
