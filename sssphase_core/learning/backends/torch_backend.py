"""The paper's method as a backend: SimSiam-pretrained encoder + SBH-trained decoder (torch)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from sssphase_core.compute import compute_device, inference_precision
from sssphase_core.errors import InputError
from sssphase_core.learning.backends.base import Query, as_patches, centre_window
from sssphase_core.learning.data import PatchDataset, ViewData
from sssphase_core.learning.domain import WidthDomain, beyond, cuts_tail, pixel_widths, with_physics_tail
from sssphase_core.learning.models import ModelPreset, get_preset
from sssphase_core.learning.training import (
    DecoderConfig,
    FootprintNet,
    PretrainConfig,
    decoder_modules,
    load_checkpoint,
    pretrain,
    resolve_checkpoint,
    train_decoder,
)


class TorchBackend:
    """``checkpoint``: a decoder checkpoint (``sss train decoder``) used by ``predict_footprints``.

    Pixels whose footprint is wider than any the decoder was trained on (:mod:`sssphase_core.learning.domain`,
    recorded in the checkpoint) get the analytic model's footprints (with projector ``black`` level), and the
    others the analytic model's tail beyond the radius the training crops held light to (where the checkpoint
    records it), unless ``guard`` is False; ``beyond_domain`` / ``predicted`` count the former and all pixels
    predicted so far. ``precision`` (``auto``, ``fp32``, ``bf16``): the decoder's inference under bf16 autocast, or not;
    ``auto`` is bf16 where the device computes it natively (:func:`~sssphase_core.compute.inference_precision`), as the
    decoder trains on a GPU; ``self.precision`` is the one used."""

    name = "torch"
    #: ``predict_footprints`` takes (N, 24, K, K) tensors on its device too: the relight crops them there from the
    #: view's stack (:func:`~sssphase_core.relight.sources.backend_source`), not on the host.
    accepts_tensors = True

    def __init__(self, checkpoint: Path | str | None = None, *, device: str = "cpu", batch_size: int = 128,
                 black: float = 0.002, guard: bool = True, precision: str = "auto") -> None:
        self.device, self.batch_size = compute_device(device), batch_size
        self.precision = inference_precision(self.device, precision)
        self.black, self.guard = float(black), bool(guard)
        self.checkpoint: Path | None = None
        self.encoder = self.decoder = None
        self.domain: WidthDomain | None = None
        self.patch = 0
        self.beyond_domain = self.predicted = 0
        self.tail_applied: tuple[int, int, int] | None = None  # the tail radii once a footprint took them
        if checkpoint is not None:
            self.load(checkpoint)

    def load(self, checkpoint: Path | str) -> None:
        self.checkpoint = resolve_checkpoint(checkpoint)  # a run folder: its best.pt when it has one
        ckpt = load_checkpoint(self.checkpoint)
        self.encoder, self.decoder = decoder_modules(ckpt, self.checkpoint)
        self.encoder.to(self.device)
        self.decoder.to(self.device)
        self.patch = self.encoder.preset.patch
        self.domain = WidthDomain.from_dict(ckpt.get("domain"))

    def pretrain(self, views: Sequence[ViewData], out_dir: Path, *, config: PretrainConfig | None = None,
                 preset: ModelPreset | None = None, **options: object) -> Path:
        """SimSiam pretraining (``preset`` overrides ``config.preset``); returns the checkpoint path."""
        cfg = config or PretrainConfig()
        p = preset or get_preset(cfg.preset)
        ds = PatchDataset(views, p.patch, sorted({v.object for v in views}))
        return pretrain(cfg, ds, out_dir, preset=p, **options)

    def fit(self, views: Sequence[ViewData], out_dir: Path, *, encoder: Path | str | None, config: DecoderConfig | None = None,
            val_views: Sequence[ViewData] | None = None, **options: object) -> Path:
        """Train the decoder on a frozen pretrained ``encoder`` checkpoint, then load the result.

        ``encoder=None`` trains encoder and decoder end-to-end (the U-Net baseline, ``config.preset``).
        """
        from sssphase_core.learning.training import decoder_patch

        config = config or DecoderConfig()
        patch = decoder_patch(encoder, config.preset)
        classes = sorted({v.object for v in [*views, *(val_views or [])]})
        ds = PatchDataset(views, patch, classes, with_targets=True)
        val = PatchDataset(val_views, patch, classes, with_targets=True) if val_views else None
        path = train_decoder(config, encoder, ds, out_dir, val=val, **options)
        self.load(path)
        return path

    @torch.no_grad()
    def predict_footprints(self, query: Query | torch.Tensor) -> np.ndarray | torch.Tensor:
        """(N, K, K, 3) float32 footprints: NumPy for a ``(psp, pixels)`` query or NumPy patches, a tensor on the
        backend's device for tensor patches (the relight's: the footprints, the analytic model's beyond the domain
        and its tail included, stay on the device)."""
        if self.decoder is None:
            raise InputError("the torch backend has no decoder checkpoint: pass checkpoint=... or call fit()")
        as_tensor = torch.is_tensor(query)
        patches = _tensor_patches(query) if as_tensor else as_patches(query, self.patch)
        far = np.zeros(len(patches), bool)
        guarded = self.guard and self.domain is not None and len(patches)
        if guarded:
            est = pixel_widths(centre_window(patches, GUARD_WINDOW), self.patch, self.black)
            far = beyond(self.domain, est["widths"])
        out = torch.zeros((len(patches), self.patch, self.patch, 3), dtype=torch.float32, device=self.device)
        near = np.flatnonzero(~far)
        every = len(near) == len(patches)  # (the usual case: slices, no index copies)
        for i in range(0, len(near), self.batch_size):
            rows = slice(i, i + self.batch_size) if every else torch.as_tensor(near[i : i + self.batch_size], device=self.device)
            if every:
                batch = patches[rows]
            elif torch.is_tensor(patches):
                batch = patches.index_select(0, rows.to(patches.device))
            else:
                batch = patches[near[i : i + self.batch_size]]
            x = torch.as_tensor(batch, device=self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
                pred, _ = FootprintNet(self.encoder, self.decoder)(x)
            out[rows] = pred.float().permute(0, 2, 3, 1)
        tail = self.domain.tail_radius if guarded else None  # type: ignore[union-attr]
        tail = tail if tail is not None and cuts_tail(tail, self.patch) and len(near) else None
        if far.any() or tail is not None:
            # beyond what the decoder learned: the physics, which reads the width at any scale, rendered on the device
            from sssphase_core.learning.backends.analytic_backend import render_footprints

            energy = torch.as_tensor(est["energy"], dtype=torch.float32, device=self.device)
            axes = torch.as_tensor(est["axes"], dtype=torch.float32, device=self.device)
            cut = torch.as_tensor(np.flatnonzero(far), device=self.device)
            out[cut] = render_footprints(energy[cut], axes[cut], self.patch)
            if tail is not None:
                rows = torch.as_tensor(near, device=self.device)
                out[rows] = with_physics_tail(out[rows], render_footprints(energy[rows], axes[rows], self.patch), tail)  # type: ignore[assignment]
                self.tail_applied = tail
        self.beyond_domain += int(far.sum())
        self.predicted += len(patches)
        return out if as_tensor else out.cpu().numpy()


#: The window around each pixel the guard's width estimate reads (the analytic model's, 5 x 5).
GUARD_WINDOW = 5


def _tensor_patches(query: torch.Tensor) -> torch.Tensor:
    """A tensor query: (N, 24, K, K) float32 patches on any device, as they are."""
    if query.ndim != 4 or query.shape[1] != 24 or query.shape[2] != query.shape[3]:
        raise InputError(f"PSP patches must be (N, 24, K, K), got {tuple(query.shape)}")
    return query.float()
