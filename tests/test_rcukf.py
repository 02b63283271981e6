"""Residual-constrained fading-memory UKF (p002): reduction to the UKF, order of operations,
masks, behaviour after an abrupt change, parameters, and the shared battery."""

from __future__ import annotations

import pytest
import torch

from difffilter.filters import UKF, MerweScaled
from difffilter.filters.adaptive import RCUKF
from difffilter.models import FunctionalModel, LinearModel

from .filter_contract import FilterContract, make_data

F64 = torch.float64
SP = MerweScaled(alpha=1.0)


class NoFading(RCUKF):
    """RC-UKF with the fading factor pinned to 1 (everything else, C0 included, still runs)."""

    def fading_factor(self, residual_cov, spread_zz, r, pxz, cov, mask):
        eta = super().fading_factor(residual_cov, spread_zz, r, pxz, cov, mask)
        return torch.ones_like(eta)


def beacon_model(extra_state: bool = False) -> FunctionalModel:
    """2-D constant velocity with ranges to two beacons; ``extra_state`` appends a random-walk
    state that neither the dynamics nor the measurement couple to the others."""
    n = 5 if extra_state else 4

    def f(x):
        out = [x[..., 0] + 0.5 * x[..., 1], x[..., 1], x[..., 2] + 0.5 * x[..., 3], x[..., 3]]
        return torch.stack(out + ([x[..., 4]] if extra_state else []), -1)

    def h(x):
        p = torch.stack([x[..., 0], x[..., 2]], -1)
        b = torch.tensor([[20.0, -5.0], [-10.0, 30.0]], dtype=x.dtype)
        return (p[..., None, :] - b).norm(dim=-1)

    return FunctionalModel(f=f, h=h, Q=0.05 * torch.eye(n, dtype=F64), R=0.5 * torch.eye(2, dtype=F64))


def beacon_data(B=3, T=25, seed=1):
    return make_data(B, T, 2, seed=seed) + torch.tensor([20.0, 30.0], dtype=F64)


@pytest.mark.parametrize("per_state", [False, True])
def test_eta_one_reproduces_the_ukf(per_state):
    model = beacon_model()
    z = beacon_data()
    mask = torch.rand(3, 25, 2, generator=torch.Generator().manual_seed(0)) > 0.3
    mask[1, 4:8] = False
    zn = torch.where(mask, z, torch.nan)
    m0, P0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64) * 4
    res = NoFading(model, sigma_points=SP, per_state=per_state)(zn, m0, P0, mask=mask)
    ref = UKF(model, sigma_points=SP)(zn, m0, P0, mask=mask)
    for key in ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis"):
        torch.testing.assert_close(getattr(res, key), getattr(ref, key), rtol=0, atol=1e-12)
    faded = RCUKF(model, sigma_points=SP, per_state=per_state)(zn, m0, P0, mask=mask)
    assert (faded.fading_factor > 1).any() and (faded.mean - ref.mean).abs().max() > 1e-3


def test_order_of_operations_matches_manual_recursion():
    """eps from the un-faded prediction, C0 recursion, eta, inflation of the spread only, then
    the UKF update recomputed from the inflated prior."""
    model = beacon_model()
    z = beacon_data(B=2, T=15, seed=4)
    rho = 0.8
    rc = RCUKF(model, sigma_points=SP, rho=rho)
    res = rc(z, torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64) * 4)
    ukf = UKF(model, sigma_points=SP)
    R, Q = model.R.detach(), model.Q.detach()
    belief = {"mean": torch.zeros(2, 4, dtype=F64), "cov": torch.eye(4, dtype=F64).expand(2, 4, 4) * 4}
    c0 = torch.zeros(2, 2, 2, dtype=F64)
    with torch.no_grad():
        for t in range(15):
            prior = ukf.predict(belief, None)
            _, info = ukf.update(prior, z[:, t], None, None)
            eps, S = info.innovation, info.innovation_cov
            c0 = (rho * c0 + eps[:, :, None] * eps[:, None, :]) / (1 + rho)
            eta = torch.clamp((c0 - R).diagonal(dim1=-2, dim2=-1).sum(-1) / (S - R).diagonal(dim1=-2, dim2=-1).sum(-1), min=1.0)
            faded = eta[:, None, None] * (prior["cov"] - Q) + Q
            belief, _ = ukf.update({"mean": prior["mean"], "cov": faded}, z[:, t], None, None)
            torch.testing.assert_close(res.fading_factor[:, t], eta, rtol=0, atol=1e-10)
            torch.testing.assert_close(res.mean[:, t], belief["mean"], rtol=0, atol=1e-9)
            torch.testing.assert_close(res.cov[:, t], belief["cov"], rtol=0, atol=1e-9)
    torch.testing.assert_close(res.final_belief["residual_cov"], c0, rtol=0, atol=1e-10)
    assert (res.fading_factor > 1).any()


def test_masks_keep_the_residual_covariance():
    model = beacon_model()
    rc = RCUKF(model, sigma_points=SP)
    z = beacon_data(B=2, T=6)
    belief = rc.initial_belief(torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64), batch_size=2)
    for t in range(4):
        belief, _, _ = rc.step(belief, z[:, t])
    before = belief["residual_cov"].clone()
    none = torch.zeros(2, 2, dtype=torch.bool)
    after, _, info = rc.step(belief, torch.full_like(z[:, 4], torch.nan), none)
    torch.testing.assert_close(after["residual_cov"], before, rtol=0, atol=0)
    torch.testing.assert_close(after["fading_factor"], torch.ones(2, dtype=F64), rtol=0, atol=0)
    assert (info.log_likelihood == 0).all()
    part = torch.tensor([[True, False], [False, True]])
    after2, _, _ = rc.step(after, torch.where(part, z[:, 5], torch.nan), part)
    changed = after2["residual_cov"] != before
    assert changed[0, 0, 0] and changed[1, 1, 1]
    assert not changed[0, 1].any() and not changed[0, :, 1].any() and not changed[1, 0].any() and not changed[1, :, 0].any()


def test_fading_recovers_faster_after_a_velocity_jump():
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    model = LinearModel(
        F=F, H=torch.tensor([[1.0, 0.0]], dtype=F64), Q=torch.diag(torch.tensor([1e-4, 1e-4], dtype=F64)), R=torch.eye(1, dtype=F64)
    )
    t = torch.arange(60, dtype=F64)
    truth = torch.where(t < 30, t, 30 + 4.0 * (t - 30))  # speed 1 -> 5 at t = 30
    g = torch.Generator().manual_seed(7)
    z = (truth + torch.randn(8, 60, generator=g, dtype=F64))[..., None]
    m0, P0 = torch.tensor([0.0, 1.0], dtype=F64), torch.eye(2, dtype=F64)
    ukf = UKF(model, sigma_points=SP)(z, m0, P0)
    rc = RCUKF(model, sigma_points=SP, rho=0.5)(z, m0, P0)
    err_ukf = (ukf.mean[:, 31:50, 0] - truth[31:50]).abs().mean()
    err_rc = (rc.mean[:, 31:50, 0] - truth[31:50]).abs().mean()
    assert err_rc < 0.5 * err_ukf
    assert rc.fading_factor[:, 31:40].max() > 2


def test_per_state_factor_leaves_unobserved_state_alone_and_cap_holds():
    model = beacon_model(extra_state=True)
    z = beacon_data(T=20) * 1.05  # biased ranges keep the residuals large
    m0, P0 = torch.zeros(5, dtype=F64), torch.eye(5, dtype=F64) * 4
    rc = RCUKF(model, sigma_points=SP, per_state=True, fading_cap=3.0)
    res = rc(z, m0, P0)
    assert res.fading_factor.shape == (3, 20, 5)
    torch.testing.assert_close(res.fading_factor[..., 4], torch.ones(3, 20, dtype=F64), rtol=0, atol=1e-12)
    assert res.fading_factor[..., :4].max() > 1.5 and res.fading_factor.max() <= 3.0 + 1e-12
    rc_scalar = RCUKF(model, sigma_points=SP, fading_cap=2.0)
    out = rc_scalar(z, m0, P0)
    assert out.fading_factor.max() <= 2.0 + 1e-12 and (out.fading_factor == rc_scalar.fading_cap).any()
    out.log_likelihood.sum().backward()
    for name in ("rho", "fading_cap"):
        grad = getattr(rc_scalar.parametrizations, name).original.grad
        assert torch.isfinite(grad).all() and grad.abs() > 0, name


def test_bad_arguments():
    model = beacon_model()
    with pytest.raises(ValueError, match="rho"):
        RCUKF(model, rho=0.0)
    with pytest.raises(ValueError, match="fading_cap"):
        RCUKF(model, fading_cap=0.5)
    rc = RCUKF(model, rho=1.0)
    assert abs(rc.rho.item() - 1.0) < 1e-12


class TestRCUKFFixedEta(FilterContract):
    def make_filter(self, model):
        return NoFading(model, sigma_points=SP)


class TestRCUKF(FilterContract):
    """Real fading: linear-Gaussian equivalences do not hold, the rest of the battery does."""

    test_equals_closed_form_kalman = None
    test_log_likelihood_equals_dense_joint_gaussian = None
    test_mask_equals_closed_form_subset_update = None

    def make_filter(self, model):
        return RCUKF(model, sigma_points=SP, rho=0.7)


class TestRCUKFPerStateCapped(TestRCUKF):
    def make_filter(self, model):
        return RCUKF(model, sigma_points=SP, rho=0.7, per_state=True, fading_cap=4.0)
