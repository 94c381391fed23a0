"""PSP patch encoder: stem, three PixelUnshuffle + pre-activation residual stages, bottleneck, GAP."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sssphase_core.learning.models.presets import ModelPreset, get_preset

NEG_SLOPE = 0.1
#: added to a patch's mean level before dividing by it (camera units, a white reference reads 1): a patch of
#: almost no light is left almost as dark as it is instead of having its noise raised to the level of a lit one
LEVEL_FLOOR = 1e-3


def patch_level(x: torch.Tensor) -> torch.Tensor:
    """(B, C, K, K) patches -> (B, 1, 1, 1): each patch's mean over its channels and pixels (clipped at 0) plus
    :data:`LEVEL_FLOOR`. A PSP patch lit by s times the light is s times the patch, so ``x / patch_level(x)`` does
    not change with exposure, projector power or the object's distance."""
    return x.float().mean(dim=(1, 2, 3), keepdim=True).clamp_min(0) + LEVEL_FLOOR


class PreActBlock(nn.Module):
    """Pre-activation residual block (He et al. 2016): BN-LReLU-conv3x3 twice, 1x1 projection shortcut."""

    def __init__(self, c_in: int, c_out: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.bn1 = nn.BatchNorm2d(c_in)
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.drop = nn.Dropout2d(dropout) if dropout > 0 else nn.Identity()
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.shortcut = nn.Identity() if c_in == c_out else nn.Conv2d(c_in, c_out, 1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.leaky_relu(self.bn1(x), NEG_SLOPE)
        out = self.conv2(self.drop(F.leaky_relu(self.bn2(self.conv1(h)), NEG_SLOPE)))
        return out + (x if isinstance(self.shortcut, nn.Identity) else self.shortcut(h))


class Encoder(nn.Module):
    """Maps a (B, 24, K, K) PSP patch to a (B, D) embedding; ``features`` also returns the skips.

    With ``preset.scale_invariant`` the patch is first divided by its :func:`patch_level`. It is zero-padded to
    ``preset.padded`` (paper: 90 -> 96), then:
    stem conv3x3 + BN + LeakyReLU(0.1) at full size; three stages of PixelUnshuffle(2) and a
    pre-activation block (paper: 512->256 @48, 1024->384 @24, 1536->512 @12); max-pool by 2;
    a bottleneck block with dropout (512->1024 @6); global average pooling.
    """

    def __init__(self, preset: ModelPreset | str) -> None:
        super().__init__()
        p = get_preset(preset)
        self.preset = p
        self.stem = nn.Sequential(
            nn.Conv2d(p.in_channels, p.stem, 3, padding=1, bias=False),
            nn.BatchNorm2d(p.stem),
            nn.LeakyReLU(NEG_SLOPE),
        )
        chans = (p.stem, *p.stages)
        self.stages = nn.ModuleList(
            nn.Sequential(nn.PixelUnshuffle(2), PreActBlock(4 * chans[i], chans[i + 1])) for i in range(3)
        )
        self.bottleneck = PreActBlock(p.stages[-1], p.bottleneck, dropout=p.dropout)
        self.out_bn = nn.BatchNorm2d(p.bottleneck)

    def pad(self, x: torch.Tensor) -> torch.Tensor:
        extra = self.preset.padded - x.shape[-1]
        lo = extra // 2
        return F.pad(x, (lo, extra - lo, lo, extra - lo)) if extra else x

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """(bottleneck map (B, D, P/16, P/16), skips [stem @P, stage1 @P/2, stage2 @P/4, stage3 @P/8])."""
        if self.preset.scale_invariant:
            x = x / patch_level(x).to(x.dtype)
        h = self.stem(self.pad(x))
        skips = [h]
        for stage in self.stages:
            h = stage(h)
            skips.append(h)
        h = self.bottleneck(F.max_pool2d(h, 2))
        return F.leaky_relu(self.out_bn(h), NEG_SLOPE), skips

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)[0].mean(dim=(2, 3))
