"""The Self-Balanced Hybrid (SBH) footprint loss of the paper, with numerically sound choices.

L = 1 L1 + 1 L_log + 0.5 L_SSIM + 10 L_grad + 5 L_wMSE on (B, 3, K, K) footprints in linear camera
units (peaks ~0.04). Every term is evaluated in float32 whatever the input dtype (float16 inputs
would underflow in the squared terms and in SSIM's variances). Choices, all in camera units:

* ``L_log``: mean |log1p(relu(P)/e) - log1p(relu(Y)/e)| with e = ``LOG_EPS`` = 1e-4 (1/400 of a
  0.04 peak, about the sensor noise floor). ``log1p(x/e) = log(x + e) - log(e)``, so this is the
  paper's L1 on log data, offset so that zero is finite. Negative noisy targets and negative
  predictions are clamped at 0 (the L1 term still pulls negative predictions up).
* ``L_SSIM``: 1 - SSIM (11x11 Gaussian window, sigma 1.5) after dividing prediction and target by the
  target's per-sample peak (at least ``PEAK_FLOOR`` = 1e-3), i.e. SSIM with data range = the
  footprint's own peak, so C1, C2 scale with the footprint; with the authors' data range 1 the
  constants (1e-4, 9e-4) would exceed the footprint variances (~1e-5) and SSIM would be blind.
* ``L_grad``: L1 between forward differences (x and y) of P and Y, each channel divided by that
  channel's mean |grad Y| over the batch plus ``GRAD_EPS`` = 1e-5 (typical mean gradients are
  1e-4-1e-3), so a dim channel counts as much as a bright one (no colour-scale collapse).
* ``L_wMSE``: mean(w (P - Y)^2), w = 1 + var_b(Y) / (mean var_b(Y) + ``VAR_EPS``), the variance over
  the batch per channel and pixel (population variance, so a batch of 1 gives w = 1),
  ``VAR_EPS`` = 1e-12 (footprint variances are ~1e-8-1e-4); weights carry no gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.metrics import ssim as kornia_ssim

LOG_EPS = 1e-4
PEAK_FLOOR = 1e-3
GRAD_EPS = 1e-5
VAR_EPS = 1e-12
SSIM_WINDOW = 11


@dataclass(frozen=True)
class SBHWeights:
    l1: float = 1.0
    log: float = 1.0
    ssim: float = 0.5
    grad: float = 10.0
    wmse: float = 5.0


def l1_term(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean()


def log_term(pred: torch.Tensor, target: torch.Tensor, eps: float = LOG_EPS) -> torch.Tensor:
    return (torch.log1p(pred.clamp_min(0) / eps) - torch.log1p(target.clamp_min(0) / eps)).abs().mean()


def peak_normalise(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Divide both by the target's per-sample peak (floored), so data range 1 means 'the peak'."""
    peak = target.amax(dim=(1, 2, 3), keepdim=True).clamp_min(PEAK_FLOOR)
    return pred / peak, target / peak


def ssim_map(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM with data range = each target footprint's peak."""
    p, t = peak_normalise(pred, target)
    return kornia_ssim(p, t, SSIM_WINDOW, max_val=1.0)


def ssim_term(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return 1.0 - ssim_map(pred, target).mean()


def _diffs(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def grad_term(pred: torch.Tensor, target: torch.Tensor, eps: float = GRAD_EPS) -> torch.Tensor:
    (pdx, pdy), (tdx, tdy) = _diffs(pred), _diffs(target)
    norm = 0.5 * (tdx.abs().mean(dim=(0, 2, 3)) + tdy.abs().mean(dim=(0, 2, 3))) + eps
    norm = norm.view(1, -1, 1, 1)
    return 0.5 * (((pdx - tdx).abs() / norm).mean() + ((pdy - tdy).abs() / norm).mean())


def wmse_term(pred: torch.Tensor, target: torch.Tensor, eps: float = VAR_EPS) -> torch.Tensor:
    var = target.detach().var(dim=0, unbiased=False)
    w = 1.0 + var / (var.mean() + eps)
    return (w * (pred - target) ** 2).mean()


def noise_floor(footprints: torch.Tensor) -> float:
    """Robust noise std of captured footprints ``(B, 3, K, K)`` (:func:`footprints.crop_noise`): exact
    (simulated) footprints give ~0, captured ones their camera noise after black subtraction."""
    from sssphase_core.processing.footprints import crop_noise

    return crop_noise(footprints.detach().float().cpu().permute(0, 2, 3, 1).numpy())


class SBHLoss(torch.nn.Module):
    """Self-Balanced Hybrid loss; ``forward`` returns the total and the unweighted terms (floats).

    ``log_eps``: the log term's offset; training on captured footprints sets it to their noise floor
    (:func:`noise_floor`), so the log term does not fit noise below it."""

    def __init__(self, weights: SBHWeights = SBHWeights(), log_eps: float = LOG_EPS) -> None:
        super().__init__()
        self.weights, self.log_eps = weights, float(log_eps)

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        pred, target = pred.float(), target.float()
        terms = {
            "l1": l1_term(pred, target),
            "log": log_term(pred, target, self.log_eps),
            "ssim": ssim_term(pred, target),
            "grad": grad_term(pred, target),
            "wmse": wmse_term(pred, target),
        }
        total = sum(getattr(self.weights, k) * v for k, v in terms.items())
        return total, {k: float(v.detach()) for k, v in terms.items()}
