"""Physics read straight from a PSP patch, for the decoder's reciprocal head.

A fringe image is the emitted sinusoid convolved with the footprints, so at the centre pixel:

* the offset A (mean of the 4 shifts) is (black + (1 - black) / 2) x the pixel's white value,
  which by reciprocity is its footprint's energy (:func:`white_from_psp`);
* the modulation ratio B / A, per orientation and colour, is the footprint's MTF at the local fringe
  wave vector k (times the projector/camera system MTF), and k itself is the phase step between
  neighbouring pixels (:func:`modulation_features`).

These are brightness-free, so a profile predicted from them carries over to materials the decoder
never saw, where features that also see colour and brightness latch on to the training materials.
"""

from __future__ import annotations

import math

import torch
from torch import nn

N_SHIFTS = 4
#: Knots (px from the centre) of the radial log-profile: dense near the centre, where relighting is decided.
KNOTS = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 11.0, 16.0, 23.0, 32.0, 45.0, 64.0)
MOD_FLOOR = 1e-3
N_FEATURES = 13  # per colour: own log-modulation (2), k^2 (4), light share (1), all colours' (6)
SUPPORT_FRAC = 0.03  # a neighbour is off the surface when its offset is below 3% of the centre's


def _offsets(patch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(dy, dx) float (K, K) maps of pixel offsets from the patch centre K // 2."""
    d = (torch.arange(patch) - patch // 2).float()
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    return dy.clone(), dx.clone()  # meshgrid views: a buffer must own its memory


def _split(psp: torch.Tensor) -> torch.Tensor:
    """(B, 24, K, K) -> (B, orientation 2, shift 4, colour 3, K, K), float32."""
    b, _, k, _ = psp.shape
    return psp.float().reshape(b, 2, N_SHIFTS, 3, k, k)


def white_from_psp(psp: torch.Tensor) -> torch.Tensor:
    """(B, 24, K, K) -> (B, 3): 2 A at the centre pixel (the white value for black level 0)."""
    k = psp.shape[-1]
    return 2.0 * _split(psp)[..., k // 2, k // 2].mean(dim=(1, 2))


def surface_support(psp: torch.Tensor, frac: float = SUPPORT_FRAC) -> torch.Tensor:
    """(B, 24, K, K) -> (B, 1, K, K) bool: pixels whose offset A (all colours) exceeds ``frac`` of the
    centre's, i.e. the lit surface around the pixel. Footprint light exits on the surface only, and
    white (the footprint's energy, by reciprocity) counts only that light."""
    a = _split(psp).mean(dim=(1, 2)).sum(dim=1, keepdim=True)  # (B, 1, K, K)
    k = psp.shape[-1]
    return a > frac * a[..., k // 2 : k // 2 + 1, k // 2 : k // 2 + 1].clamp_min(1e-6)


def modulation_features(psp: torch.Tensor, window: int = 2, smooth: int = 2, even: bool = True) -> torch.Tensor:
    """(B, 24, K, K) -> (B, 3, N_FEATURES) per colour: log(B/A) for the x and y fringes (amplitude
    and offset averaged over the (2 smooth + 2)^2 window around the centre), then the squared
    components (k_x^2, k_y^2) of both fringes' wave vectors (rad/px, measured in a
    (2 window + 1)^2 neighbourhood on all colours), the log of the colour's share of the light,
    and all three colours' log-modulations.

    The amplitude window has an even side so that it holds each of the four Bayer sites equally often
    wherever it lies: a colour's modulation is its own sample's at its sites and demosaicing's
    interpolation elsewhere, and an odd window counted them by the centre pixel's Bayer position,
    which the profile then followed (measured on the demo's crab with a 5 x 5 window: predicted
    red centre shares 0.80 at red sites, 0.66 at blue ones; exact 0.74 at both). ``even=False``: the
    (2 smooth + 1)^2 window of decoders trained before that change (their checkpoints run as trained)."""
    x = _split(psp)
    k = x.shape[-1]
    c = k // 2
    cos_s, sin_s = x[:, :, 0] - x[:, :, 2], x[:, :, 1] - x[:, :, 3]  # (B, 2, 3, K, K): 2 B cos, 2 B sin
    near = slice(max(c - smooth - int(even), 0), c + smooth + 1)  # B and A averaged over an even window: less noise
    offset = x[..., near, near].mean(dim=(2, -2, -1))  # (B, 2, 3)
    amp = 0.5 * torch.sqrt(cos_s[..., near, near] ** 2 + sin_s[..., near, near] ** 2).mean(dim=(-2, -1))
    log_mod = torch.log((amp / offset.abs().clamp_min(1e-6)).clamp(MOD_FLOOR, 2.0))
    lo, hi = c - window, c + window + 1
    zc, zs = cos_s.sum(dim=2)[..., lo:hi, lo:hi], sin_s.sum(dim=2)[..., lo:hi, lo:hi]  # (B, 2, w, w)

    def step(dim: int) -> torch.Tensor:
        n = zc.shape[dim]
        c1, c0 = zc.narrow(dim, 1, n - 1), zc.narrow(dim, 0, n - 1)
        s1, s0 = zs.narrow(dim, 1, n - 1), zs.narrow(dim, 0, n - 1)
        re = (c1 * c0 + s1 * s0).sum(dim=(-2, -1))
        im = (s1 * c0 - c1 * s0).sum(dim=(-2, -1))
        return torch.atan2(im, re)  # (B, 2)

    k2 = torch.stack([step(-1), step(-2)], dim=-1) ** 2  # (B, orientation, axis)
    k2 = k2.flatten(1)[:, None, :].expand(-1, 3, -1)
    own = log_mod.transpose(1, 2)  # (B, 3, 2)
    # Demosaicing leaks the bright colours' fringes into a dim one: give each colour the others'
    # modulation and its share of the light, so the leak can be told from a narrow footprint.
    colour = offset.mean(dim=1).clamp_min(1e-6)  # (B, 3)
    share = torch.log(colour / colour.sum(dim=1, keepdim=True))[..., None]
    every = own.flatten(1)[:, None, :].expand(-1, 3, -1)
    return torch.cat([own, k2, share, every], dim=-1)


class RadialProfile(nn.Module):
    """Per-colour log-profile over the K x K window from the modulation features.

    One MLP shared by the three colours (plus a colour one-hot) maps a colour's features to the
    values of a piecewise-linear log-profile at :data:`KNOTS` and a log-stretch (s_x, s_y) of the
    radius (anisotropy). Its last layer starts at zero: the profile then adds nothing.
    """

    def __init__(self, patch: int, hidden: int = 64) -> None:
        super().__init__()
        knots = [kn for kn in KNOTS if kn <= patch] + ([float(patch)] if patch > KNOTS[-1] else [])
        self.register_buffer("knots", torch.tensor(knots))
        self.reach = float(knots[-1])  # the last knot as a number: reading the buffer would wait on a GPU each step
        dy, dx = _offsets(patch)
        self.register_buffer("dy", dy)
        self.register_buffer("dx", dx)
        self.mlp = nn.Sequential(nn.Linear(N_FEATURES + 3, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
                                 nn.Linear(hidden, len(knots) + 2))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, 3, N_FEATURES) -> (B, 3, K, K) log-profile."""
        b = features.shape[0]
        onehot = torch.eye(3, device=features.device).expand(b, -1, -1)
        out = self.mlp(torch.cat([features, onehot], dim=-1))  # (B, 3, J + 2)
        values, stretch = out[..., :-2], out[..., -2:].clamp(-3.0, 3.0)
        sx, sy = torch.exp(stretch[..., 0])[..., None, None], torch.exp(stretch[..., 1])[..., None, None]
        r2 = (self.dx / sx) ** 2 + (self.dy / sy) ** 2  # sqrt has an infinite slope at the centre
        r = torch.sqrt(r2.clamp_min(1e-12)).clamp_max(self.reach)  # (B, 3, K, K)
        j = (torch.searchsorted(self.knots, r.flatten(2).contiguous(), right=True) - 1).clamp(0, len(self.knots) - 2)
        j = j.view(r.shape)
        k0, k1 = self.knots[j], self.knots[j + 1]
        t = (r - k0) / (k1 - k0)
        v0 = torch.gather(values, 2, j.flatten(2)).view(r.shape)
        v1 = torch.gather(values, 2, (j + 1).flatten(2)).view(r.shape)
        return v0 + t * (v1 - v0)


class RingAverage(nn.Module):
    """Removes each ring's mean (rings of integer radius around the centre) from a (B, C, K, K) map,
    so that what remains cannot change a radial profile, only its angular detail.

    The ring means are one (K*K, R) product (R ~ 0.7 K rings) gathered back to the pixels: a (K*K, K*K)
    averaging matrix cost 45x the multiply-adds at K = 32 and 130x at K = 90 (65M per colour, a 262 MB
    buffer); checkpoints that still hold that matrix load, and it is dropped."""

    def __init__(self, patch: int) -> None:
        super().__init__()
        dy, dx = _offsets(patch)
        ring = torch.sqrt(dy**2 + dx**2).round().long().flatten()
        rings = round(math.sqrt(2) * (patch // 2)) + 1  # the corner's ring and those inside (no read of `ring`: a
        member = torch.nn.functional.one_hot(ring, rings).float()  # (K*K, R)  model on the meta device builds too)
        self.register_buffer("ring", ring, persistent=False)  # (K*K,) each pixel's ring
        self.register_buffer("weights", member / member.sum(0), persistent=False)  # (K*K, R): a column averages a ring

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(2)  # (B, C, K*K)
        return (flat - (flat @ self.weights)[..., self.ring]).view(x.shape)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object, **kwargs: object) -> None:
        state_dict.pop(prefix + "average", None)  # the averaging matrix older checkpoints hold (derived from K)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
