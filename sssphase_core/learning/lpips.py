"""LPIPS (Zhang et al., CVPR 2018, "alex" variant, v0.1) from weights already on this machine.

Nothing is downloaded. Two weight files are needed:

- the AlexNet backbone as torchvision saves it, ``alexnet-owt-7be5be79.pth`` (torch hub cache:
  ``$TORCH_HOME/hub/checkpoints/``, default ``~/.cache/torch/hub/checkpoints/``);
- LPIPS's linear layers ``alex.pth`` (shipped inside the ``lpips`` package at ``lpips/weights/v0.1/``).

``$SSS_LPIPS_DIR`` may hold both instead. The network is written here in plain torch (torchvision is
not a dependency): AlexNet's five ReLU stages, LPIPS's input scaling, unit-normalised channels, the
learned 1x1 weights, spatial mean, sum over stages. Inputs are display-encoded RGB in [0, 1].
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sssphase_core.errors import InputError

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
LINEAR_FILE = "alex.pth"
CHANNELS = (64, 192, 384, 256, 256)
SHIFT = (-0.030, -0.088, -0.188)  # LPIPS's ScalingLayer, for inputs in [-1, 1]
SCALE = (0.458, 0.448, 0.450)


def _candidates() -> dict[str, list[Path]]:
    torch_home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    own = [Path(os.environ["SSS_LPIPS_DIR"])] if os.environ.get("SSS_LPIPS_DIR") else []
    spec = importlib.util.find_spec("lpips")  # the package's files, without importing it (it needs torchvision)
    package = [Path(p) / "weights" / "v0.1" for p in (spec.submodule_search_locations or [])] if spec else []
    return {ALEXNET_FILE: [*own, torch_home / "hub" / "checkpoints"], LINEAR_FILE: [*own, *package]}


def find_weights() -> tuple[Path, Path]:
    """(AlexNet backbone, LPIPS linear layers) on this machine; an InputError names what is missing and where
    it was looked for."""
    found, missing = {}, []
    for name, folders in _candidates().items():
        hit = next((f / name for f in folders if (f / name).is_file()), None)
        if hit is None:
            where = (f"looked in {', '.join(str(f) for f in folders)}" if folders else
                     "no folder to look in: the lpips package is not installed, and SSS_LPIPS_DIR is not set")
            missing.append(f"{name} ({where})")
        found[name] = hit
    if missing:
        raise InputError("LPIPS needs weights that are not on this machine: " + "; ".join(missing) +
                         ". Put both files in a folder named by $SSS_LPIPS_DIR (nothing is downloaded)")
    return found[ALEXNET_FILE], found[LINEAR_FILE]


def available() -> tuple[bool, str]:
    """Whether LPIPS can be computed here (its weights found and loaded), and if not, precisely why."""
    try:
        load()
    except InputError as exc:
        return False, str(exc)
    return True, ""


class LPIPS(nn.Module):
    """``forward(a, b)``: (B, 3, H, W) RGB in [0, 1] -> (B,) perceptual distance (0 for identical images)."""

    def __init__(self, alexnet: dict[str, torch.Tensor], linear: dict[str, torch.Tensor]) -> None:
        super().__init__()
        convs = [nn.Conv2d(3, 64, 11, 4, 2), nn.Conv2d(64, 192, 5, padding=2), nn.Conv2d(192, 384, 3, padding=1),
                 nn.Conv2d(384, 256, 3, padding=1), nn.Conv2d(256, 256, 3, padding=1)]
        for conv, index in zip(convs, (0, 3, 6, 8, 10), strict=True):  # torchvision's features.<index>
            conv.weight.data.copy_(alexnet[f"features.{index}.weight"])
            conv.bias.data.copy_(alexnet[f"features.{index}.bias"])
        self.convs = nn.ModuleList(convs)
        self.lins = nn.ParameterList([nn.Parameter(linear[f"lin{i}.model.1.weight"].reshape(1, c, 1, 1), requires_grad=False)
                                      for i, c in enumerate(CHANNELS)])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = ((2 * x - 1) - self.shift) / self.scale
        taps = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = nn.functional.max_pool2d(x, 3, 2)
            x = torch.relu(conv(x))
            taps.append(x)
        return taps

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(a.shape[0], device=a.device)
        for fa, fb, w in zip(self.features(a), self.features(b), self.lins, strict=True):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + ((na - nb).pow(2) * w).sum(1).mean(dim=(1, 2))
        return total


_MODEL: LPIPS | None = None
#: weight files found unusable, and why: :func:`available` asks once per scored image, and the files are not
#: read again
_UNUSABLE: dict[tuple[Path, Path], str] = {}


def load() -> LPIPS:
    """The LPIPS network from the local weights (loaded once per process)."""
    global _MODEL
    if _MODEL is None:
        alexnet, linear = find_weights()
        if (alexnet, linear) in _UNUSABLE:
            raise InputError(_UNUSABLE[alexnet, linear])
        try:
            _MODEL = LPIPS(torch.load(alexnet, map_location="cpu", weights_only=True),
                           torch.load(linear, map_location="cpu", weights_only=True))
        except (RuntimeError, KeyError, OSError, ValueError, TypeError, pickle.UnpicklingError, EOFError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            _UNUSABLE[alexnet, linear] = f"LPIPS weights {alexnet} / {linear} are not the expected files ({first})"
            raise InputError(_UNUSABLE[alexnet, linear]) from None
    return _MODEL


def lpips_distance(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """LPIPS between two linear (H, W, 3) images, both display-encoded with the reference's exposure
    (99.5th percentile on ``mask`` -> white, sRGB); pixels outside ``mask`` are set to black in both."""
    from sssphase_core.processing.colour import display_scale, srgb

    scale = display_scale(reference, mask)
    keep = np.ones(reference.shape[:2], bool) if mask is None else mask.astype(bool)
    tensors = [torch.as_tensor(srgb(np.nan_to_num(x) / scale) * keep[..., None], dtype=torch.float32).permute(2, 0, 1)[None]
               for x in (image, reference)]
    with torch.no_grad():
        return float(load()(*tensors)[0])


def lpips_footprints(pred: np.ndarray, target: np.ndarray, batch: int = 256) -> np.ndarray:
    """Per-footprint LPIPS of (N, K, K, 3) linear footprints, each pair shown with its GT peak as white (sRGB)."""
    from sssphase_core.processing.colour import srgb

    model = load()
    peak = np.maximum(np.nan_to_num(target).max(axis=(1, 2, 3), keepdims=True), 1e-12)
    out = []
    for start in range(0, len(target), batch):
        a, b = (torch.as_tensor(srgb(np.nan_to_num(x[start:start + batch]) / peak[start:start + batch]),
                                dtype=torch.float32).permute(0, 3, 1, 2) for x in (pred, target))
        with torch.no_grad():
            out.append(model(a, b).numpy())
    return np.concatenate(out) if out else np.zeros(0, np.float32)
