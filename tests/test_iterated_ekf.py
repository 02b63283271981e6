"""Iterated EKF: one iteration is the EKF; many iterations reach the posterior mode (MAP) of a
strongly nonlinear range-only update, computed independently by scipy's BFGS."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from difffilter.filters import EKF, IteratedEKF
from difffilter.models import FunctionalModel

F64 = torch.float64
BEACONS = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=F64)


def ranges(x):
    return torch.linalg.vector_norm(x[..., None, :2] - BEACONS, dim=-1)


def range_model(q=1e-3, r=0.01):
    return FunctionalModel(f=lambda x: x, h=ranges, Q=q * torch.eye(2, dtype=F64), R=r * torch.eye(2, dtype=F64))


def map_estimate(prior_mean, prior_cov, z, r):
    """Posterior mode of N(x; m, P) N(z; |x - b_i|, r I) by BFGS (numpy, analytic gradient)."""
    pinv = np.linalg.inv(prior_cov)
    b = BEACONS.numpy()

    def cost(x):
        d = x - prior_mean
        res = z - np.linalg.norm(x - b, axis=1)
        return 0.5 * d @ pinv @ d + 0.5 * res @ res / r

    def grad(x):
        diff = x - b
        rng = np.linalg.norm(diff, axis=1)
        res = z - rng
        return pinv @ (x - prior_mean) - (res / r) @ (diff / rng[:, None])

    out = minimize(cost, prior_mean, jac=grad, method="BFGS", options={"gtol": 1e-13, "maxiter": 1000})
    return out.x


def test_one_iteration_is_the_ekf():
    g = torch.Generator().manual_seed(0)
    z = (ranges(torch.tensor([4.0, 3.0], dtype=F64)) + 0.3 * torch.randn(3, 20, 2, generator=g, dtype=F64)).abs()
    mask = torch.rand(3, 20, 2, generator=g) > 0.3
    m0, p0 = torch.tensor([3.0, 4.0], dtype=F64), 2.0 * torch.eye(2, dtype=F64)
    a = IteratedEKF(range_model(), iterations=1)(z, m0, p0, mask=mask)
    b = EKF(range_model())(z, m0, p0, mask=mask)
    for name in ("mean", "cov", "log_likelihood", "nis"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0)


def test_iterations_reach_the_posterior_mode_of_a_range_only_update():
    r = 0.01
    model = range_model(q=1e-12, r=r)
    g = torch.Generator().manual_seed(1)
    # prior std 2 m a few metres from the beacons: the range function is far from linear over it
    prior_means = torch.tensor([[4.0, 3.0], [6.0, 2.0], [3.0, 1.5], [7.0, 4.0]], dtype=F64)
    truth = prior_means + 1.5 * torch.randn(4, 2, generator=g, dtype=F64)
    truth[:, 1] = truth[:, 1].abs() + 0.5  # same side of the beacon line as the prior
    z = (ranges(truth) + 0.1 * torch.randn(4, 2, generator=g, dtype=F64))[:, None]
    p0 = 4.0 * torch.eye(2, dtype=F64)
    with torch.no_grad():
        iekf = IteratedEKF(model, iterations=30)(z, prior_means, p0)
        ekf = EKF(model)(z, prior_means, p0)
    for b in range(4):
        # the prediction is the identity with Q = 1e-12: the update's prior is (m0, P0 + 1e-12 I)
        ref = map_estimate(prior_means[b].numpy(), p0.numpy() + 1e-12 * np.eye(2), z[b, 0].numpy(), r)
        np.testing.assert_allclose(iekf.mean[b, 0].numpy(), ref, rtol=0, atol=1e-7)
        assert np.abs(ekf.mean[b, 0].numpy() - ref).max() > 1e-2  # the single linearisation is far off
    # the covariance is the EKF form at the mode: (P^-1 + H^T R^-1 H)^-1 with H at the final iterate
    x = iekf.mean[:, 0]
    h = torch.func.vmap(torch.func.jacrev(ranges))(x)
    info = torch.linalg.inv(p0 + 1e-12 * torch.eye(2, dtype=F64)) + h.mT @ h / r
    # Joseph form with H at the second-to-last iterate, which equals the last one at convergence
    torch.testing.assert_close(iekf.cov[:, 0], torch.linalg.inv(info), rtol=1e-6, atol=1e-10)


def test_iterating_lowers_the_error_of_range_only_tracking():
    g = torch.Generator().manual_seed(2)
    B, T = 64, 15
    x = torch.tensor([5.0, 3.0], dtype=F64) + 0.5 * torch.randn(B, 2, generator=g, dtype=F64)
    truth = x[:, None].expand(B, T, 2)
    z = ranges(truth) + 0.1 * torch.randn(B, T, 2, generator=g, dtype=F64)
    m0, p0 = torch.tensor([4.0, 4.0], dtype=F64), 4.0 * torch.eye(2, dtype=F64)
    err = {}
    for n in (1, 5):
        with torch.no_grad():
            out = IteratedEKF(range_model(q=1e-6, r=0.01), iterations=n)(z, m0, p0)
        err[n] = float(((out.mean - truth) ** 2).sum(-1).mean(0)[0])  # first update: the nonlinear one
    assert err[5] < 0.5 * err[1]


def test_gradients_and_bad_input():
    model = range_model()
    g = torch.Generator().manual_seed(3)
    z = (ranges(torch.tensor([4.0, 3.0], dtype=F64)) + 0.1 * torch.randn(2, 4, 2, generator=g, dtype=F64)).requires_grad_(True)
    m0 = torch.tensor([3.5, 3.5], dtype=F64, requires_grad=True)

    def fn(zz, mm):
        out = IteratedEKF(model, iterations=3)(zz, mm, torch.eye(2, dtype=F64))
        return out.mean, out.log_likelihood

    assert torch.autograd.gradcheck(fn, (z, m0), atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="iterations"):
        IteratedEKF(model, iterations=0)
