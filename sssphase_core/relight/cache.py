"""A compressed cache of a source's footprints, keyed by pixel (:class:`FootprintCache`), and where a view's
caches are kept (:func:`cache_path`; torch is imported only when footprints are converted)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import warnings
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from sssphase_core.relight.engine import FootprintSource
    from sssphase_core.store.session import Session


def to_float16(a: np.ndarray) -> np.ndarray:
    """``a`` rounded to float16 (torch's conversion: the same bits as numpy's, ~40x faster on footprints, whose
    tails are mostly float16 subnormals, numpy's slow path: 1.2 s against 0.03 s per 1,024 1080p footprints)."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(a, np.float32)).half().numpy()


def from_float16(a: np.ndarray) -> np.ndarray:
    """float16 ``a`` as float32 (torch's conversion, for the same reason as :func:`to_float16`)."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(a)).float().numpy()


#: The footprints a cache holds in memory at most (bytes of float16).
CACHE_BYTES = 2 * 2**30


class FootprintCache:
    """A compressed (float16 ``.npz``) cache of footprints keyed by pixel, wrapped around a source.

    Later relights (other patterns) read cached footprints and run the source only for pixels that
    are not cached yet; footprints computed now are rounded to float16 as well, so that an image does not
    depend on whether its footprints were cached; ``save()`` writes the cache back when new footprints were computed. It holds
    at most ``max_bytes`` in memory (a 1080p view at K = 90 has ~15 GB of float16 footprints): past
    that, footprints pass through uncached and ``uncached`` counts them. It holds the source's own
    footprints (before any view calibration, which :func:`relight_view` applies after the splat); a
    file of another ``FORMAT`` (format 1 held calibrated footprints) is ignored and rewritten.
    """

    FORMAT = 2

    def __init__(self, source: FootprintSource, path: Path | str, shape: tuple[int, int], patch: int,
                 max_bytes: int = CACHE_BYTES):
        self.source, self.path, self.shape, self.patch = source, Path(path), shape, patch
        self.max_rows = max(0, int(max_bytes) // (patch * patch * 3 * 2))
        self.slot = np.full(shape[0] * shape[1], -1, np.int64)
        self.data = np.zeros((0, patch, patch, 3), np.float16)  # capacity grows by doubling; ``size`` rows used
        self.size = 0
        self.hits = self.misses = self.uncached = 0
        self._dirty = False
        if self.path.exists():
            self._load()
        self.kept_used = np.zeros(self.size, bool)  # which of the footprints kept before (loaded) were read

    def _load(self) -> None:
        """Take the file's footprints when it is a cache of this view and patch; anything else (another
        format, a damaged or foreign file) is ignored and rewritten, and footprints that are not finite are
        computed again: a cache only saves time."""
        import zipfile

        try:
            with np.load(self.path, allow_pickle=False) as z:
                if not ("format" in z.files and int(z["format"]) == self.FORMAT and tuple(z["shape"]) == tuple(self.shape)):
                    return
                data, index = z["data"], z["index"]
        except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile):
            return
        data, index = data[: self.max_rows], np.asarray(index)
        if (data.shape[1:] != (self.patch, self.patch, 3) or data.dtype != np.float16 or index.ndim != 1
                or index.dtype.kind not in "iu" or len(index) < len(data)):
            return
        index = index[: len(data)].astype(np.int64)
        if len(index) and (index.min() < 0 or index.max() >= len(self.slot) or len(np.unique(index)) != len(index)):
            return
        finite = np.concatenate([np.isfinite(data[i:i + 4096]).reshape(len(data[i:i + 4096]), -1).all(axis=1)
                                 for i in range(0, len(data), 4096)]) if len(data) else np.ones(0, bool)
        if not finite.all():  # damaged rows, or a model's own non-finite ones: asked of the model again (it answers for them)
            data, index = data[finite], index[finite]
            self._dirty = True
        self.data, self.size = data, len(data)
        self.slot[index] = np.arange(self.size)

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        flat = pixels[:, 0].astype(np.int64) * self.shape[1] + pixels[:, 1]
        pos = self.slot[flat]
        miss = pos < 0
        out = np.empty((len(pixels), self.patch, self.patch, 3), np.float32)
        if (~miss).any():
            out[~miss] = from_float16(self.data[pos[~miss]])
            hit = pos[~miss]
            self.kept_used[hit[hit < len(self.kept_used)]] = True
        if miss.any():
            from sssphase_core.relight.engine import footprint_array

            fp = self.source(pixels[miss])
            fp = to_float16(footprint_array(fp))  # as the cache holds them: a relight is the same whether its footprints
            out[miss] = from_float16(fp)  # were computed now or read back (sss view's next pattern = sss relight's)
            keep = min(len(fp), self.max_rows - self.size)
            self.uncached += len(fp) - keep
            if keep > 0:
                if self.size + keep > len(self.data):
                    grown = np.zeros((min(self.max_rows, max(2 * len(self.data), self.size + keep, 1024)),
                                      self.patch, self.patch, 3), np.float16)
                    grown[: self.size] = self.data[: self.size]
                    self.data = grown
                self.data[self.size : self.size + keep] = fp[:keep]
                self.slot[flat[miss][:keep]] = self.size + np.arange(keep)
                self.size += keep
                self._dirty = True
        self.hits += int((~miss).sum())
        self.misses += int(miss.sum())
        return out

    @property
    def kept_read(self) -> int:
        """How many footprints were read that an earlier run kept (not those this run computed and read again)."""
        return int(self.kept_used.sum())

    def save(self) -> None:
        if not self._dirty:
            return
        index = np.flatnonzero(self.slot >= 0)
        index = index[np.argsort(self.slot[index])]
        from sssphase_core.store.files import atomic_path

        with atomic_path(self.path, ".npz") as tmp:
            write_npz(tmp, data=self.data[: self.size], index=index, shape=np.asarray(self.shape),
                      format=np.asarray(self.FORMAT))
        self._dirty = False


def write_npz(path: Path | str, **arrays: np.ndarray) -> None:
    """``np.savez_compressed`` at zlib's fastest level (1, not numpy's 6): float16 footprints compress within 4% of
    level 6 in under half its time (42 MB of a 256 x 192 view: 18.1 against 17.4 MB, 0.68 against 1.50 s)."""
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(array), allow_pickle=False)


# --- where a view's footprints are cached ------------------------------------------------------------

def model_tag(checkpoint: Path | str | None) -> str:
    """Short digest of the checkpoint path and modification time: a retrained model gets a new cache."""
    key = "none" if checkpoint is None else f"{Path(checkpoint).resolve()}:{Path(checkpoint).stat().st_mtime_ns}"
    return hashlib.sha256(key.encode()).hexdigest()[:10]


def precision_tag(precision: str) -> str:
    """What a decoder's inference precision adds to its caches' names: nothing for float32 (the names caches had
    before bf16 inference), ``_bf16`` for bf16."""
    return "" if precision == "fp32" else f"_{precision}"


def view_tag(session: Session, view: int) -> str:
    """Short digest of a view's array checksums (the manifest's): footprints cached for one session's view
    are never read for another session's (the same object name imported again, another session relit into
    the same output folder)."""
    arrays = session.manifest.get("views", {}).get(str(view), {}).get("arrays", {})
    key = json.dumps({name: a.get("checksum") for name, a in sorted(arrays.items())}, sort_keys=True)
    return hashlib.sha256(f"{session.path.resolve()}:{key}".encode()).hexdigest()[:10]


def cache_stem(session: Session, rv: Any, backend: str, checkpoint: Path | str | None, precision: str,
               decoder: bool) -> str:
    """The name every cache of a view relit by ``backend`` starts with: object, view, the view's arrays and, when
    the backend has a ``decoder``, the checkpoint and its inference ``precision``."""
    tag = model_tag(checkpoint if decoder else None) + precision_tag(precision if decoder else "fp32")
    return f"{rv.object}_v{rv.view}_{view_tag(session, rv.view)}_{backend}_{tag}"


def cache_path(out: Path, session: Session, rv: Any, member: str, checkpoint: Path | str | None,
               precision: str = "fp32") -> Path:
    """The footprint cache of backend ``member`` for a view (:func:`cache_stem`), so that nothing stale or foreign
    is read."""
    return out / "cache" / f"{cache_stem(session, rv, member, checkpoint, precision, member == 'torch')}.npz"


#: The folder of a decoder run where ``sss train decoder --check-sessions`` relights its check sessions: the
#: footprints cached there start the caches of ``sss eval relight`` and ``sss relight`` with that run's checkpoint.
CHECK_FOLDER = "check"


def seed_cache(path: Path, checkpoint: Path | str | None) -> None:
    """Start the footprint cache file ``path`` (``OUT/cache/<name>``, :func:`cache_path`) from the file of the same
    name in the checkpoint's run's :data:`CHECK_FOLDER` when ``path`` has none yet: the name holds the session
    view's arrays and the checkpoint file's path and time, so an equal name is the same footprints (the training's
    check relit that view with that checkpoint). Linked where the file system allows (both are only ever
    replaced whole, never written in place), else copied."""
    if checkpoint is None or path.exists():
        return
    seed = Path(checkpoint).parent / CHECK_FOLDER / "cache" / path.name
    if not seed.is_file():
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(seed, path)
        except OSError:  # another file system, or one without hard links: copied whole, then renamed
            from sssphase_core.store.files import atomic_path

            with atomic_path(path, ".npz") as tmp:
                shutil.copyfile(seed, tmp)
    except OSError as exc:  # a full or read-only --out: the relight computes those footprints itself (a cache only
        warnings.warn(f"cache: {path} was not started from {seed} ({exc.strerror or exc}): its footprints are "  # saves
                      "computed again", UserWarning, stacklevel=2)  # time; it named the seed as if that had failed)


@contextmanager
def saved_if_interrupted(caches: Iterable[FootprintCache]) -> Iterator[None]:
    """Save the ``caches``' footprints computed so far when the block is interrupted (Ctrl-C, SIGTERM), so that the
    same relight run again computes only the rest (a 1080p view through a decoder on a CPU takes tens of minutes)."""
    try:
        yield
    except KeyboardInterrupt:
        for cache in caches:
            kept(cache.save, cache.path)
        raise


def kept(save: Callable[[], None], path: Path) -> str | None:
    """Run a cache's ``save`` (of the file ``path``) -> None, or the line that says it was not kept: a cache only
    saves time, so a file system that refuses it (full, read-only, a file where its folder goes) costs the next
    relight its time, not this one its images."""
    try:
        save()
    except OSError as exc:
        return (f"cache: {path} was not kept ({exc.strerror or exc}): later relights compute its footprints again "
                "(--no-cache keeps none)")
    return None


def footprint_bytes(n_pixels: int, patch: int) -> int:
    """The float16 bytes of ``n_pixels`` footprints of K = ``patch`` (what a cache of a view would hold)."""
    return n_pixels * patch**2 * 3 * 2


def view_caches(out: Path, rv: Any, sources: list[tuple[Any, int]], members: tuple[str, ...],
                checkpoint: Path | str | None) -> list[FootprintCache]:
    """Each (source, K) of a view's backend ``members`` wrapped in its :class:`FootprintCache` at ``out/cache``
    (:func:`cache_path`), started from the checkpoint run's check where it relit the view (:func:`seed_cache`)."""
    caches = []
    for (src, k), member in zip(sources, members, strict=True):
        precision = getattr(getattr(src, "backend", None), "precision", "fp32")  # the decoder's (make_source's source)
        path = cache_path(out, rv.session, rv, member, checkpoint, precision)
        seed_cache(path, checkpoint)
        caches.append(FootprintCache(src, path, rv.proj.shape, k))
    return caches
