"""IteratedSmoother (parallel IEKS / IPLS) against sequential references written here from the
definitions, the MAP stationarity of the IEKS fixed point, and gradients."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from difffilter.filters import Cubature, KalmanFilter
from difffilter.models import DynamicsModel, FunctionalModel, MeasurementModel, StateSpaceModel, TimeVaryingLinearModel
from difffilter.params import register_covariance
from difffilter.smoothers import IteratedSmoother, RTSSmoother

F64 = torch.float64
DT = 0.1


class Pendulum(DynamicsModel):
    """Pendulum with a learnable frequency ``omega``."""

    state_dim = 2

    def __init__(self, omega: float = 1.5) -> None:
        super().__init__()
        self.omega = nn.Parameter(torch.tensor(omega, dtype=F64))
        register_covariance(self, "Q", torch.tensor([[1e-3, 5e-4], [5e-4, 2e-2]], dtype=F64), "full")

    def forward(self, x, u=None):
        return torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * self.omega**2 * torch.sin(x[..., 0])], -1)


class SineRange(MeasurementModel):
    measurement_dim = 2

    def __init__(self) -> None:
        super().__init__()
        register_covariance(self, "R", torch.diag(torch.tensor([0.05, 0.1], dtype=F64)), "full")

    def forward(self, x, u=None):
        return torch.stack([torch.sin(x[..., 0]), x[..., 0] + 0.5 * x[..., 1] ** 2], -1)


def _problem(steps: int = 15, bsz: int = 2, seed: int = 0):
    model = StateSpaceModel(Pendulum(), SineRange())
    g = torch.Generator().manual_seed(seed)
    x = torch.tensor([[0.8, 0.0], [-0.4, 0.6]], dtype=F64)[:bsz]
    zs = []
    with torch.no_grad():
        for _ in range(steps):
            x = model.dynamics(x) + 0.05 * torch.randn(x.shape, generator=g, dtype=F64)
            zs.append(model.measurement(x) + 0.2 * torch.randn(bsz, 2, generator=g, dtype=F64))
    z = torch.stack(zs, 1)
    mask = torch.rand(bsz, steps, 2, generator=g) > 0.2
    z = torch.where(mask, z, torch.full_like(z, float("nan")))
    return model, z, mask, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 0.5


def _cubature_slr(fn, mean, cov):
    """Statistical linear regression of ``fn`` under ``N(mean, cov)`` with the cubature rule
    (points ``mean +- sqrt(n) L e_i``, weights ``1 / 2n``), from the definitions."""
    n = mean.shape[-1]
    chol = torch.linalg.cholesky(cov)
    pts = torch.cat([mean[..., None, :] + math.sqrt(n) * chol.mT, mean[..., None, :] - math.sqrt(n) * chol.mT], -2)
    y = fn(pts)
    ybar = y.mean(-2)
    dx, dy = pts - mean[..., None, :], y - ybar[..., None, :]
    psi = dx.mT @ dy / (2 * n)
    a = torch.linalg.solve(cov, psi).mT
    omega = dy.mT @ dy / (2 * n) - a @ cov @ a.mT
    return a, ybar - (a @ mean[..., None])[..., 0], 0.5 * (omega + omega.mT)


def _reference(model, z, mask, m0, p0, method: str, iterations: int, start=None):
    """Sequential iterated smoother: relinearise around the previous smoothed trajectory (start:
    ``start = (mean, cov) [B, T+1, ...]``, else the prior everywhere), then the sequential Kalman
    filter + RTS smoother."""
    bsz, steps, _ = z.shape
    n, m = 2, 2
    mean = m0.expand(bsz, steps + 1, n).clone() if start is None else start[0]
    cov = p0.expand(bsz, steps + 1, n, n).clone() if start is None else start[1]
    q, r = model.dynamics.Q, model.measurement.R
    lin = RTSSmoother(KalmanFilter(TimeVaryingLinearModel(state_dim=n, measurement_dim=m)))
    for _ in range(iterations):
        prev, cur = mean[:, :-1].reshape(-1, n), mean[:, 1:].reshape(-1, n)
        if method == "extended":
            # analytic Jacobians of Pendulum and SineRange
            one, zero = torch.ones_like(prev[:, 0]), torch.zeros_like(prev[:, 0])
            w2 = model.dynamics.omega**2
            fj = torch.stack([torch.stack([one, DT * one], -1), torch.stack([-DT * w2 * torch.cos(prev[:, 0]), one], -1)], -2)
            hj = torch.stack([torch.stack([torch.cos(cur[:, 0]), zero], -1), torch.stack([one, cur[:, 1]], -1)], -2)
            c = model.dynamics(prev) - (fj @ prev[..., None])[..., 0]
            d = model.measurement(cur) - (hj @ cur[..., None])[..., 0]
            qq, rr = q.expand(len(prev), n, n), r.expand(len(cur), m, m)
        else:
            fj, c, of = _cubature_slr(model.dynamics, prev, cov[:, :-1].reshape(-1, n, n))
            hj, d, oh = _cubature_slr(model.measurement, cur, cov[:, 1:].reshape(-1, n, n))
            qq, rr = q + of, r + oh
        u = {"F": fj, "c": c, "Q": qq, "H": hj, "d": d, "R": rr}
        u = {k: v.reshape(bsz, steps, *v.shape[1:]) for k, v in u.items()}
        out = lin(z, m0, p0, mask=mask, controls=u)
        mean = torch.cat([out.initial_mean[:, None], out.mean], 1)
        cov = torch.cat([out.initial_cov[:, None], out.cov], 1)
    return out


@pytest.mark.parametrize("method", ["extended", "sigma"])
def test_each_pass_equals_sequential_reference(method):
    model, z, mask, m0, p0 = _problem(steps=6)
    sm = IteratedSmoother(model, method=method, iterations=3, sigma_points=Cubature())
    first = sm.filter(z, m0, p0, mask=mask)  # the smoother's start: the sequential EKF / UKF
    start = (torch.cat([m0.expand(2, 1, 2), first.mean], 1), torch.cat([p0.expand(2, 1, 2, 2), first.cov], 1))
    ref = _reference(model, z, mask, m0, p0, method, 3, start)
    out = sm(z, m0, p0, mask=mask)
    for name in ("mean", "cov", "initial_mean", "initial_cov", "cross_cov"):
        assert torch.allclose(getattr(out, name), getattr(ref, name), atol=1e-10, rtol=0), name
    assert torch.allclose(out.filtered.log_likelihood, ref.filtered.log_likelihood, atol=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["extended", "sigma"])
def test_fixed_point_equals_sequential_reference(method):
    model, z, mask, m0, p0 = _problem(steps=8)
    its = 25
    ref = _reference(model, z, mask, m0, p0, method, its)
    par = IteratedSmoother(model, method=method, iterations=its, sigma_points=Cubature())(z, m0, p0, mask=mask)
    seq = IteratedSmoother(model, method=method, iterations=its, sigma_points=Cubature(), parallel=False)(z, m0, p0, mask=mask)
    for name in ("mean", "cov", "initial_mean", "initial_cov", "cross_cov"):
        a, b, c = getattr(par, name), getattr(ref, name), getattr(seq, name)
        assert torch.allclose(a, b, atol=1e-8, rtol=0), f"{name}: {float((a - b).abs().max()):.2e}"
        assert torch.allclose(a, c, atol=1e-10, rtol=0), name
    # converged: one more pass moves nothing
    more = IteratedSmoother(model, method=method, iterations=its + 1, sigma_points=Cubature())(z, m0, p0, mask=mask)
    assert torch.allclose(more.mean, par.mean, atol=1e-10)


def test_ieks_fixed_point_is_map():
    # the IEKS is Gauss-Newton on the trajectory's negative log-posterior: its gradient vanishes there
    model, z, mask, m0, p0 = _problem()
    out = IteratedSmoother(model, iterations=20)(z, m0, p0, mask=mask)
    traj = torch.cat([out.initial_mean[:, None], out.mean], 1).detach().requires_grad_()
    q, r = model.dynamics.Q.detach(), model.measurement.R.detach()
    with torch.no_grad():
        omega = model.dynamics.omega.detach()

    def nlp(x):
        x0, xs = x[:, 0], x[:, 1:]
        f = torch.stack([x[:, :-1, 0] + DT * x[:, :-1, 1], x[:, :-1, 1] - DT * omega**2 * torch.sin(x[:, :-1, 0])], -1)
        h = torch.stack([torch.sin(xs[..., 0]), xs[..., 0] + 0.5 * xs[..., 1] ** 2], -1)
        e0 = x0 - m0
        ew = xs - f
        ev = torch.where(mask, torch.nan_to_num(z) - h, torch.zeros_like(h))
        quad = lambda e, c: (e * torch.linalg.solve(c, e[..., None])[..., 0]).sum()  # noqa: E731
        # a missing component: drop it from R by a unit variance on a zero residual
        return 0.5 * (quad(e0, p0) + quad(ew, q) + (ev**2 / r.diagonal()).sum())

    (grad,) = torch.autograd.grad(nlp(traj), traj)
    assert float(grad.abs().max()) < 1e-8


def test_gradients_through_iterations():
    model, z, mask, m0, p0 = _problem(steps=4, bsz=1)
    grads = []
    for parallel in (True, False):
        out = IteratedSmoother(model, iterations=4, parallel=parallel)(z, m0, p0, mask=mask)
        grads.append(torch.autograd.grad((out.mean**2).sum() + out.cov.sum(), model.dynamics.omega))
    assert torch.allclose(grads[0][0], grads[1][0], atol=1e-10)
    # against finite differences of the learnable frequency
    for method in ("extended", "sigma"):
        sm = IteratedSmoother(model, method=method, iterations=2, sigma_points=Cubature())

        def fn(omega, sm=sm):
            out = torch.func.functional_call(sm, {"filter.model.dynamics.omega": omega}, (z[:, :3], m0, p0), {"mask": mask[:, :3]})
            return out.mean, out.cov

        assert torch.autograd.gradcheck(fn, (torch.tensor(1.5, dtype=F64, requires_grad=True),), fast_mode=True)


def test_bad_arguments():
    model, *_ = _problem()
    with pytest.raises(ValueError, match="method"):
        IteratedSmoother(model, method="newton")
    with pytest.raises(ValueError, match="iterations"):
        IteratedSmoother(model, iterations=0)


def test_controls_and_float32():
    def f(x, u):
        return torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1] + DT * (u[..., 0] - torch.sin(x[..., 0]))], -1)

    def h(x, u):
        return torch.stack([torch.sin(x[..., 0]) + u[..., 1], x[..., 1]], -1)

    def model(dtype):
        return FunctionalModel(f=f, h=h, Q=torch.eye(2, dtype=dtype) * 0.01, R=torch.eye(2, dtype=dtype) * 0.1, controls=True)

    g = torch.Generator().manual_seed(5)
    z = torch.randn(2, 6, 2, generator=g, dtype=F64) * 0.3
    u = torch.randn(2, 6, 2, generator=g, dtype=F64)
    m0, p0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 0.5
    for method in ("extended", "sigma"):
        outs = [IteratedSmoother(model(F64), method=method, iterations=3, parallel=p)(z, m0, p0, controls=u) for p in (True, False)]
        assert torch.allclose(outs[0].mean, outs[1].mean, atol=1e-10)
        low = IteratedSmoother(model(torch.float32), method=method, iterations=3)(z.float(), m0.float(), p0.float(), controls=u.float())
        assert low.mean.dtype == torch.float32 and torch.allclose(low.mean.double(), outs[0].mean, atol=1e-4)
