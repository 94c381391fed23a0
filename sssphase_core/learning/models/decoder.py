"""Footprint decoder: sub-pixel upsampling stages with attention-gated skips from the frozen encoder."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sssphase_core.errors import InputError
from sssphase_core.learning.inputs import DECODER_HEADS
from sssphase_core.learning.models.encoder import NEG_SLOPE, PreActBlock, patch_level
from sssphase_core.learning.models.physics import (
    RadialProfile,
    RingAverage,
    modulation_features,
    surface_support,
    white_from_psp,
)
from sssphase_core.learning.models.presets import ModelPreset, get_preset


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


OFF_SURFACE = -30.0  # log-shape off the lit surface (e^-30: nothing, yet finite gradients)


class Decoder(nn.Module):
    """Predicts a (B, 3, K, K) footprint from the encoder's bottleneck map and skips.

    Two heads on the same 1x1 conv:

    * ``reciprocal`` (default): footprint = energy * shape. The shape is a softmax over the K x K
      window per colour (non-negative, sums to 1) of three log-terms: a learned prior map
      (initialised to the training footprints' mean shape, :meth:`init_shape_prior`), a radial
      profile predicted from the centre pixel's modulation ratios and fringe frequencies
      (:class:`~sssphase_core.learning.models.physics.RadialProfile`), and the conv output less its ring
      means (the decoder's angular detail: anisotropy, edges; zero at start), restricted to the lit
      surface in the patch (:func:`~sssphase_core.learning.models.physics.surface_support`). The conv may not
      set the radial profile: trained on a handful of materials it keys on their colour and gives
      unseen ones the wrong width (measured: a near-delta footprint for the sand rake). The energy
      is the pixel's white value read from its own PSP patch
      (:func:`~sssphase_core.learning.models.physics.white_from_psp`) times a learned per-colour factor.
      Energy is what relighting needs most and the SBH terms constrain least (they are relative:
      log, peak-normalised SSIM, normalised gradients), so it comes from physics, and the profile
      comes from brightness-free features, so it carries over to unseen materials (measured in
      the docs' learning and relighting pages).
    * ``direct`` (the paper's): ``softplus(conv) * out_scale``; ``out_scale`` (footprints peak near
      0.04 in linear camera units) keeps the conv on O(1) values, bias -4 starts at ~1e-3 (a tail). Behind a
      ``scale_invariant`` encoder it is also multiplied by the patch's level, so that s times the light gives s
      times the footprint.

    ``n_classes`` > 0 adds the auxiliary material-classification head on the pooled embedding
    (``forward`` then returns (footprint, logits)).
    """

    def __init__(self, preset: ModelPreset | str, out_scale: float = 0.05, n_classes: int = 0,
                 head: str = "reciprocal") -> None:
        super().__init__()
        if head not in DECODER_HEADS:
            raise InputError(f"unknown decoder head {head!r}; choose one of {', '.join(DECODER_HEADS)}")
        p = get_preset(preset)
        self.preset, self.head_kind = p, head
        skips = (*reversed(p.stages), p.stem)
        chans = (p.bottleneck, *p.decoder)
        self.stages = nn.ModuleList(
            UpStage(chans[i], chans[i + 1], skips[i], max(p.attention, chans[i + 1] // 4)) for i in range(4)
        )
        self.head = nn.Sequential(nn.BatchNorm2d(p.decoder[-1]), nn.LeakyReLU(NEG_SLOPE), nn.Conv2d(p.decoder[-1], 3, 1))
        nn.init.constant_(self.head[-1].bias, -4.0 if head == "direct" else 0.0)
        self.register_buffer("out_scale", torch.tensor(float(out_scale)))
        if head == "reciprocal":
            nn.init.zeros_(self.head[-1].weight)
            self.shape_prior = nn.Parameter(torch.zeros(3, p.patch, p.patch))
            self.profile = RadialProfile(p.patch)
            self.angular = RingAverage(p.patch)
            self.log_gain = nn.Parameter(torch.zeros(3))
        #: the profile's modulation window has an even side (False: a decoder trained before, as trained)
        self.even_window = True
        self.aux = nn.Linear(p.bottleneck, n_classes) if n_classes > 0 else None

    def physics_parameters(self) -> list[nn.Parameter]:
        """The reciprocal head's few physics-side parameters that train (profile MLP, prior map, and the
        per-colour gain unless :meth:`freeze_gain`)."""
        if self.head_kind != "reciprocal":
            return []
        return [q for q in (*self.profile.parameters(), self.shape_prior, self.log_gain) if q.requires_grad]

    def freeze_gain(self) -> None:
        """Keep the energy gain at its value (1 for a new head): the energy is then the reciprocity white
        value read from the PSP patch. Learned from captured dot crops, whose sharp footprints carry
        demosaicing lobes (a centre above the crop's total energy) and a noise floor, the SBH terms set
        it 0.5-2.2x off per colour and relit an unseen soap at 15-17 dB (below no scattering, 23.4 dB);
        with the gain fixed, 33.8 dB."""
        if self.head_kind == "reciprocal":
            self.log_gain.requires_grad_(False)

    @torch.no_grad()
    def init_shape_prior(self, footprints: torch.Tensor, *, demosaiced: bool = False, floor: float = 1e-7) -> None:
        """Set the log-prior map to the mean per-channel-normalised shape of (N, 3, K, K) footprints.

        Crops of a camera that measures every colour (a three-chip camera, rendered or imported frames) are
        linear in the light: their zero-mean noise averages out of the mean, which is taken before clipping.
        The mean of clipped crops keeps the noise's positive half as a tail (on Mitsuba renders half of the
        prior's energy beyond 3 px where the crops hold 11 %), and the head's SBH loss, led by its gradient
        term, hardly moves a flat pedestal: decoders kept much of it (lab workflow: 0.2-0.8 dB of relighting on
        two of three unseen objects). ``demosaiced`` crops (a Bayer camera's) ring around sharp light: their
        mean has negative lobes near the centre, which as a log-prior would be holes, so each crop is clipped
        before the mean there, as before."""
        if self.head_kind != "reciprocal":
            return
        fp = footprints.float()
        if demosaiced:
            fp = fp.clamp_min(0)
            shape = (fp / fp.sum(dim=(2, 3), keepdim=True).clamp_min(1e-12)).mean(dim=0)
        else:
            energy = fp.sum(dim=(2, 3), keepdim=True)
            lit = (energy > 0).flatten(1).all(dim=1)  # a crop with no light in a colour has no shape
            shape = (fp[lit] / energy[lit]).mean(dim=0) if bool(lit.any()) else torch.zeros_like(fp[0])
        self.shape_prior.copy_(torch.log(shape.clamp_min(0) + floor))

    def forward(
        self, bottleneck: torch.Tensor, skips: list[torch.Tensor], psp: torch.Tensor | None = None
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        h = bottleneck
        for stage, skip in zip(self.stages, reversed(skips), strict=True):
            h = stage(h, skip)
        k = self.preset.patch
        lo = (h.shape[-1] - k) // 2
        raw = self.head(h)[..., lo : lo + k, lo : lo + k]
        pooled = bottleneck.mean(dim=(2, 3))
        if self.head_kind == "direct":
            out = F.softplus(raw) * self.out_scale
            if self.preset.scale_invariant:  # the encoder saw the patch at unit level: give the footprint its level
                if psp is None:
                    raise InputError("a scale-invariant encoder's direct head needs the PSP patches (their level)")
                out = out * patch_level(psp).to(out.dtype)
        else:
            if psp is None:
                raise InputError("the reciprocal decoder head needs the PSP patches (its energy comes from them)")
            detail = self.angular(raw.float())  # the conv adds angular detail, never a radial profile
            logits = detail + self.shape_prior + self.profile(modulation_features(psp, even=self.even_window))
            logits = logits.masked_fill(~surface_support(psp), OFF_SURFACE)  # light exits on the surface only
            shape = torch.softmax(logits.flatten(2), dim=-1).view(raw.shape)
            energy = white_from_psp(psp).clamp_min(0) * torch.exp(self.log_gain.clamp(-3.0, 3.0))
            out = shape * energy[:, :, None, None]
        if self.aux is None:
            return out
        return out, self.aux(pooled)
