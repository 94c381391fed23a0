"""A view's footprints as a few eigen-footprints per colour, for relighting new patterns in seconds.

Relighting splats one K x K footprint per lit pixel ``p``, scaled by the light it receives ``L(p)``:
``I(q) = sum_p L(p) f_p(q - p)``. Written in a basis of r footprint images ``B_k`` per colour (from the
SVD of a sample of the view's own footprints), ``f_p = sum_k a_pk B_k``, the sum becomes r convolutions:
``I = sum_k (L a_k) * B_k``, each a 2-D filter over the image (OpenCV's ``filter2D``, DFT-based for large
kernels). A 1080p view at K = 90 has ~10 GB of float16 footprints, more than any cache holds, and its full
splat takes minutes on 2 cores; its coefficients take (N, 3, r) values (~25 MB in float16 at r = 23) and a new
pattern is r x 3 filters. The footprints are smooth, so few components keep them: the 1080p crab's analytic
footprints need 23 for 5e-6 of their energy left out, and relight within 88 dB (PSNR at the image's peak)
of the full splat, 17.5x faster (``sss bench relight-cache``, docs/benchmarks/paper-scale.md).

:class:`LowRankTap` collects the coefficients while a relight's footprint pass goes by (the view
calibration's PSP patterns light every pixel); :class:`LowRankFootprints` holds and relights them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from sssphase_core.processing.projector import emitted_light
from sssphase_core.relight.engine import (
    FootprintSource,
    Projection,
    footprint_array,
    member_maps,
    pattern_stack,
    received_light,
)

#: Footprints sampled from the view to find its basis, the largest rank, and the share of their energy
#: (sum of squares) the basis may leave out.
BASIS_SAMPLE, MAX_RANK, RESIDUAL = 2048, 48, 1e-6
#: The share of the footprints (every n-th) whose residual is measured as the pass goes by.
RESIDUAL_STRIDE = 4


def _top_right_singular(a: np.ndarray, n: int, power: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(singular values (l,), right singular vectors (l, D)) of the l = min(n, rows, cols) leading components of
    ``a`` (rows, D): a randomised range finder with ``power`` subspace iterations (Halko, Martinsson & Tropp 2011),
    ~20x cheaper than a full SVD of a 2,048 x 8,100 sample, the leading components equal within float tolerance."""
    rows, cols = a.shape
    n = min(n, rows, cols)
    q = np.linalg.qr(a @ np.random.default_rng(seed).standard_normal((cols, n)))[0]
    for _ in range(power):
        q = np.linalg.qr(a @ np.linalg.qr(a.T @ q)[0])[0]
    _, sigma, vt = np.linalg.svd(q.T @ a, full_matrices=False)
    return sigma, vt


def fit_basis(sample: np.ndarray, max_rank: int = MAX_RANK, residual: float = RESIDUAL) -> np.ndarray:
    """(S, K, K, 3) footprints -> (3, r, K, K) orthonormal eigen-footprints per colour: the leading right
    singular vectors, as few (at least 1, at most ``max_rank``) as leave at most ``residual`` of the sample's
    energy out in every colour."""
    s, k = sample.shape[0], sample.shape[1]
    flat = [np.nan_to_num(np.asarray(sample[..., c], np.float64).reshape(s, k * k)) for c in range(3)]
    svds = [_top_right_singular(a, max_rank + 8) for a in flat]  # (sigma, Vt) per colour, a margin beyond max_rank
    rank = 1
    for a, (sigma, _) in zip(flat, svds, strict=True):
        total = float(np.square(a).sum())  # the whole energy, not only the components found
        if total > 0:
            left = 1.0 - np.cumsum(sigma**2) / total
            rank = max(rank, int(np.argmax(left <= residual)) + 1 if (left <= residual).any() else len(sigma))
    rank = min(rank, max_rank, min(len(sigma) for sigma, _ in svds))
    return np.stack([vt[:rank].reshape(rank, k, k) for _, vt in svds]).astype(np.float32)


class LowRankFootprints:
    """A view's footprints as coefficients ``(N, 3, r)`` of the pixels ``(N, 2)`` on eigen-footprints
    ``basis`` (3, r, K, K); ``residual``: the share of the footprints' energy the basis leaves out
    (measured over every footprint projected)."""

    FORMAT = 1

    def __init__(self, basis: np.ndarray, pixels: np.ndarray, coefficients: np.ndarray, shape: tuple[int, int],
                 residual: float) -> None:
        self.basis, self.pixels, self.coefficients = basis, pixels, coefficients
        self.shape, self.residual = (int(shape[0]), int(shape[1])), float(residual)

    @property
    def rank(self) -> int:
        return int(self.basis.shape[1])

    def relight(self, proj: Projection, patterns: np.ndarray, *, white: np.ndarray | None = None) -> np.ndarray:
        """(P, H, W, 3) images under projector ``patterns`` (as :func:`~sssphase_core.relight.engine.relight`
        takes them, the projector black level's light from ``white`` included)."""
        import cv2

        pats = pattern_stack(patterns, proj)
        light = emitted_light(pats, proj.gamma) * np.float32(1.0 - proj.black)
        ys, xs = self.pixels[:, 0], self.pixels[:, 1]
        received = received_light(proj, light, ys, xs)  # (N, P, 3)
        h, w = self.shape
        k = self.basis.shape[-1]
        anchor = k - 1 - k // 2  # filter2D correlates: the flipped kernel's centre
        out = np.zeros((len(pats), h, w, 3), np.float32)
        grid = np.zeros((h, w), np.float32)
        for c in range(3):
            kernels = [np.ascontiguousarray(self.basis[c, j, ::-1, ::-1]) for j in range(self.rank)]
            for p in range(len(pats)):
                for j, kernel in enumerate(kernels):
                    grid[ys, xs] = received[:, p, c] * self.coefficients[:, c, j]
                    out[p, ..., c] += cv2.filter2D(grid, -1, kernel, anchor=(anchor, anchor), borderType=cv2.BORDER_CONSTANT)
        if white is not None and proj.black > 0:
            out += np.float32(proj.black) * np.asarray(white, np.float32)[None]
        return out

    def mapped(self, change: Callable[[torch.Tensor], torch.Tensor]) -> LowRankFootprints:
        """These footprints through a linear ``change`` ((N, K, K, 3) -> (N, K, K, 3): a stretch, a softening), each
        colour's energy kept: their eigen-footprints are the changed ``basis`` and each pixel's coefficients are scaled
        by its colours' energy before over after."""
        import torch

        k = self.basis.shape[-1]
        flat = torch.from_numpy(np.ascontiguousarray(self.basis.transpose(1, 2, 3, 0)))  # (r, K, K, 3): one per component
        basis = np.ascontiguousarray(change(flat).numpy().transpose(3, 0, 1, 2), np.float32)  # (3, r, K, K)
        had = np.einsum("ncr,cr->nc", self.coefficients, self.basis.reshape(3, -1, k * k).sum(-1))
        has = np.einsum("ncr,cr->nc", self.coefficients, basis.reshape(3, -1, k * k).sum(-1))
        scale = np.where(has > 0, had / np.where(has > 0, has, 1.0), 1.0).astype(np.float32)
        return LowRankFootprints(basis, self.pixels, self.coefficients * scale[..., None], self.shape, self.residual)

    def arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The arrays that :meth:`from_arrays` reads back (coefficients as float16)."""
        return {f"{prefix}basis": self.basis, f"{prefix}pixels": self.pixels.astype(np.int32),
                f"{prefix}coefficients": self.coefficients.astype(np.float16), f"{prefix}shape": np.asarray(self.shape),
                f"{prefix}residual": np.asarray(self.residual), f"{prefix}format": np.asarray(self.FORMAT)}

    @classmethod
    def from_arrays(cls, z: dict[str, np.ndarray] | np.lib.npyio.NpzFile, prefix: str = "") -> LowRankFootprints | None:
        """Read :meth:`arrays` back; None for anything else (another format, shapes that do not agree)."""
        try:
            if int(z[f"{prefix}format"]) != cls.FORMAT:
                return None
            basis, pixels = np.asarray(z[f"{prefix}basis"], np.float32), np.asarray(z[f"{prefix}pixels"], np.int64)
            coef, shape = np.asarray(z[f"{prefix}coefficients"], np.float32), tuple(int(x) for x in z[f"{prefix}shape"])
            residual = float(z[f"{prefix}residual"])
        except (KeyError, ValueError, TypeError):
            return None
        ok = (basis.ndim == 4 and basis.shape[0] == 3 and basis.shape[2] == basis.shape[3] and pixels.ndim == 2
              and pixels.shape[1] == 2 and coef.shape == (len(pixels), 3, basis.shape[1]) and len(shape) == 2
              and np.isfinite(basis).all() and np.isfinite(coef).all())
        if ok and len(pixels):
            ok = bool(pixels.min() >= 0 and (pixels[:, 0] < shape[0]).all() and (pixels[:, 1] < shape[1]).all())
        return cls(basis, pixels, coef, shape, residual) if ok else None  # type: ignore[arg-type]


class LowRankTap:
    """A footprint source that passes its source's footprints on and keeps their coefficients on a basis
    fitted to a sample of the view's pixels (the sample's footprints come from the source first: put a
    :class:`~sssphase_core.relight.cache.FootprintCache` in front so that the pass reuses them)."""

    def __init__(self, source: FootprintSource, pixels: np.ndarray, shape: tuple[int, int], *,
                 sample: int = BASIS_SAMPLE, seed: int = 0) -> None:
        self.source, self.shape = source, (int(shape[0]), int(shape[1]))
        pick = np.sort(np.random.default_rng(seed).permutation(len(pixels))[:sample])
        self.basis = fit_basis(footprint_array(source(pixels[pick])) if len(pick) else np.zeros((1, 1, 1, 3), np.float32))
        self.slot = np.full(self.shape[0] * self.shape[1], -1, np.int64)
        self.parts: list[tuple[np.ndarray, np.ndarray]] = []  # (pixels (n, 2), coefficients (n, 3, r)) per call
        self.count, self.energy, self.kept = 0, 0.0, 0.0
        self._device_basis: torch.Tensor | None = None  # the basis on the footprints' device, for tensors

    def __call__(self, pixels: np.ndarray) -> np.ndarray | torch.Tensor:
        out = self.source(pixels)  # a model's tensor on its device is projected there and handed on as it is
        flat = pixels[:, 0].astype(np.int64) * self.shape[1] + pixels[:, 1]
        new = self.slot[flat] < 0
        if new.any():
            on_device = torch.is_tensor(out) and out.device.type != "cpu"  # (on the CPU NumPy's products are 3x faster)
            coef, energy, kept = (self._project_tensor if on_device else self._project)(out, new)
            self.energy, self.kept = self.energy + energy, self.kept + kept
            self.slot[flat[new]] = self.count + np.arange(len(coef))
            self.parts.append((pixels[new].astype(np.int64), coef))
            self.count += len(coef)
        return out

    def _project(self, out: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, float, float]:
        """The ``new`` rows' coefficients (n, 3, r) on the basis, and the squared energy of every
        :data:`RESIDUAL_STRIDE`-th one and of its projection (float64)."""
        out = footprint_array(out)
        fp = out if new.all() else out[new]
        if not np.isfinite(fp).all():  # (the splat zeroes them and warns: the coefficients do the same)
            fp = np.nan_to_num(fp, nan=0.0, posinf=0.0, neginf=0.0)
        n, k = len(fp), fp.shape[1]
        flat_fp = fp.reshape(n, k * k, 3)
        coef = np.stack([flat_fp[..., c] @ self.basis[c].reshape(-1, k * k).T for c in range(3)], axis=1)  # (n, 3, r)
        every = slice(None, None, RESIDUAL_STRIDE)  # the residual measured on a share of them, in float64
        energy = float(np.square(flat_fp[every], dtype=np.float64).sum())
        kept = float(np.square(coef[every], dtype=np.float64).sum())  # (orthonormal basis: |projection|^2)
        return coef.astype(np.float32, copy=False), energy, kept

    def _project_tensor(self, out: torch.Tensor, new: np.ndarray) -> tuple[np.ndarray, float, float]:
        """:meth:`_project` on the footprints' device (a GPU relight's footprints are not copied to the host; on the
        CPU, NumPy's strided products take a third of torch's time: 38 against 116 ms for 1,024 K = 90 footprints)."""
        fp = out.float() if new.all() else out.float()[torch.as_tensor(np.flatnonzero(new), device=out.device)]
        if not torch.isfinite(fp.sum()):
            fp = torch.nan_to_num(fp, nan=0.0, posinf=0.0, neginf=0.0)
        n, k = len(fp), fp.shape[1]
        if self._device_basis is None or self._device_basis.device != fp.device:  # (moved there once)
            self._device_basis = torch.as_tensor(self.basis, device=fp.device).reshape(3, -1, k * k)  # (3, r, K^2)
        basis = self._device_basis
        flat_fp = fp.reshape(n, k * k, 3)
        coef = torch.stack([flat_fp[..., c] @ basis[c].T for c in range(3)], dim=1)  # (n, 3, r)
        energy = float(flat_fp[::RESIDUAL_STRIDE].double().square().sum())
        kept = float(coef[::RESIDUAL_STRIDE].double().square().sum())
        return coef.cpu().numpy(), energy, kept

    def covers(self, pixels: np.ndarray) -> bool:
        """Whether every one of ``pixels`` (N, 2) went by (then any pattern can be relit from the taps)."""
        return bool((self.slot[pixels[:, 0].astype(np.int64) * self.shape[1] + pixels[:, 1]] >= 0).all())

    def result(self) -> LowRankFootprints:
        residual = 1.0 - self.kept / self.energy if self.energy > 0 else 0.0
        r = self.basis.shape[1]
        pixels = np.concatenate([p for p, _ in self.parts]) if self.parts else np.zeros((0, 2), np.int64)
        coef = np.concatenate([c for _, c in self.parts]) if self.parts else np.zeros((0, 3, r), np.float32)
        return LowRankFootprints(self.basis, pixels, coef, self.shape, max(residual, 0.0))


#: The eigen-footprint file's format. 2: its calibration weights are fitted on white-consistent images
#: (``calibration.exit_gain``) where the view records every colour; 3: that white is the nine-capture one
#: (``calibration.exit_white``); 4: a digest of its arrays, so a damaged or edited file is recomputed instead of
#: relighting wrong; 5: every view's weights are fitted on white-consistent images, a Bayer camera's too, and each
#: member's gain and the no-scattering term's white are kept (a new pattern needs neither computed again); 6: the
#: stretch of the calibration's twins (``relight_view``'s ``widen``, 0 for none) is kept, and the twins' weights and
#: gains beside their members' (their eigen-footprints are the members' :meth:`LowRankFootprints.mapped`); 7: with a
#: stretch, every model's footprints stretched along x, y and both; 8: only the first model's
#: (:func:`~sssphase_core.relight.engine.axis_stretches`), its own not among them, then the others' as they are; 9: the
#: first model's members are its footprints stretched along x, y and both and softened
#: (:func:`~sssphase_core.relight.engine.member_maps`). Files of earlier formats are not read.
LOWRANK_FORMAT = 9
#: More members than any blend has: a file claiming more is damaged (and is not looped over).
MAX_MEMBERS = 8


def _digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over ``arrays`` (name, dtype, shape and :func:`~sssphase_core.store.session.array_checksum` of each,
    in name order) but their ``digest``."""
    import hashlib

    from sssphase_core.store.session import array_checksum

    return hashlib.sha256("".join(f"{name}|{np.asarray(a).dtype.str}|{np.shape(a)}|{array_checksum(np.asarray(a))}\n"
                                  for name, a in sorted(arrays.items()) if name != "digest").encode()).hexdigest()


def save_lowrank(path: Path | str, members: list[LowRankFootprints], weights: np.ndarray, view_weights: np.ndarray,
                 gains: np.ndarray, white: np.ndarray, mask: np.ndarray, widen: float | None = None) -> None:
    """One view's fast relight: each member's eigen-footprints, the view calibration's weights (S, H, W, 3) (float16)
    and view-wide ones (S, 3), each member's white-consistent gain ``gains`` (S, H, W, 3) and the no-scattering
    term's white ``white`` (H, W, 3) (``calibration.exit_gain``, ``exit_white``; both kept at the view's ``mask``
    (H, W) pixels, where they differ from 1 and from the white capture), written atomically. With ``widen`` the
    calibration's S = len(members) + 3 members are the first member's (:func:`~sssphase_core.relight.engine.member_maps`:
    stretched ``widen`` x along x, y and both, softened), then the others."""
    from sssphase_core.store.files import atomic_path

    mask = np.asarray(mask, bool)
    arrays: dict[str, np.ndarray] = {"format": np.asarray(LOWRANK_FORMAT), "members": np.asarray(len(members)),
                                     "widen": np.asarray(float(widen or 0.0)),
                                     "weights": weights.astype(np.float16),
                                     "view_weights": np.asarray(view_weights, np.float32),
                                     "gains": np.asarray(gains, np.float32)[:, mask],
                                     "white": np.asarray(white, np.float32)[mask]}
    for i, m in enumerate(members):
        arrays.update(m.arrays(f"m{i}_"))
    arrays["digest"] = np.asarray(_digest(arrays))
    with atomic_path(Path(path), ".npz") as tmp:
        np.savez(tmp, **arrays)


def load_lowrank(path: Path | str, mask: np.ndarray, widen: float | None = None
                 ) -> tuple[list[LowRankFootprints], np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`save_lowrank`'s file for a view of decoded ``mask`` (H, W) -> (the calibration's S members (with
    ``widen``, the first member's calibration members, then the others), weights, view weights, gains (S, n, 3) and white (n, 3)
    at the mask's n pixels); None when it is missing, damaged, of another view, of another stretch or of another
    format (:data:`LOWRANK_FORMAT`; a cache only saves time)."""
    import zipfile

    path = Path(path)
    mask = np.asarray(mask, bool)
    shape, lit = mask.shape, int(mask.sum())
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != LOWRANK_FORMAT:
                return None
            arrays = {name: z[name] for name in z.files}
    except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile):
        return None
    try:
        if str(arrays["digest"]) != _digest(arrays):  # damaged or edited since it was written: recompute
            return None
        n, stretch = int(arrays["members"]), float(arrays["widen"])
        if not 1 <= n <= MAX_MEMBERS or stretch != float(widen or 0.0):
            return None
        members = [LowRankFootprints.from_arrays(arrays, f"m{i}_") for i in range(n)]
        if stretch and all(m is not None for m in members):
            members = [members[0].mapped(m) for m in member_maps(stretch)] + members[1:]  # type: ignore[union-attr]
            n = len(members)
        weights, view_weights = np.asarray(arrays["weights"], np.float32), np.asarray(arrays["view_weights"], np.float32)
        gains, white = np.asarray(arrays["gains"], np.float32), np.asarray(arrays["white"], np.float32)
    except (ValueError, KeyError, TypeError):
        return None
    if (any(m is None or m.shape != tuple(shape) for m in members) or weights.shape != (n, *shape, 3)
            or view_weights.shape != (n, 3) or gains.shape != (n, lit, 3) or white.shape != (lit, 3)
            or not (np.isfinite(weights).all() and np.isfinite(gains).all() and np.isfinite(white).all())):
        return None
    return members, weights, view_weights, gains, white  # type: ignore[return-value]
