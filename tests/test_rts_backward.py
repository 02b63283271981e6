"""The RTS backward pass's fast paths against independent references: a numpy loop of the
recursion's equations (values, 1e-10 in float64, KF / EKF / UKF gains with partial masks),
torch autograd through the per-step loop (gradients), gradcheck, the sigma-point
cross-covariance (the linear-f shortcut), and float32 at extreme scales."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, UKF, KalmanFilter, MerweScaled
from difffilter.filters.scan import scan_rts
from difffilter.models import FunctionalModel
from difffilter.smoothers import RTSSmoother
from difffilter.smoothers.backward import sequential_rts
from difffilter.smoothers.base import rts_backward, rts_step, smoother_gains
from difffilter.smoothers.transition import transition_cross_covariance
from tests.test_smoothers import CTRL, M0, P0, linear_model, linear_window, pendulum, pendulum_data

F64 = torch.float64


def numpy_rts(mean, cov, prior_mean, prior_cov, gains, m0, p0):
    """The recursion written out per trajectory and step in numpy (float64)."""
    mean, cov, pm, pp, g, m0, p0 = (x.detach().double().numpy() for x in (mean, cov, prior_mean, prior_cov, gains, m0, p0))
    bsz, steps = mean.shape[:2]
    s_m, s_p, cross = mean.copy(), cov.copy(), np.zeros_like(cov)
    i_m, i_p = np.zeros_like(m0), np.zeros_like(p0)
    for b in range(bsz):
        for t in range(steps - 1, -1, -1):
            cross[b, t] = g[b, t] @ s_p[b, t]
            prev_m, prev_p = (mean[b, t - 1], cov[b, t - 1]) if t > 0 else (m0[b], p0[b])
            new_m = prev_m + g[b, t] @ (s_m[b, t] - pm[b, t])
            new_p = prev_p + g[b, t] @ (s_p[b, t] - pp[b, t]) @ g[b, t].T
            new_p = 0.5 * (new_p + new_p.T)
            if t > 0:
                s_m[b, t - 1], s_p[b, t - 1] = new_m, new_p
            else:
                i_m[b], i_p[b] = new_m, new_p
    return s_m, s_p, cross, i_m, i_p


def autograd_loop(mean, cov, prior_mean, prior_cov, gains, m0, p0):
    """The per-step loop of :func:`rts_step` differentiated by torch autograd."""
    m_t, p_t, pm_t, pp_t, g_t = (x.unbind(1) for x in (mean, cov, prior_mean, prior_cov, gains))
    s_m, s_p = m_t[-1], p_t[-1]
    means, covs, crosses = [s_m], [s_p], []
    for t in range(len(m_t) - 1, -1, -1):
        crosses.append(g_t[t] @ s_p)
        prev = (m_t[t - 1], p_t[t - 1]) if t > 0 else (m0, p0)
        s_m, s_p = rts_step(*prev, g_t[t], pm_t[t], pp_t[t], s_m, s_p)
        means.append(s_m)
        covs.append(s_p)
    i_m, i_p = means.pop(), covs.pop()
    return torch.stack(means[::-1], 1), torch.stack(covs[::-1], 1), torch.stack(crosses[::-1], 1), i_m, i_p


def backward_inputs(kind: str, dtype=F64):
    """Filter moments and smoother gains of a KF, EKF or UKF window with partly missing steps."""
    if kind == "ukf-pendulum":
        z, _ = pendulum_data(B=3, T=25, seed=3)
        mask = torch.rand(z.shape[:2], generator=torch.Generator().manual_seed(1)) > 0.3
        z = torch.where(mask[..., None], z, torch.nan)
        model, m0, p0, u = pendulum(dtype)[0], torch.tensor([1.0, 0.0], dtype=dtype), 0.1 * torch.eye(2, dtype=dtype), None
        filt = UKF(model, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=1.0))
    else:
        z, u, mask = linear_window(T=12, seed=5)
        model, m0, p0 = linear_model(dtype), M0.to(dtype), P0.to(dtype)
        filt = {"kf": KalmanFilter, "ekf": EKF, "ukf": UKF}[kind](model)
    smoother = RTSSmoother(filt)
    res = filt(z.to(dtype), m0, p0, mask=mask, controls=u)
    init = smoother.initial_belief(z, m0, p0, None)
    gains, prior_cov = smoother.gains(res, init, u)
    return [x.detach() for x in (res.mean, res.cov, res.prior_mean, prior_cov, gains, init["mean"], init["cov"])]


@pytest.mark.parametrize("kind", ["kf", "ekf", "ukf", "ukf-pendulum"])
def test_fast_backward_paths_equal_the_recursion_and_its_autograd_gradients(kind):
    args = backward_inputs(kind)
    ref = numpy_rts(*args)
    leaves = [x.clone().requires_grad_(True) for x in args]
    auto = autograd_loop(*leaves)
    weights = [torch.randn(o.shape, generator=torch.Generator().manual_seed(i), dtype=F64) for i, o in enumerate(auto)]
    auto_grads = torch.autograd.grad(sum((o * w).sum() for o, w in zip(auto, weights, strict=True)), leaves)
    for method in ("sequential", "scan", "auto"):
        out = rts_backward(*leaves, method=method)
        for got, want in zip(out, ref, strict=True):
            np.testing.assert_allclose(got.detach().numpy(), want, rtol=0, atol=1e-10)
        grads = torch.autograd.grad(sum((o * w).sum() for o, w in zip(out, weights, strict=True)), leaves)
        for got, want in zip(grads, auto_grads, strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=1e-10)


def test_a_loss_of_some_outputs_gets_the_gradients_of_the_full_graph():
    """The hand-written reverse mode skips the covariance adjoints when only means are used."""
    args = backward_inputs("ekf")
    for used in ([0], [0, 3], [1], [2], [4], [0, 2]):
        leaves = [x.clone().requires_grad_(True) for x in args]
        got = torch.autograd.grad(sum(sequential_rts(*leaves)[i].square().sum() for i in used), leaves, materialize_grads=True)
        want = torch.autograd.grad(sum(autograd_loop(*leaves)[i].square().sum() for i in used), leaves, materialize_grads=True)
        for a, b in zip(got, want, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-10)


def test_gradcheck_of_the_backward_paths_and_the_gain_solve():
    args = [x[:1, :3].clone() if i < 5 else x[:1].clone() for i, x in enumerate(backward_inputs("ukf"))]
    leaves = tuple(x.requires_grad_(True) for x in args)
    assert torch.autograd.gradcheck(sequential_rts, leaves)
    assert torch.autograd.gradcheck(scan_rts, (leaves[4], *leaves[:4], *leaves[5:]))
    cross = (leaves[1] @ torch.eye(4, dtype=F64).flip(0)).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(smoother_gains, (cross, leaves[3]))


def test_linear_dynamics_shortcut_equals_the_sigma_point_cross_covariance():
    """``C = P F^T`` against the unscented transform through the same map given as a function."""
    model = linear_model()
    dyn = model.dynamics
    f_mat = dyn.matrix(None).detach()
    as_function = FunctionalModel(
        f=lambda x, u: x @ f_mat.mT + u @ CTRL.T, h=lambda x, u: x[..., [0, 2]], Q=dyn.Q.detach(), R=torch.eye(2, dtype=F64), controls=True
    )
    g = torch.Generator().manual_seed(0)
    mean = 100.0 * torch.randn(6, 4, generator=g, dtype=F64)
    a = torch.randn(6, 4, 4, generator=g, dtype=F64)
    cov = a @ a.mT + 0.1 * torch.eye(4, dtype=F64)
    u = torch.randn(6, 2, generator=g, dtype=F64)
    for pts in (MerweScaled(alpha=0.3, beta=2.0, kappa=0.0), MerweScaled(alpha=1.0)):
        fast = transition_cross_covariance(UKF(model, sigma_points=pts), mean, cov, u)
        points = transition_cross_covariance(UKF(as_function, sigma_points=pts), mean, cov, u)
        torch.testing.assert_close(fast, points, rtol=1e-9, atol=1e-9)


def test_float32_at_extreme_scales_stays_finite():
    """Large positions (1e4) and tiny noise (1e-6) in float32: smoothed moments and gradients
    finite on every backward path."""
    for kind in ("ekf", "ukf"):
        args = [x.float() for x in backward_inputs(kind)]
        args[0], args[2], args[5] = args[0] + 1e4, args[2] + 1e4, args[5] + 1e4
        for scale in (1e-6, 1e6):
            scaled = [x * scale if i in (1, 3, 6) else x for i, x in enumerate(args)]
            for method in ("sequential", "scan"):
                leaves = [x.clone().requires_grad_(True) for x in scaled]
                out = rts_backward(*leaves, method=method)
                (out[0].sum() + out[1].sum() / scale).backward()
                assert all(bool(torch.isfinite(o).all()) for o in out), (kind, scale, method)
                assert all(bool(torch.isfinite(x.grad).all()) for x in leaves), (kind, scale, method)


def test_smoother_training_step_in_float32_is_finite_and_close_to_float64():
    z, u, mask = linear_window(T=30, seed=2)
    out = {}
    for dtype in (torch.float32, F64):
        model = linear_model(dtype)
        smoother = RTSSmoother(UKF(model))
        res = smoother(z.to(dtype), M0.to(dtype), P0.to(dtype), mask=mask, controls=u.to(dtype))
        res.mean.square().sum().backward()
        grad = model.dynamics.parametrizations.Q.original.grad
        assert torch.isfinite(res.mean).all() and torch.isfinite(grad).all()
        out[dtype] = res.mean.double()
    torch.testing.assert_close(out[torch.float32], out[F64], rtol=1e-4, atol=1e-3)


def test_bad_methods_raise():
    args = backward_inputs("kf")
    with pytest.raises(ValueError, match="method"):
        rts_backward(*args, method="parallel")
    with pytest.raises(ValueError, match="angular"):
        rts_backward(*args, SimpleNamespace(angular=(0,)), method="scan")  # type: ignore[arg-type]
