"""Non-additive noise f(x, w, u), h(x, v, u): closed-form moments where the unscented transform
is exact, equivalence with the additive model when the noise enters linearly, the EKF's
noise Jacobians, and the augmented UKF's advantage where the noise passes through a nonlinearity."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF, Julier, KalmanFilter
from difffilter.models import LinearModel, NonAdditiveModel
from difffilter.sim.sampling import sample_trajectories
from difffilter.smoothers import RTSSmoother
from tests.filter_contract import cv_matrices

F64 = torch.float64


def test_prediction_and_update_match_closed_forms():
    """f(x, w) = x + w + c w^2 and h(x, v) = x + v + d v^2 (scalars): Julier points with
    n + kappa = 3 in the two augmented dimensions reproduce E[w^4] = 3 Q^2, so the UKF's moments
    are exact: x- = m + c Q, P- = P + Q + 2 c^2 Q^2, S = P- + R + 2 d^2 R^2, P_xz = P-."""
    c, d, q, r = 0.7, -0.4, 0.3, 0.2
    model = NonAdditiveModel(
        f=lambda x, w: x + w + c * w**2, h=lambda x, v: x + v + d * v**2,
        Q=torch.tensor([[q]], dtype=F64), R=torch.tensor([[r]], dtype=F64), state_dim=1, measurement_dim=1,
    )  # fmt: skip
    m, p, z = 1.5, 0.8, torch.tensor([[[2.3]]], dtype=F64)
    m0, p0 = torch.tensor([m], dtype=F64), torch.tensor([[p]], dtype=F64)
    out = UKF(model, sigma_points=Julier(kappa=1.0), noise="augmented")(z, m0, p0)
    prior_m, prior_p = m + c * q, p + q + 2 * c**2 * q**2
    s = prior_p + r + 2 * d**2 * r**2
    zhat = prior_m + d * r
    assert out.prior_mean[0, 0, 0].item() == pytest.approx(prior_m, rel=1e-13)
    assert out.prior_cov[0, 0, 0, 0].item() == pytest.approx(prior_p, rel=1e-13)
    assert out.mean[0, 0, 0].item() == pytest.approx(prior_m + prior_p / s * (2.3 - zhat), rel=1e-13)
    assert out.cov[0, 0, 0, 0].item() == pytest.approx(prior_p - prior_p**2 / s, rel=1e-13)
    ll = -0.5 * ((2.3 - zhat) ** 2 / s + math.log(2 * math.pi * s))
    assert out.log_likelihood[0, 0].item() == pytest.approx(ll, rel=1e-13)
    # the EKF linearises at zero noise: F_w = 1, H_v = 1
    ekf = EKF(model)(z, m0, p0)
    s_lin = p + q + r
    assert ekf.prior_cov[0, 0, 0, 0].item() == pytest.approx(p + q, rel=1e-13)
    assert ekf.mean[0, 0, 0].item() == pytest.approx(m + (p + q) / s_lin * (2.3 - m), rel=1e-13)
    # independent check of the closed form itself: Monte Carlo of the prediction
    g = torch.Generator().manual_seed(0)
    x = m + math.sqrt(p) * torch.randn(400_000, generator=g, dtype=F64)
    w = math.sqrt(q) * torch.randn(400_000, generator=g, dtype=F64)
    y = x + w + c * w**2
    assert float(y.mean()) == pytest.approx(prior_m, abs=4e-3)
    assert float(y.var()) == pytest.approx(prior_p, rel=1e-2)


def linear_noise_models():
    mats = cv_matrices()
    # five noise inputs drive the four states (so G Q G^T is positive definite), three drive two measurements
    g = torch.tensor(
        [[0.5, 0.0, 0.1, 0.0, 0.0], [1.0, 0.1, 0.0, 0.3, 0.0], [0.0, 0.5, 0.0, 0.0, 0.2], [0.2, 1.0, 0.0, 0.0, 0.4]], dtype=F64
    )
    dmat = torch.tensor([[1.0, 0.3, 0.0], [0.0, 0.5, 1.0]], dtype=F64)
    qw = torch.diag(torch.tensor([0.4, 0.3, 0.2, 0.1, 0.3], dtype=F64))
    qw[0, 1] = qw[1, 0] = 0.1
    rv = torch.diag(torch.tensor([0.5, 0.2, 0.7], dtype=F64))
    noisy = NonAdditiveModel(
        f=lambda x, w: x @ mats["F"].T + w @ g.T, h=lambda x, v: x @ mats["H"].T + v @ dmat.T, Q=qw, R=rv, state_dim=4, measurement_dim=2
    )
    additive = LinearModel(F=mats["F"], H=mats["H"], Q=g @ qw @ g.T, R=dmat @ rv @ dmat.T)
    return noisy, additive


@pytest.mark.parametrize("kind", ["ekf", "ukf", "ukf-reuse"])
def test_noise_entering_linearly_equals_the_additive_kalman_filter_and_smoother(kind):
    noisy, additive = linear_noise_models()
    filt = {
        "ekf": lambda: EKF(noisy),
        "ukf": lambda: UKF(noisy, noise="augmented"),
        "ukf-reuse": lambda: UKF(noisy, noise="augmented", redraw_after_predict=False),
    }[kind]()
    g = torch.Generator().manual_seed(1)
    z = torch.randn(3, 12, 2, generator=g, dtype=F64).cumsum(1)
    mask = torch.rand(3, 12, 2, generator=g) > 0.25
    m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    out = RTSSmoother(filt)(z, m0, p0, mask=mask)
    ref = RTSSmoother(KalmanFilter(additive))(z, m0, p0, mask=mask)
    for name in ("mean", "cov", "cross_cov"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-10)
    torch.testing.assert_close(out.filtered.log_likelihood, ref.filtered.log_likelihood, rtol=0, atol=1e-10)


def test_declared_nonadditive_but_additive_function_equals_the_additive_path():
    mats = cv_matrices()
    f = lambda x: x @ mats["F"].T  # noqa: E731
    h = lambda x: torch.stack([x[..., 0].hypot(x[..., 2]), x[..., 1]], -1)  # noqa: E731
    noisy = NonAdditiveModel(f=lambda x, w: f(x) + w, h=lambda x, v: h(x) + v, Q=mats["Q"], R=mats["R"], state_dim=4, measurement_dim=2)
    from difffilter.models import FunctionalModel

    plain = FunctionalModel(f=f, h=h, Q=mats["Q"], R=mats["R"])
    z = torch.randn(2, 8, 2, dtype=F64, generator=torch.Generator().manual_seed(2)).abs() + 3
    m0, p0 = torch.tensor([3.0, 0.5, 1.0, 0.2], dtype=F64), torch.eye(4, dtype=F64)
    for make in (lambda m: UKF(m, noise="augmented"), EKF):
        a, b = make(noisy)(z, m0, p0), make(plain)(z, m0, p0)
        torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=1e-12)


def test_augmented_ukf_follows_heading_noise_through_the_nonlinearity():
    """Unicycle with heading noise: E[px'] = px + E[cos(theta + w)] = px + cos(m) exp(-(P + s^2) / 2)
    in closed form.  The augmented UKF's sigma points of w pass through cos and see the shrinkage;
    the EKF's linearisation does not."""
    s2 = 0.5**2

    def f(x, w):
        head = x[..., 2] + w[..., 0]
        return torch.stack([x[..., 0] + torch.cos(head), x[..., 1] + torch.sin(head), head], -1)

    model = NonAdditiveModel(
        f=f, h=lambda x: x[..., :2], Q=torch.tensor([[s2]], dtype=F64), R=torch.eye(2, dtype=F64), state_dim=3, nonadditive="f"
    )
    m0 = torch.tensor([0.0, 0.0, 0.3], dtype=F64)
    p0 = torch.diag(torch.tensor([0.1, 0.1, 0.2], dtype=F64))
    z = torch.zeros(1, 1, 2, dtype=F64)
    exact = math.cos(0.3) * math.exp(-(0.2 + s2) / 2)
    ukf = UKF(model, noise="augmented", sigma_points=Julier(kappa=0.0))(z, m0, p0, mask=torch.zeros(1, 1, dtype=torch.bool))
    ekf = EKF(model)(z, m0, p0, mask=torch.zeros(1, 1, dtype=torch.bool))
    err_ukf = abs(ukf.prior_mean[0, 0, 0].item() - exact)
    err_ekf = abs(ekf.prior_mean[0, 0, 0].item() - exact)
    assert err_ekf == pytest.approx(math.cos(0.3) - exact, rel=1e-12)
    assert err_ukf < 0.1 * err_ekf


def test_model_checks_simulation_and_the_additive_ukf_refusal():
    noisy, additive = linear_noise_models()
    with pytest.raises(ValueError, match="augmented"):
        UKF(noisy)
    with pytest.raises(ValueError, match="measurement_dim"):
        NonAdditiveModel(f=lambda x, w: x, h=lambda x, v: x, Q=torch.eye(2), R=torch.eye(2), state_dim=2)
    with pytest.raises(ValueError, match="nonadditive"):
        NonAdditiveModel(f=lambda x: x, h=lambda x: x, Q=torch.eye(2), R=torch.eye(2), state_dim=2, nonadditive="g")
    # the sampler draws w ~ N(0, Q) of the noise dimension and passes it through f
    data = sample_trajectories(noisy, batch_size=4000, num_steps=1, initial_mean=torch.zeros(4), initial_cov=1e-12 * torch.eye(4), seed=0)
    emp = data.truth[:, 0].T.cov()
    torch.testing.assert_close(emp, additive.Q, rtol=0, atol=0.05)
