"""Patch datasets: 24-channel PSP patches around surface pixels, with footprint targets and labels.

A view is a :class:`ViewData`: its 8 PSP images (8, H, W, 3), the surface pixels used from it, their
object and material labels and, for decoder training, their footprints (N, K, K, 3), which may be a
lazily read chunked array (zarr) so that a session's footprints are never all loaded. Views come
from the simulator (:func:`simulate_views`) or a session directory (:func:`session_views`) (flat
synthetic scenes with analytic footprints, for `sss bench gpu` and the tests, are in
:mod:`sssphase_core.bench.synthetic`). Pixel subsets are drawn with seeds
derived from (seed, object, view), so every run sees the same patches.
"""

from __future__ import annotations

import hashlib
import json
import warnings
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sssphase_core.errors import DataError, InputError
from sssphase_core.store.light import light_problem, white_level

N_PSP = 8


@dataclass
class ViewData:
    """One view of one object; ``footprints`` (if any) is aligned with ``pixels``."""

    object: str
    view: int
    psp: np.ndarray  # (8, H, W, 3) float32
    pixels: np.ndarray  # (N, 2) int (y, x)
    materials: np.ndarray  # (N,) int material label, -1 unknown
    footprints: object | None = None  # (N, K, K, 3) array-like or None
    isp: dict | None = None  # the camera pipeline that made the footprint crops (a session view's camera_isp)
    dots: np.ndarray | None = None  # (N, k, k): the camera pixels each crop's dot lit (None: the pixel alone)

    def __post_init__(self) -> None:
        if self.psp.ndim != 4 or self.psp.shape[0] != N_PSP or self.psp.shape[-1] != 3:
            raise DataError(f"{self.object}/view {self.view}: PSP stack must be (8, H, W, 3), got {self.psp.shape}")
        if self.footprints is not None and self.footprints.shape[0] != len(self.pixels):
            raise DataError(f"{self.object}/view {self.view}: {self.footprints.shape[0]} footprints for {len(self.pixels)} pixels")


def view_seed(seed: int, obj: str, view: int) -> int:
    """A stable per-(object, view) seed (not Python's salted ``hash``)."""
    return zlib.crc32(f"{seed}/{obj}/{view}".encode())


def sample_pixels(mask: np.ndarray, n: int | None, seed: int) -> np.ndarray:
    """Up to ``n`` mask pixels (all if None), sorted in raster order, drawn with ``seed``."""
    pixels = np.argwhere(mask)
    if n is not None and len(pixels) > n:
        pick = np.random.default_rng(seed).choice(len(pixels), n, replace=False)
        pixels = pixels[np.sort(pick)]
    return pixels.astype(np.int64)


def to_channels_first(psp: np.ndarray) -> torch.Tensor:
    """(8, H, W, 3) -> (24, H, W) tensor with channel ``img * 3 + c``."""
    t = torch.as_tensor(np.ascontiguousarray(psp, dtype=np.float32))
    return t.permute(0, 3, 1, 2).reshape(3 * N_PSP, t.shape[1], t.shape[2])


def pad_for_patches(stack: torch.Tensor, k: int) -> torch.Tensor:
    """(C, H, W) -> (C, H + K - 1, W + K - 1) zero-padded so that :func:`crop_patches` needs no padding."""
    lo = k // 2
    return torch.nn.functional.pad(stack, (lo, k - 1 - lo, lo, k - 1 - lo))


def crop_patches(stack: torch.Tensor, pixels: np.ndarray | torch.Tensor, k: int, *, padded: bool = False) -> torch.Tensor:
    """(C, H, W) stack -> (N, C, K, K) crops with the pixel at K // 2, zero outside the image.

    ``padded``: ``stack`` is already :func:`pad_for_patches`'s output (a training loader pads each view
    once instead of copying the whole stack per batch: 1080p stacks are 200 MB)."""
    source = stack if padded else pad_for_patches(stack, k)
    pix = torch.as_tensor(pixels, dtype=torch.long, device=source.device)
    offs = torch.arange(k, device=source.device)
    ys = (pix[:, 0, None] + offs)[:, :, None].expand(-1, k, k)
    xs = (pix[:, 1, None] + offs)[:, None, :].expand(-1, k, k)
    return source[:, ys, xs].permute(1, 0, 2, 3)


def psp_patches(psp: np.ndarray, pixels: np.ndarray, k: int, chunk: int = 4096) -> np.ndarray:
    """(8, H, W, 3) PSP images -> (N, 24, K, K) float32 patches around ``pixels``."""
    stack = pad_for_patches(to_channels_first(psp), k)
    return torch.cat([crop_patches(stack, pixels[i : i + chunk], k, padded=True) for i in range(0, len(pixels), chunk)]).numpy()


class PatchDataset(torch.utils.data.Dataset):
    """Patches of several views; items are dicts of tensors (``psp``, ``object``, ``material``, ``view``
    and, when ``with_targets``, ``footprint`` (3, K, K), ``camera``, the code of the camera that recorded
    it (:func:`sssphase_core.learning.camera.crop_codes`), and ``dot`` (k, k), the camera pixels its dot lit
    (:func:`sssphase_core.processing.footprints.dot_kernels`). ``batch(indices)`` builds a batch at once."""

    def __init__(self, views: Sequence[ViewData], patch: int, classes: Sequence[str], *, with_targets: bool = False) -> None:
        if not views:
            raise InputError("no views to build a patch dataset from")
        if with_targets and any(v.footprints is None for v in views):
            missing = ", ".join(f"{v.object}/{v.view}" for v in views if v.footprints is None)
            raise DataError(f"no footprints stored for {missing}: decoder training needs captured footprints")
        if with_targets:
            odd = [v for v in views if tuple(v.footprints.shape[1:3]) != (patch, patch)]  # type: ignore[union-attr]
            if odd:
                from sssphase_core.learning.models import PRESETS

                k = odd[0].footprints.shape[1]  # type: ignore[union-attr]
                sizes = ", ".join(f"{name} {p.patch}" for name, p in PRESETS.items())
                raise InputError(f"the footprints of {odd[0].object} view {odd[0].view} are {k}x{k} but this decoder "
                                 f"predicts {patch}x{patch}: the crop size is the rig's (the rig file's patch, "
                                 f"`sss import --patch`) and must be the model preset's ({sizes})")
        unknown = sorted({v.object for v in views} - set(classes))
        if unknown:
            raise InputError(f"objects {unknown} are not among the classes {list(classes)}")
        self.views, self.patch, self.classes, self.with_targets = list(views), patch, list(classes), with_targets
        self.stacks = [pad_for_patches(to_channels_first(v.psp), patch) for v in self.views]  # padded once
        self._crop_from = self.stacks  # or their copies on a training device (place)
        counts = np.array([len(v.pixels) for v in self.views])
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.view_of = np.repeat(np.arange(len(self.views)), counts)
        self._labels = {
            "object": np.repeat([self.classes.index(v.object) for v in self.views], counts),
            "material": np.concatenate([np.asarray(v.materials, np.int64) for v in self.views]),
            "view": np.repeat([v.view for v in self.views], counts),
        }
        if with_targets:  # each crop's camera and dot, through which decoder training passes its prediction
            from sssphase_core.learning.camera import crop_codes
            from sssphase_core.processing.footprints import pixel_alone_kernel

            self.camera = np.concatenate([crop_codes(v.isp, v.pixels, patch) for v in self.views])
            alone = pixel_alone_kernel()
            side = len(alone)
            self.dots = np.concatenate([np.broadcast_to(alone, (len(v.pixels), side, side)) if v.dots is None
                                        else np.asarray(v.dots, np.float32).reshape(-1, side, side) for v in self.views])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    @property
    def stack_bytes(self) -> int:
        """Bytes of the padded PSP view stacks (what :meth:`place` copies)."""
        return sum(s.numel() * s.element_size() for s in self.stacks)

    def place(self, device: torch.device | str | None) -> None:
        """Crop patches from copies of the PSP stacks on ``device`` (no host crop, no host-to-device copy
        of the patches; footprint targets and labels stay on the host); ``None``: from the host stacks
        again, the copies released."""
        self._crop_from = self.stacks if device is None else [s.to(device) for s in self.stacks]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[0] for k, v in self.batch(np.array([i])).items()}

    def labels(self, kind: str = "object") -> np.ndarray:
        """Per-item ``object`` (index into ``classes``), ``material`` label or ``view`` index."""
        if kind not in self._labels:
            raise InputError(f"unknown label kind {kind!r} (object, material or view)")
        return self._labels[kind]

    def batch(self, indices: np.ndarray | torch.Tensor) -> dict[str, torch.Tensor]:
        idx = np.asarray(indices, dtype=np.int64)
        vids = self.view_of[idx]
        out = {k: torch.as_tensor(v[idx]) for k, v in self._labels.items()}
        out["psp"] = torch.empty(len(idx), 3 * N_PSP, self.patch, self.patch, device=self._crop_from[0].device)
        if self.with_targets:
            out["footprint"] = torch.empty(len(idx), 3, self.patch, self.patch)
            out["camera"], out["dot"] = torch.as_tensor(self.camera[idx]), torch.as_tensor(self.dots[idx])
        for vid in np.unique(vids):
            sel = np.nonzero(vids == vid)[0]
            local = idx[sel] - self.offsets[vid]
            view = self.views[vid]
            out["psp"][torch.as_tensor(sel, device=out["psp"].device)] = crop_patches(
                self._crop_from[vid], view.pixels[local], self.patch, padded=True)
            if self.with_targets:
                order = np.argsort(local)  # chunked stores read sorted indices fastest
                fp = torch.as_tensor(_take(view.footprints, local[order]), dtype=torch.float32)
                out["footprint"][sel[order]] = fp.permute(0, 3, 1, 2)
        return out


def _take(array: object, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of a numpy or chunked (zarr: ``oindex``) array."""
    return np.asarray(array.oindex[idx] if hasattr(array, "oindex") else array[idx])


def split_by_object(views: Sequence[ViewData], test_objects: Sequence[str]) -> tuple[list[ViewData], list[ViewData]]:
    """(train, test) with every view of ``test_objects`` in test (unseen objects, as in the paper)."""
    test = set(test_objects)
    return [v for v in views if v.object not in test], [v for v in views if v.object in test]


def split_by_view(views: Sequence[ViewData], held_out: Sequence[int]) -> tuple[list[ViewData], list[ViewData]]:
    """(train, test) with the view indices ``held_out`` in test."""
    held = set(held_out)
    return [v for v in views if v.view not in held], [v for v in views if v.view in held]


# --- sources -----------------------------------------------------------------------------------


def _cache_path(cache_dir: Path | None, params: dict) -> Path | None:
    if cache_dir is None:
        return None
    key = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir) / f"{params['object']}_v{params['view']}_{key}.npz"


def _load_cached(path: Path | None, obj: str, view: int) -> ViewData | None:
    """A cached simulated view, or None when there is none or the file is damaged (it is simulated again and
    the cache rewritten: the cache is ours, never a user's data)."""
    if path is None or not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            fp = z["footprints"] if "footprints" in z.files else None
            return ViewData(obj, view, z["psp"], z["pixels"], z["materials"], fp)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):  # truncated, foreign or pickled
        warnings.warn(f"{path}: a damaged cache file of {obj} view {view}; simulated again", stacklevel=3)
        return None


def _save_cached(path: Path | None, vd: ViewData) -> None:
    if path is None:
        return
    from sssphase_core.store.files import atomic_path

    arrays = {"psp": vd.psp, "pixels": vd.pixels, "materials": vd.materials}
    if vd.footprints is not None:
        arrays["footprints"] = np.asarray(vd.footprints)
    with atomic_path(path, ".npz") as tmp:
        np.savez(tmp, **arrays)


def simulate_views(
    objects: Sequence[str],
    views: Sequence[int],
    *,
    n_views: int = 4,
    rig: str = "cpu",
    pixels_per_view: int | None = 2000,
    footprints: bool = False,
    noisy_footprints: bool = False,
    seed: int = 0,
    cache_dir: Path | str | None = None,
) -> list[ViewData]:
    """Render the 8 noisy PSP captures of each (object, view) with the simulated rig.

    Footprint targets are the simulator's exact footprints (plus the capture noise model when
    ``noisy_footprints``). Results are cached as .npz under ``cache_dir`` keyed by every parameter.
    """
    from sssphase_core.processing.patterns import paper_inputs, psp_config_for
    from sssphase_core.sim import SimScene, get_object, rig_preset

    rig_cfg = rig_preset(rig)
    out = []
    for obj in objects:
        get_object(obj)  # raises UnknownObjectError listing the catalogue
        for view in views:
            params = dict(object=obj, view=int(view), n_views=n_views, rig=rig, n=pixels_per_view,
                          fp=footprints, noisy=noisy_footprints, seed=seed, v=1)
            path = _cache_path(Path(cache_dir) if cache_dir else None, params)
            cached = _load_cached(path, obj, int(view))
            if cached is not None:
                out.append(cached)
                continue
            scene = SimScene(obj, rig=rig_cfg, view=int(view), n_views=n_views, seed=seed)
            wp, hp = _projector_size(scene)
            patterns = paper_inputs(wp, hp, period=psp_config_for(wp, hp).period)
            rng = np.random.default_rng(view_seed(seed, obj, int(view)))
            psp = np.asarray(scene.capture(patterns, rng), dtype=np.float32)
            valid = scene.mask & np.isfinite(scene.proj_xy).all(axis=-1)
            pixels = sample_pixels(valid, pixels_per_view, view_seed(seed + 1, obj, int(view)))
            materials = _material_labels(scene, pixels)
            fp = None
            if footprints:
                fp = np.asarray(scene.footprints(pixels), dtype=np.float32)
                if noisy_footprints:
                    fp = fp + _footprint_noise(scene, fp, rng)
            vd = ViewData(obj, int(view), psp, pixels, materials, fp)
            _save_cached(path, vd)
            out.append(vd)
    return out


def _projector_size(scene: object) -> tuple[int, int]:
    return int(scene.rig.projector.width), int(scene.rig.projector.height)


def _material_labels(scene: object, pixels: np.ndarray) -> np.ndarray:
    mat = getattr(scene, "material", None)
    if isinstance(mat, dict):
        mat = mat.get("label", mat.get("labels"))
    elif mat is not None and hasattr(mat, "label"):
        mat = mat.label
    if mat is None:
        return np.full(len(pixels), -1, np.int64)
    return np.asarray(mat)[pixels[:, 0], pixels[:, 1]].astype(np.int64)


def _footprint_noise(scene: object, fp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One capture's noise on footprints (shot + read noise of the simulated sensor, linear units)."""
    return (rng.standard_normal(fp.shape) * scene.rig.sensor.noise_std(np.clip(fp, 0, None))).astype(np.float32)


#: A view's sampled footprint rows up to this size are read into memory once. A random batch touches
#: a chunk (hundreds of crops) per row it reads: the lite demo's loader spent 0.14 s per batch of 32.
ROWS_IN_MEMORY_BYTES = 64 * 2**20


class Rows:
    """Rows ``idx`` of a (possibly chunked, lazily read) array, readable like one: ``shape``, ``[i]``."""

    def __init__(self, array: object, idx: np.ndarray) -> None:
        self.array, self.idx = array, np.asarray(idx, np.int64)
        self.shape = (len(self.idx), *array.shape[1:])
        self.nbytes = int(np.prod(self.shape)) * np.dtype(array.dtype).itemsize  # type: ignore[attr-defined]

    def __len__(self) -> int:
        return len(self.idx)

    def __getitem__(self, i: np.ndarray) -> np.ndarray:
        return _take(self.array, self.idx[np.asarray(i)])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return np.asarray(_take(self.array, self.idx), dtype=dtype)


def held_out_split(root: Path | str, objects: Sequence[str] | None = None) -> tuple[dict[str, list[int]], dict[str, list[int]]]:
    """Training and validation views ``({object: views}, {object: views})`` of the sessions under ``root``:
    each session's last complete view is held out for validation when it has two or more, else all of
    its views train (what `sss train decoder --sessions` uses when no views are given). ``root`` may
    also be one session folder (:func:`~sssphase_core.store.session.sessions_at`)."""
    from sssphase_core.store.session import sessions_at

    train, val = {}, {}
    for s in sessions_at(root):
        if objects and s.name not in objects:
            continue
        views = sorted(s.views())
        held = views[-1:] if len(views) >= 2 else []
        train[s.name], val[s.name] = [v for v in views if v not in held], held
    return train, val


def session_views(
    root: Path | str,
    objects: Sequence[str] | None = None,
    views: Sequence[int] | Mapping[str, Sequence[int]] | None = None,
    *,
    pixels_per_view: int | None = 2000,
    footprints: bool = False,
    seed: int = 0,
    psp_cache: dict[tuple[str, int], np.ndarray] | None = None,
) -> list[ViewData]:
    """Views of the sessions under ``root`` (one folder per object, see ``sssphase_core.store.session``; or
    ``root`` is one session folder: :func:`~sssphase_core.store.session.sessions_at`).

    PSP stacks are loaded per view (8 images, clipped samples repaired: :func:`repaired_psp`).
    ``views``: the same views of every session, each object's own (a mapping), or None for every complete
    view. Footprints are read once per view when the sampled rows are small (:data:`ROWS_IN_MEMORY_BYTES`),
    else they stay in their zarr arrays and are read per batch. With ``footprints`` the pixels are
    those with captured footprints, and each view records how its crops were recorded (the camera's
    ``camera_isp`` and each crop's dot offset, for :mod:`sssphase_core.learning.camera`); otherwise the
    decoded correspondence mask.
    Material labels come from ``gt/labels`` when present (simulated sessions), else -1. ``psp_cache``: the PSP
    stacks read (and checked) so far by (session folder, view), shared by the views it returns (a run that reads the
    same views for several steps: at 1080p each stack is 200 MB read, repaired and checked).
    """
    from sssphase_core.store.session import by_object, sessions_at

    sessions = by_object(sessions_at(root), purpose="training would read one of them only; give "
                         "--sessions a folder holding one session per object")
    names = list(objects) if objects else sorted(sessions)
    missing = [n for n in names if n not in sessions]
    if missing:
        raise DataError(f"no session for {missing} under {root} (found: {', '.join(sorted(sessions)) or 'none'})")
    out = []
    for name in names:
        s = sessions[name]
        chosen = views.get(name, []) if isinstance(views, Mapping) else views
        for view in s.views() if chosen is None else chosen:
            if view not in s.views():
                raise DataError(f"session {s.path} has no complete view {view} (its views: "
                                f"{', '.join(map(str, s.views())) or 'none'}; choose among those)")
            level = white_level(s.load(view, "white")) if "white" in s.arrays(view) else None
            psp = None if psp_cache is None else psp_cache.get((str(s.path), int(view)))
            if psp is None:
                psp = repaired_psp(s, view)
                # NaN surfaced as a NaN loss blamed on the learning rate; huge or negated frames train on no light
                problem = light_problem("psp", psp, level)
                if problem:
                    raise DataError(f"session {s.path} view {view}: {problem}: re-capture or re-import the view, or "
                                    "leave it out (--views)")
                if psp_cache is not None:
                    psp_cache[(str(s.path), int(view))] = psp
            rng_seed = view_seed(seed, name, view)
            fp = None
            if footprints:
                if "footprints/crops" not in s.arrays(view):
                    raise DataError(f"session {s.path} view {view} has no footprints: capture with --footprints")
                all_px = s.load(view, "footprints/pixels").astype(np.int64)
                h, w = psp.shape[1:3]
                if all_px.ndim != 2 or all_px.shape[1:] != (2,) or not (
                        (all_px >= 0).all() and (all_px[:, 0] < h).all() and (all_px[:, 1] < w).all()):
                    raise DataError(f"session {s.path} view {view}: footprints/pixels are not (N, 2) pixels inside the "
                                    f"{w}x{h} image: the session is damaged")
                keep = np.zeros(len(all_px), bool)
                keep[sample_pixels(np.ones(len(all_px), bool), pixels_per_view, rng_seed)[:, 0]] = True
                idx = np.flatnonzero(keep)
                pixels, fp = all_px[idx], Rows(s.read(view, "footprints/crops"), idx)
                if fp.nbytes <= ROWS_IN_MEMORY_BYTES:  # one sorted read, instead of whole chunks per batch
                    fp = np.asarray(fp)
                    # crops of -60000 trained to a loss of 1e10 and exited 0: held to the frames' test of light
                    problem = light_problem("footprints/crops", fp, level)
                    if problem:
                        raise DataError(f"session {s.path} view {view}: {problem}: re-capture or re-import the view, "
                                        "or leave it out (--views)")
            else:
                pixels = sample_pixels(s.load(view, "corr/mask").astype(bool), pixels_per_view, rng_seed)
            labels = s.load(view, "gt/labels") if "gt/labels" in s.arrays(view) else None
            mats = labels[pixels[:, 0], pixels[:, 1]].astype(np.int64) if labels is not None else np.full(len(pixels), -1)
            isp, dots = None, None
            if footprints:  # how the crops were recorded: the camera's pipeline, and the pixels each one's dot lit
                from sssphase_core.processing.footprints import dot_kernels

                isp = s.manifest.get("views", {}).get(str(view), {}).get("camera_isp")
                if {"corr/xp", "corr/yp", "corr/mask"} <= set(s.arrays(view)):  # else: crops centred on their pixels
                    xp, yp = (s.load(view, k).astype(np.float64) for k in ("corr/xp", "corr/yp"))
                    dots = dot_kernels(xp, yp, s.load(view, "corr/mask").astype(bool), pixels)
            out.append(ViewData(name, int(view), psp, pixels, mats, fp, isp, dots))
    return out


def repaired_psp(session: object, view: int) -> np.ndarray:
    """A session view's (8, H, W, 3) PSP stack with clipped samples repaired (:func:`psp.declip`) where
    the session knows its clipping level: what the model backends see when relighting, so training sees it too."""
    psp = np.asarray(session.load(view, "psp"), np.float32)  # type: ignore[attr-defined]
    level, white_level = session.clip_levels()  # type: ignore[attr-defined]
    from sssphase_core.processing.isp import SATURATION_MARGIN
    from sssphase_core.processing.psp import declip

    if level is None or not (psp >= SATURATION_MARGIN * level).any():
        return psp

    white = np.asarray(session.load(view, "white"), np.float32)  # type: ignore[attr-defined]
    black = session.projector_black(view, white)  # type: ignore[attr-defined]
    return declip(psp, level, white=white, white_saturation=white_level, black=black)[0]
