"""Footprint decoder: sub-pixel upsampling stages with attention-gated skips from the frozen encoder."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sssphase_core.models.encoder import NEG_SLOPE, PreActBlock
from sssphase_core.models.presets import ModelPreset, get_preset


def icnr_(weight: torch.Tensor, scale: int = 2) -> torch.Tensor:
    """ICNR init (Aitken et al. 2017) of a conv feeding PixelShuffle(scale): no checkerboard at start."""
    c_out, *rest = weight.shape
    sub = torch.empty(c_out // scale**2, *rest)
    nn.init.kaiming_normal_(sub, a=NEG_SLOPE)
    with torch.no_grad():
        weight.copy_(sub.repeat_interleave(scale**2, dim=0))
    return weight


class AttentionGate(nn.Module):
    """Additive attention gate (Oktay et al. 2018): weights the skip by a map computed with the gating signal."""

    def __init__(self, c_gate: int, c_skip: int, c_inter: int) -> None:
        super().__init__()
        self.w_g = nn.Conv2d(c_gate, c_inter, 1, bias=False)
        self.w_x = nn.Conv2d(c_skip, c_inter, 1, bias=True)
        self.psi = nn.Conv2d(c_inter, 1, 1)

    def forward(self, gate: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return skip * torch.sigmoid(self.psi(F.relu(self.w_g(gate) + self.w_x(skip))))


class UpStage(nn.Module):
    """1x1 expand (ICNR) -> PixelShuffle(2) -> 3x3 smoothing -> gated skip concat -> pre-activation block."""

    def __init__(self, c_in: int, c_out: int, c_skip: int, c_att: int) -> None:
        super().__init__()
        self.expand = nn.Conv2d(c_in, 4 * c_out, 1, bias=False)
        icnr_(self.expand.weight)
        self.shuffle = nn.PixelShuffle(2)
        self.smooth = nn.Sequential(
            nn.Conv2d(c_out, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.LeakyReLU(NEG_SLOPE)
        )
        self.gate = AttentionGate(c_out, c_skip, c_att)
        self.block = PreActBlock(c_out + c_skip, c_out)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        up = self.smooth(self.shuffle(self.expand(x)))
        return self.block(torch.cat([up, self.gate(up, skip)], dim=1))


class Decoder(nn.Module):
    """Predicts a (B, 3, K, K) footprint from the encoder's bottleneck map and skips.

    Outputs are ``softplus(head) * out_scale``: footprints are light, never negative (a linear head
    drifted to negative footprints in short runs, which the log term cannot correct since it clamps
    predictions at 0), and ``out_scale`` (footprints peak near 0.04 in linear camera units) keeps the
    final 1x1 conv on O(1) values. Its bias starts at -4 (softplus = 0.018, i.e. ~1e-3 after
    scaling: the level of a footprint's tail, where most pixels are). ``n_classes`` > 0 adds the auxiliary
    material-classification head on the pooled embedding (``forward`` then returns (footprint, logits)).
    """

    def __init__(self, preset: ModelPreset | str, out_scale: float = 0.05, n_classes: int = 0) -> None:
        super().__init__()
        p = get_preset(preset)
        self.preset = p
        skips = (*reversed(p.stages), p.stem)
        chans = (p.bottleneck, *p.decoder)
        self.stages = nn.ModuleList(
            UpStage(chans[i], chans[i + 1], skips[i], max(p.attention, chans[i + 1] // 4)) for i in range(4)
        )
        self.head = nn.Sequential(nn.BatchNorm2d(p.decoder[-1]), nn.LeakyReLU(NEG_SLOPE), nn.Conv2d(p.decoder[-1], 3, 1))
        nn.init.constant_(self.head[-1].bias, -4.0)
        self.register_buffer("out_scale", torch.tensor(float(out_scale)))
        self.aux = nn.Linear(p.bottleneck, n_classes) if n_classes > 0 else None

    def forward(
        self, bottleneck: torch.Tensor, skips: list[torch.Tensor]
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        h = bottleneck
        for stage, skip in zip(self.stages, reversed(skips), strict=True):
            h = stage(h, skip)
        out = F.softplus(self.head(h)) * self.out_scale
        lo = (out.shape[-1] - self.preset.patch) // 2
        out = out[..., lo : lo + self.preset.patch, lo : lo + self.preset.patch]
        if self.aux is None:
            return out
        return out, self.aux(bottleneck.mean(dim=(2, 3)))
