"""SimSiam (Chen & He 2021): encoder + projector + predictor, symmetric negative cosine with stop-gradient,
optionally with a decorrelation term against dimensional collapse (VICReg's covariance term)."""

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

    def forward(self, x1: torch.Tensor, x2: torch.Tensor, decorrelate: float = 0.0) -> dict[str, torch.Tensor]:
        """Both views -> loss and the tensors the collapse monitor needs (embedding and projection of view 1).

        ``decorrelate`` > 0 adds that weight times :func:`decorrelation_loss` of both views' projections (the
        term itself is returned as ``decorrelation``)."""
        y1, y2 = self.encoder(x1), self.encoder(x2)
        z1, z2 = self.projector(y1), self.projector(y2)
        p1, p2 = self.predictor(z1), self.predictor(z2)
        loss = 0.5 * (simsiam_loss(p1, z2) + simsiam_loss(p2, z1))
        out = {"embedding": y1.detach(), "projection": z1.detach()}
        if decorrelate > 0:
            out["decorrelation"] = 0.5 * (decorrelation_loss(z1) + decorrelation_loss(z2))
            loss = loss + decorrelate * out["decorrelation"]
        return {"loss": loss, **out}


def simsiam_loss(p: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """-cos(p, stopgrad(z)), averaged over the batch."""
    return -F.cosine_similarity(p, z.detach(), dim=-1).mean()


def decorrelation_loss(x: torch.Tensor) -> torch.Tensor:
    """Mean squared off-diagonal correlation between the D features of a (B, D) batch: 0 when they are
    uncorrelated, 1 when all move together (dimensional collapse). VICReg's covariance term (Bardes et al.
    2022) on standardised features, so that it does not depend on their scale; () scalar."""
    x = x.float()
    x = (x - x.mean(dim=0)) / x.std(dim=0).clamp_min(1e-4)
    c = (x.T @ x) / max(1, len(x) - 1)
    off = c - torch.diag(torch.diagonal(c))
    return off.pow(2).sum() / (c.shape[0] * (c.shape[0] - 1))
