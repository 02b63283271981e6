"""EKF/UKF blend (p004): limits, convex combination, switch and gate, and the shared battery."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF, MerweScaled, SquareRootUKF
from difffilter.mixers import Blend
from difffilter.models import FunctionalModel
from experiments.papers.p004 import switching_statistics

from .filter_contract import FilterContract

F64 = torch.float64
SIGMAS = {"sigma_accel": 0.05, "sigma_gyro": 0.01, "sigma_gnss": 1.0, "sigma_imu": 0.1}


def unicycle(dtype=F64) -> FunctionalModel:
    """IMU-driven planar vehicle ``[px, py, v, heading]``, controls ``u = [accel, yaw rate]``
    (dt = 1 s), GNSS position measurement."""

    def f(x, u):
        th = x[..., 3]
        return torch.stack(
            [x[..., 0] + x[..., 2] * torch.cos(th), x[..., 1] + x[..., 2] * torch.sin(th), x[..., 2] + u[..., 0], th + u[..., 1]], -1
        )

    def h(x, u):
        return x[..., :2]

    Q = torch.diag(torch.tensor([0.05, 0.05, 0.02, 1e-3], dtype=dtype))
    return FunctionalModel(f=f, h=h, Q=Q, R=torch.eye(2, dtype=dtype), controls=True)


def manoeuvre(B: int = 2, T: int = 40, dtype=F64, seed: int = 0):
    """Straight, accelerating, turning and varying-turn-rate segments; returns (z, u, truth)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=F64)
    accel = torch.where((t >= 5) & (t < 10), 1.0, 0.0)
    rate = torch.where((t >= 15) & (t < 25), 0.15, 0.0) + torch.where(t >= 30, 0.1 * torch.sin(0.5 * t), 0.0)
    u = torch.stack([accel, rate], -1).expand(B, T, 2).clone()
    x = torch.tensor([0.0, 0.0, 5.0, 0.3], dtype=F64).expand(B, 4)
    truth = []
    for k in range(T):
        x = torch.stack(
            [x[:, 0] + x[:, 2] * torch.cos(x[:, 3]), x[:, 1] + x[:, 2] * torch.sin(x[:, 3]), x[:, 2] + u[:, k, 0], x[:, 3] + u[:, k, 1]], -1
        )
        truth.append(x)
    truth = torch.stack(truth, 1)
    z = truth[..., :2] + torch.randn(B, T, 2, generator=g, dtype=F64)
    return z.to(dtype), u.to(dtype), truth.to(dtype)


def stats(u):
    return switching_statistics(u[..., 0], u[..., 1], **SIGMAS)


M0 = torch.tensor([0.0, 0.0, 5.0, 0.0], dtype=F64)
P0 = torch.diag(torch.tensor([1.0, 1.0, 0.5, 0.3], dtype=F64))
SP = MerweScaled(alpha=1.0)


def _stepwise_prior_check(blend: Blend, z, u, expect):
    """Run the blend and compare each step's prior with ``expect(posterior belief, u_t)``."""
    res = blend(z, M0, P0, controls=u)
    belief = blend.initial_belief(M0, P0, batch_size=z.shape[0])
    for t in range(z.shape[0]):
        ref_mean, ref_cov = expect(belief, u[:, t])
        torch.testing.assert_close(res.prior_mean[:, t], ref_mean, rtol=0, atol=1e-10)
        torch.testing.assert_close(res.prior_cov[:, t], ref_cov, rtol=0, atol=1e-10)
        belief = {"mean": res.mean[:, t], "cov": res.cov[:, t]}
    return res


def test_delta_one_predicts_like_ekf_and_zero_equals_ukf():
    model = unicycle()
    z, u, _ = manoeuvre()
    ekf, ukf = EKF(model), UKF(model, sigma_points=SP)
    one = Blend(ekf, ukf, delta=1.0)

    def ekf_prior(belief, ut):
        p = ekf.predict(belief, ut)
        return p["mean"], p["cov"]

    res = _stepwise_prior_check(one, z, u, ekf_prior)
    # ... followed by the UKF update of that prior
    post, _ = ukf.update({"mean": res.prior_mean[:, 7], "cov": res.prior_cov[:, 7]}, z[:, 7], None, u[:, 7])
    torch.testing.assert_close(res.mean[:, 7], post["mean"], rtol=0, atol=1e-10)
    zero = Blend(ekf, UKF(model, sigma_points=SP, redraw_after_predict=False), delta=0.0)(z, M0, P0, controls=u)
    ref = UKF(model, sigma_points=SP)(z, M0, P0, controls=u)
    for key in ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood"):
        torch.testing.assert_close(getattr(zero, key), getattr(ref, key), rtol=0, atol=1e-10)
    ekf_res = ekf(z, M0, P0, controls=u)
    assert (ekf_res.prior_mean - ref.prior_mean).abs().max() > 1e-2  # the case is nonlinear enough to tell them apart


@pytest.mark.parametrize("spread", [False, True])
def test_fixed_delta_is_convex_combination(spread):
    model = unicycle()
    z, u, _ = manoeuvre()
    ekf, ukf = EKF(model), UKF(model, sigma_points=SP)
    blend = Blend(ekf, ukf, delta=0.85, spread=spread)
    assert abs(blend.delta.item() - 0.85) < 1e-12

    def expect(belief, ut):
        pe, pu = ekf.predict(belief, ut), ukf.predict(belief, ut)
        d = pe["mean"] - pu["mean"]
        cov = 0.85 * pe["cov"] + 0.15 * pu["cov"] + (0.85 * 0.15 * d[:, :, None] * d[:, None, :] if spread else 0.0)
        return 0.85 * pe["mean"] + 0.15 * pu["mean"], cov

    res = _stepwise_prior_check(blend, z, u, expect)
    torch.testing.assert_close(res.blend_weight, torch.full_like(res.blend_weight, 0.85), rtol=0, atol=1e-12)


def test_switching_statistics_equations():
    accel = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    gyro = torch.tensor([[0.0, 0.0, math.pi / 2], [0.0, 0.0, 0.0]], dtype=F64)
    gamma, mu = switching_statistics(
        accel.norm(dim=-1), gyro.norm(dim=-1), sigma_accel=0.2, sigma_gyro=0.05, sigma_gnss=0.5, sigma_imu=0.1, gravity=9.8
    )
    torch.testing.assert_close(gamma, torch.tensor([0.4, 0.4], dtype=F64), rtol=0, atol=1e-15)
    torch.testing.assert_close(mu, torch.tensor([math.sqrt(25 / 9.8**2 + 0.25), 0.0], dtype=F64), rtol=0, atol=1e-15)


def test_switch_picks_ekf_on_straight_and_ukf_when_manoeuvring():
    model = unicycle()
    z, u, _ = manoeuvre()
    blend = Blend(EKF(model), UKF(model, sigma_points=SP), mode="switch", statistics=stats, thresholds=(0.1, 0.04))
    res = blend(z, M0, P0, controls=u)
    gamma, mu = stats(u)
    expect = ((gamma <= 0.1) & (mu <= 0.04)).to(F64)
    torch.testing.assert_close(res.blend_weight, expect, rtol=0, atol=0)
    assert expect[0, :5].eq(1).all() and expect[0, 15:25].eq(0).all()


def test_soft_gate_gradients_wrt_thresholds_are_finite_and_nonzero():
    model = unicycle()
    z, u, truth = manoeuvre(B=3)
    blend = Blend(EKF(model), UKF(model, sigma_points=SP), mode="gate", statistics=stats, thresholds=(0.03, 0.05), temperature=(0.01, 0.02))
    res = blend(z, M0, P0, controls=u)
    assert ((res.blend_weight > 0.01) & (res.blend_weight < 0.99)).any()
    loss = ((res.mean[..., :2] - truth[..., :2]) ** 2).mean()
    loss.backward()
    for name in ("gamma_threshold", "mu_threshold", "gamma_temperature", "mu_temperature"):
        grad = getattr(blend.parametrizations, name).original.grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs() > 0, name
    # with tiny temperatures the gate reproduces the hard switch (statistics away from thresholds)
    sharp = Blend(EKF(model), UKF(model, sigma_points=SP), mode="gate", statistics=stats, thresholds=(0.1, 0.04), temperature=1e-4)
    hard = Blend(EKF(model), UKF(model, sigma_points=SP), mode="switch", statistics=stats, thresholds=(0.1, 0.04))
    torch.testing.assert_close(sharp(z, M0, P0, controls=u).mean, hard(z, M0, P0, controls=u).mean, rtol=0, atol=1e-8)


def test_square_root_ukf_branch_and_float32():
    model = unicycle()
    z, u, _ = manoeuvre()
    ref = Blend(EKF(model), UKF(model, sigma_points=SP), delta=0.5)(z, M0, P0, controls=u)
    sr = Blend(EKF(model), SquareRootUKF(model, sigma_points=SP), delta=0.5)(z, M0, P0, controls=u)
    torch.testing.assert_close(sr.mean, ref.mean, rtol=0, atol=1e-9)
    m32 = unicycle(torch.float32)
    r32 = Blend(EKF(m32), UKF(m32, sigma_points=SP), mode="gate", statistics=stats)(z.float(), M0.float(), P0.float(), controls=u.float())
    r64 = Blend(EKF(model), UKF(model, sigma_points=SP), mode="gate", statistics=stats)(z, M0, P0, controls=u)
    assert r32.mean.dtype == torch.float32
    assert ((r32.mean.double() - r64.mean).abs().max() / r64.mean.abs().max()) < 1e-4


def test_bad_arguments():
    model = unicycle()
    with pytest.raises(ValueError, match="mode"):
        Blend(model, model, mode="soft")
    with pytest.raises(ValueError, match="delta"):
        Blend(model, model, delta=1.5)
    with pytest.raises(ValueError, match="statistics"):
        Blend(model, model, mode="gate")
    with pytest.raises(ValueError, match="positive"):
        Blend(model, model, mode="gate", statistics=stats, thresholds=(-1.0, 0.1))
    with pytest.raises(TypeError, match="ekf"):
        Blend(UKF(model), model)


class TestBlendFixed(FilterContract):
    def make_filter(self, model):
        return Blend(EKF(model), UKF(model, sigma_points=SP), delta=0.85, spread=True)


class TestBlendGate(FilterContract):
    def make_filter(self, model):
        dtype = model.Q.dtype

        def constant_stats(u):
            return torch.tensor(0.05, dtype=dtype), torch.tensor(0.04, dtype=dtype)

        return Blend(
            EKF(model), UKF(model, sigma_points=SP), mode="gate", statistics=constant_stats, thresholds=(0.1, 0.05), temperature=0.02
        )
