"""SimSiam (Chen & He 2021): encoder + projector + predictor, symmetric negative cosine with stop-gradient."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sssphase_core.learning.models.encoder import Encoder
from sssphase_core.learning.models.presets import ModelPreset, get_preset


def _linear_bn(c_in: int, c_out: int, *, relu: bool = True, affine: bool = True) -> list[nn.Module]:
    layers: list[nn.Module] = [nn.Linear(c_in, c_out, bias=False), nn.BatchNorm1d(c_out, affine=affine)]
    return [*layers, nn.ReLU(inplace=True)] if relu else layers


class SimSiam(nn.Module):
    """Projector D->H->H->P (bias-free linear + BN, last BN without affine); predictor P->h->P."""

    def __init__(self, preset: ModelPreset | str) -> None:
        super().__init__()
        p = get_preset(preset)
        self.preset = p
        self.encoder = Encoder(p)
        self.projector = nn.Sequential(
            *_linear_bn(p.embed_dim, p.proj_hidden),
            *_linear_bn(p.proj_hidden, p.proj_hidden),
            *_linear_bn(p.proj_hidden, p.proj_dim, relu=False, affine=False),
        )
        self.predictor = nn.Sequential(*_linear_bn(p.proj_dim, p.pred_hidden), nn.Linear(p.pred_hidden, p.proj_dim))

    def forward(self, x1: torch.Tensor, x2: torch.Tensor) -> dict[str, torch.Tensor]:
        """Both views -> loss and the tensors the collapse monitor needs (embedding and projection of view 1)."""
        y1, y2 = self.encoder(x1), self.encoder(x2)
        z1, z2 = self.projector(y1), self.projector(y2)
        p1, p2 = self.predictor(z1), self.predictor(z2)
        loss = 0.5 * (simsiam_loss(p1, z2) + simsiam_loss(p2, z1))
        return {"loss": loss, "embedding": y1.detach(), "projection": z1.detach()}


def simsiam_loss(p: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """-cos(p, stopgrad(z)), averaged over the batch."""
    return -F.cosine_similarity(p, z.detach(), dim=-1).mean()
