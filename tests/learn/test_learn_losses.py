"""Self-Balanced Hybrid loss: each term on edge cases, finite values and gradients."""

from __future__ import annotations

import pytest
import torch

from sssphase_core.learning import losses as L

TERMS = [L.l1_term, L.log_term, L.ssim_term, L.grad_term, L.wmse_term]


def footprint(b: int = 4, k: int = 16, peak: float = 0.04) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(k) - k // 2, torch.arange(k) - k // 2, indexing="ij")
    r = torch.hypot(y.float(), x.float())
    widths = torch.tensor([2.0, 1.2, 0.7]).view(1, 3, 1, 1) * torch.linspace(0.8, 1.2, b).view(b, 1, 1, 1)
    return peak * torch.exp(-r / widths)


EDGE_TARGETS = {
    "zeros": torch.zeros(4, 3, 16, 16),
    "negative": -0.01 * torch.rand(4, 3, 16, 16),
    "constant": torch.full((4, 3, 16, 16), 0.02),
    "footprint": footprint(),
}


@pytest.mark.parametrize("term", TERMS, ids=lambda t: t.__name__)
@pytest.mark.parametrize("target_name", list(EDGE_TARGETS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_terms_are_finite_with_finite_gradients(term, target_name, dtype):
    target = EDGE_TARGETS[target_name]
    for start in (torch.zeros_like(target), target + 0.003 * torch.randn_like(target), torch.full_like(target, -0.01)):
        pred = start.to(dtype).requires_grad_()
        value = term(pred.float(), target.to(dtype).float())
        value.backward()
        assert torch.isfinite(value)
        assert torch.isfinite(pred.grad).all()


def test_sbh_total_with_float16_inputs():
    target = footprint().half()
    pred = (target.float() + 0.002 * torch.randn(target.shape)).half().requires_grad_()
    total, terms = L.SBHLoss()(pred, target)
    total.backward()
    assert total.dtype == torch.float32 and torch.isfinite(total)
    assert pred.grad.dtype == torch.float16 and torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    w = L.SBHWeights()
    assert float(total.detach()) == pytest.approx(sum(getattr(w, k) * v for k, v in terms.items()), rel=1e-5)


@pytest.mark.parametrize("term", [L.l1_term, L.log_term, L.grad_term, L.wmse_term], ids=lambda t: t.__name__)
def test_terms_vanish_at_the_target(term):
    t = footprint()
    assert float(term(t, t)) == pytest.approx(0.0, abs=1e-7)
    assert float(term(t * 1.5, t)) > 0


def test_ssim_term_is_near_zero_at_the_target_and_uses_the_footprint_peak():
    t = footprint()
    assert float(L.ssim_term(t, t)) < 1e-4
    blurred = torch.nn.functional.avg_pool2d(t, 3, 1, 1)
    # data range = peak: scaling both images leaves it unchanged, and it sees the blur clearly
    assert float(L.ssim_term(10 * blurred, 10 * t)) == pytest.approx(float(L.ssim_term(blurred, t)), rel=1e-4)
    from kornia.metrics import ssim

    blind = 1 - float(ssim(blurred, t, 11, max_val=1.0).mean())
    assert float(L.ssim_term(blurred, t)) > 10 * blind


def test_log_term_weights_faint_tails():
    t = footprint()
    tail = t.clone()
    tail[t < 1e-3] *= 2  # double only the faint tail
    peak = t.clone()
    peak[t > 0.02] += 2e-3  # perturb the peak by a larger absolute amount
    assert float(L.l1_term(tail, t)) < float(L.l1_term(peak, t)) * 10
    assert float(L.log_term(tail, t)) > float(L.log_term(peak, t))


def test_grad_term_is_channel_normalised():
    t = footprint()
    p = t + 0.002 * torch.randn_like(t)
    scale = torch.tensor([1.0, 0.3, 3.0]).view(1, 3, 1, 1)
    assert float(L.grad_term(p * scale, t * scale)) == pytest.approx(float(L.grad_term(p, t)), rel=2e-2)


def test_wmse_weights_follow_batch_variance():
    t = footprint(b=1)
    p = t + 0.01
    # a batch of one has zero variance: w = 1 and the term is the plain MSE
    assert float(L.wmse_term(p, t)) == pytest.approx(float(((p - t) ** 2).mean()), rel=1e-6)
    t2 = footprint(b=8)
    err = torch.zeros_like(t2)
    err[..., 8, 10] = 0.01  # error where the batch varies most (the shoulder)
    err_flat = torch.zeros_like(t2)
    err_flat[..., 0, 0] = 0.01  # same error where targets barely vary
    assert float(L.wmse_term(t2 + err, t2)) > float(L.wmse_term(t2 + err_flat, t2))
