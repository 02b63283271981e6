"""Issue 17, defect 4: every bad input gets a ValueError/TypeError naming the argument.

Before, each of these was accepted silently, or failed later with an unrelated RuntimeError or
a message not naming the argument.
"""

from __future__ import annotations

import pytest
import torch

from difffilter.filters import UKF, KalmanFilter
from difffilter.models import ConstantAcceleration, ConstantVelocity, CurrentStatistical, LinearModel, Singer
from difffilter.models.base import StateSpaceModel
from difffilter.params import check_covariance

from .filter_contract import cv_matrices, make_data

F64 = torch.float64


def linear(dtype=F64) -> LinearModel:
    return LinearModel(**{k: v.to(dtype) for k, v in cv_matrices().items()})


def cv_filter() -> KalmanFilter:
    meas = LinearModel(
        F=torch.eye(2, dtype=F64), H=torch.tensor([[1.0, 0.0]], dtype=F64), Q=torch.eye(2, dtype=F64), R=torch.eye(1, dtype=F64)
    ).measurement
    return KalmanFilter(StateSpaceModel(ConstantVelocity(axes=1, dt=1.0, q=0.5, dtype=F64), meas))


def run(flt, z=None, **kw):  # type: ignore[no-untyped-def]
    n = flt.state_dim
    z = make_data(3, 6, flt.measurement_dim) if z is None else z
    return flt(z, torch.zeros(n, dtype=z.dtype), torch.eye(n, dtype=z.dtype), **kw)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_raw_parameter_is_named_before_it_poisons_the_batch(bad):
    flt = UKF(linear())
    with torch.no_grad():
        flt.model.measurement.parametrizations.R.original[0, 0] = bad
    with pytest.raises(ValueError, match=r"parameter model\.measurement\.R .*non-finite"):
        run(flt)


def test_linear_model_matrices_are_validated():
    m = cv_matrices()
    nan_f = m["F"].clone()
    nan_f[0, 1] = float("nan")
    with pytest.raises(ValueError, match="F must be finite"):
        LinearModel(**{**m, "F": nan_f})
    with pytest.raises(TypeError, match="H has dtype torch.float32 .* F, H, Q, R, B one dtype"):
        LinearModel(**{**m, "H": m["H"].float()})
    with pytest.raises(TypeError, match="R has dtype torch.float32"):
        LinearModel(**{**m, "R": m["R"].float()})


@pytest.mark.parametrize("dt", [float("inf"), float("nan"), 0.0, -1.0])
def test_constant_velocity_dt_is_validated(dt):
    with pytest.raises(ValueError, match="dt must be finite and positive"):
        ConstantVelocity(dt=dt)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -0.5])
def test_per_step_dt_is_validated_and_the_batch_element_named(bad):
    flt = cv_filter()
    dt = torch.ones(3, 6, 1, dtype=F64)
    dt[2, 4, 0] = bad
    with pytest.raises(ValueError, match=r"controls\['dt'\] must be finite and non-negative.*\[b, t\] = \[2, 4\].*batch elements \[2\]"):
        run(flt, controls={"dt": dt})


def test_a_zero_per_step_interval_is_no_time_passing():
    """``dt = 0`` (a trajectory whose first step starts at its given belief) is accepted: identity
    transition, zero process noise, finite gradients; the filter's first posterior is then the
    plain Kalman update of the initial belief (closed form)."""
    gen = torch.Generator().manual_seed(0)
    for dyn in (
        ConstantVelocity(axes=2, q=0.7, dtype=F64),
        ConstantVelocity(axes=2, q=0.7, noise="discrete", dtype=F64),
        ConstantAcceleration(axes=2, q=0.3, dtype=F64),
        Singer(axes=2, tau=5.0, sigma_a=0.4, dtype=F64),
        CurrentStatistical(axes=2, tau=5.0, dtype=F64),
    ):
        x = torch.randn(3, dyn.state_dim, generator=gen, dtype=F64)
        u = {"dt": torch.zeros(3, 1, dtype=F64)}
        torch.testing.assert_close(dyn(x, u), x, rtol=0, atol=0)
        q = dyn.process_noise(x, u)
        torch.testing.assert_close(q, torch.zeros_like(q), rtol=0, atol=0)
        (dyn(x, u).sum() + q.sum()).backward()
        assert all(bool(torch.isfinite(p.grad).all()) for p in dyn.parameters() if p.grad is not None), type(dyn).__name__
    flt = cv_filter()
    z = make_data(3, 6, 1)
    dt = torch.ones(3, 6, 1, dtype=F64)
    dt[:, 0] = 0.0
    m0, p0 = torch.tensor([1.0, -0.5], dtype=F64), torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    res = flt(z, m0, p0, controls={"dt": dt})
    h, r = torch.tensor([[1.0, 0.0]], dtype=F64), torch.eye(1, dtype=F64)
    gain = p0 @ h.T / (h @ p0 @ h.T + r)
    want = m0 + (gain @ (z[:, 0, :, None] - (h @ m0)[:, None]))[..., 0]
    torch.testing.assert_close(res.mean[:, 0], want, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.cov[:, 0], (p0 - gain @ h @ p0).expand(3, 2, 2), rtol=1e-12, atol=1e-12)


def test_empty_batch_or_time_axis():
    flt = KalmanFilter(linear())
    with pytest.raises(ValueError, match=r"measurements must hold at least one trajectory and one step.*\(3, 0, 2\)"):
        run(flt, make_data(3, 6, 2)[:, :0])
    with pytest.raises(ValueError, match=r"measurements must hold at least one trajectory.*\(0, 6, 2\)"):
        run(flt, make_data(3, 6, 2)[:0])


def test_non_boolean_mask_values_are_refused():
    flt = KalmanFilter(linear())
    mask = torch.ones(3, 6, dtype=torch.long)
    mask[1, 2] = 2
    with pytest.raises(ValueError, match="mask must be boolean .* 0 and 1"):
        run(flt, mask=mask)
    ok = run(flt, mask=(mask == 1).long())  # integer 0/1 masks stay accepted
    assert torch.isfinite(ok.mean).all()


def test_assigning_covariances_is_validated_in_the_users_terms():
    model = linear()
    with pytest.raises(ValueError, match=r"Q must have shape \[4, 4\], got \[3, 3\]"):
        model.Q = torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match="Q must be finite"):
        model.Q = torch.full((4, 4), float("nan"), dtype=F64)
    with pytest.raises(TypeError, match="R must have dtype torch.float64"):
        model.R = torch.eye(2)
    with pytest.raises(ValueError, match="R must be symmetric"):
        model.R = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64)
    cv = ConstantVelocity(dt=1.0, q=1.0, dtype=F64)
    with pytest.raises(ValueError, match=r"q must exceed 0\.0"):
        cv.q = torch.tensor([-1.0], dtype=F64)


def test_one_covariance_validator_for_models_and_initial_beliefs():
    flt = KalmanFilter(linear())
    bad = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    bad[1, 0, 0] = -1.0
    with pytest.raises(ValueError, match=r"initial_cov must be positive definite \(batch elements \[1\]\)"):
        flt(make_data(3, 6, 2), torch.zeros(4, dtype=F64), bad)
    with pytest.raises(ValueError, match=r"P must be positive definite \(batch elements \[1\]\)"):
        check_covariance("P", bad, 4, batch_ok=True)
    nan_mean = torch.zeros(3, 4, dtype=F64)
    nan_mean[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"initial_mean contains non-finite values \(batch elements \[2\]\)"):
        flt(make_data(3, 6, 2), nan_mean, torch.eye(4, dtype=F64))
