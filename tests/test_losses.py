"""Training losses on hand-made filter outputs: the robust HuberLoss against its formula."""

from __future__ import annotations

import pytest
import torch

from difffilter.filters.base import FilterResult
from difffilter.learn import HuberLoss, MSELoss

f64 = torch.float64


def _result(mean: torch.Tensor) -> FilterResult:
    b, t, n = mean.shape
    cov = torch.eye(n, dtype=mean.dtype).expand(b, t, n, n)
    zeros = torch.zeros(b, t, dtype=mean.dtype)
    return FilterResult(mean, cov, mean, cov, zeros, zeros, zeros, {"mean": mean[:, -1], "cov": cov[:, -1]})


def test_huber_loss_matches_its_formula_skips_missing_truth_and_has_finite_gradients():
    # errors of norm 0 (exactly at the truth), 3 (quadratic branch) and 30 (linear branch) on
    # components [0, 2]; component 1 is ignored; the last step has no truth.
    truth = torch.zeros(2, 4, 4, dtype=f64)
    truth[1, 3] = float("nan")
    mean = torch.zeros(2, 4, 3, dtype=f64)
    mean[0, 1, 0], mean[0, 2, 2], mean[0, :, 1] = 3.0, 30.0, 100.0
    mean[1, 0, 0], mean[1, 1, 2], mean[1, 2, 0], mean[1, 3, 0] = 4.0, 5.0, 6.0, 1e3
    mean.requires_grad_(True)
    loss = HuberLoss(state_index=[0, 2], truth_index=[0, 3], delta=5.0)(_result(mean), {"truth": truth})
    rho = lambda n: 0.5 * n * n if n <= 5.0 else 5.0 * (n - 2.5)  # noqa: E731
    expected = torch.tensor([(rho(0.0) + rho(3.0) + rho(30.0) + rho(0.0)) / 4, (rho(4.0) + rho(5.0) + rho(6.0)) / 3], dtype=f64)
    torch.testing.assert_close(loss, expected)
    loss.sum().backward()
    assert bool(torch.isfinite(mean.grad).all())
    assert float(mean.grad[0, 0].abs().sum()) == 0.0  # zero error: zero gradient, no NaN
    assert float(mean.grad[1, 3].abs().sum()) == 0.0  # missing truth: no gradient
    torch.testing.assert_close(mean.grad[0, 2, 2], torch.tensor(5.0 / 4, dtype=f64))  # slope delta in the linear branch


def test_huber_loss_is_half_the_mse_sum_for_small_errors_and_rejects_bad_delta():
    mean = torch.randn(3, 7, 2, dtype=f64, generator=torch.Generator().manual_seed(0))
    truth = torch.zeros(3, 7, 2, dtype=f64)
    res, batch = _result(mean), {"truth": truth}
    # all errors below delta: rho = ||e||^2 / 2 = (d / 2) x the per-component mse
    torch.testing.assert_close(HuberLoss(delta=1e3)(res, batch), MSELoss()(res, batch))
    with pytest.raises(ValueError, match="delta"):
        HuberLoss(delta=0.0)
    with pytest.raises(ValueError, match="truth"):
        HuberLoss()(res, {})
