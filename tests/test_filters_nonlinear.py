"""Nonlinear filters against filterpy, and numerical-robustness cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from difffilter.filters import EKF, UKF, Cubature, Julier, KalmanFilter, MerweScaled, SquareRootUKF
from difffilter.models import FunctionalModel, LinearModel

DT = 1.0
F_CV = np.array([[1, DT, 0, 0], [0, 1, 0, 0], [0, 0, 1, DT], [0, 0, 0, 1.0]])
STATION = np.array([-30.0, 5.0])


def fx_np(x, dt=DT):
    return F_CV @ x


def hx_np(x):
    dx, dy = x[0] - STATION[0], x[2] - STATION[1]
    return np.array([math.hypot(dx, dy), math.atan2(dy, dx)])


def f_t(x):
    F = torch.tensor(F_CV, dtype=x.dtype)
    return x @ F.mT


def h_t(x):
    dx, dy = x[..., 0] - STATION[0], x[..., 2] - STATION[1]
    return torch.stack([torch.sqrt(dx * dx + dy * dy), torch.atan2(dy, dx)], -1)


Q = np.diag([0.05, 0.1, 0.05, 0.1])
R = np.diag([0.5**2, 0.02**2])


def range_bearing_data(T=40, seed=0):
    rng = np.random.default_rng(seed)
    x = np.array([10.0, 1.0, 20.0, -0.5])
    zs = []
    for _ in range(T):
        x = fx_np(x) + rng.multivariate_normal(np.zeros(4), Q)
        zs.append(hx_np(x) + rng.multivariate_normal(np.zeros(2), R))
    return np.array(zs)


def rb_model():
    return FunctionalModel(f=f_t, h=h_t, Q=torch.tensor(Q), R=torch.tensor(R))


@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.3, 2.0, 1.0), (1e-3, 2.0, 0.0), (0.8, 0.0, -1.0)])
def test_ukf_matches_filterpy_every_step(alpha, beta, kappa):
    z = range_bearing_data()
    x0, P0 = np.array([9.0, 0.5, 21.0, 0.0]), np.diag([4.0, 1.0, 4.0, 1.0])
    ref = UnscentedKalmanFilter(dim_x=4, dim_z=2, dt=DT, hx=hx_np, fx=fx_np, points=MerweScaledSigmaPoints(4, alpha, beta, kappa))
    ref.x, ref.P, ref.Q, ref.R = x0.copy(), P0.copy(), Q, R
    res = UKF(rb_model(), sigma_points=MerweScaled(alpha=alpha, beta=beta, kappa=kappa))(
        torch.tensor(z)[None], torch.tensor(x0), torch.tensor(P0)
    )
    tol = 1e-8 if alpha > 1e-2 else 1e-6  # |W0| ~ 1e6 amplifies rounding in both codes
    for t in range(len(z)):
        ref.predict()
        np.testing.assert_allclose(res.prior_mean[0, t].detach().numpy(), ref.x, atol=tol, rtol=0)
        ref.update(z[t])
        np.testing.assert_allclose(res.mean[0, t].detach().numpy(), ref.x, atol=tol, rtol=0)
        np.testing.assert_allclose(res.cov[0, t].detach().numpy(), ref.P, atol=tol, rtol=0)
        np.testing.assert_allclose(float(res.log_likelihood[0, t].detach()), ref.log_likelihood, atol=tol * 10, rtol=0)


def test_ekf_matches_filterpy_every_step():
    z = range_bearing_data(seed=1)
    x0, P0 = np.array([9.0, 0.5, 21.0, 0.0]), np.diag([4.0, 1.0, 4.0, 1.0])
    ref = ExtendedKalmanFilter(dim_x=4, dim_z=2)
    ref.x, ref.P, ref.Q, ref.R, ref.F = x0.copy(), P0.copy(), Q, R, F_CV

    def hjac(x):
        dx, dy = x[0] - STATION[0], x[2] - STATION[1]
        r2 = dx * dx + dy * dy
        r = math.sqrt(r2)
        return np.array([[dx / r, 0, dy / r, 0], [-dy / r2, 0, dx / r2, 0]])

    res = EKF(rb_model())(torch.tensor(z)[None], torch.tensor(x0), torch.tensor(P0))
    for t in range(len(z)):
        ref.predict()
        ref.update(z[t], hjac, hx_np)
        np.testing.assert_allclose(res.mean[0, t].detach().numpy(), ref.x, atol=1e-8, rtol=0)
        np.testing.assert_allclose(res.cov[0, t].detach().numpy(), ref.P, atol=1e-8, rtol=0)
        np.testing.assert_allclose(float(res.log_likelihood[0, t].detach()), ref.log_likelihood, atol=1e-8, rtol=0)


def test_kalman_matches_filterpy_kalman():
    from filterpy.kalman import KalmanFilter as FilterpyKF

    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    Rl = np.array([[1.0, 0.3], [0.3, 2.0]])
    rng = np.random.default_rng(3)
    z = rng.normal(size=(30, 2)).cumsum(0)
    x0, P0 = np.array([0.5, 0.0, -0.5, 0.1]), np.eye(4) * 3
    ref = FilterpyKF(dim_x=4, dim_z=2)
    ref.x, ref.P, ref.F, ref.H, ref.Q, ref.R = x0.copy(), P0.copy(), F_CV, H, Q, Rl
    model = LinearModel(F=torch.tensor(F_CV), H=torch.tensor(H), Q=torch.tensor(Q), R=torch.tensor(Rl))
    res = KalmanFilter(model)(torch.tensor(z)[None], torch.tensor(x0), torch.tensor(P0))
    for t in range(30):
        ref.predict()
        ref.update(z[t])
        np.testing.assert_allclose(res.mean[0, t].detach().numpy(), ref.x, atol=1e-9, rtol=0)
        np.testing.assert_allclose(res.cov[0, t].detach().numpy(), ref.P, atol=1e-9, rtol=0)
        np.testing.assert_allclose(float(res.log_likelihood[0, t].detach()), ref.log_likelihood, atol=1e-9, rtol=0)


def _gpsdr_like(dtype):
    """8-state p000-style model (CA per axis, yaw-rate and odometer measurements)."""
    T = 0.1
    a = torch.tensor([[1, T, T * T / 2], [0, 1, T], [0, 0, 1]], dtype=dtype)
    F = torch.block_diag(a, a, torch.tensor([[math.exp(-T / 100)]], dtype=dtype), torch.eye(1, dtype=dtype))

    def f(x):
        return x @ F.mT

    def h(x):
        ve, ae, vn, an, eps, psi = x[..., 1], x[..., 2], x[..., 4], x[..., 5], x[..., 6], x[..., 7]
        v2 = ve * ve + vn * vn + 1e-6
        return torch.stack([x[..., 0], x[..., 3], (vn * ae - ve * an) / v2 + eps, psi * T * torch.sqrt(v2)], -1)

    q1 = torch.tensor([[T**5 / 20, T**4 / 8, T**3 / 6], [T**4 / 8, T**3 / 3, T**2 / 2], [T**3 / 6, T**2 / 2, T]], dtype=dtype)
    Qm = torch.block_diag(2 * q1, 2 * q1, torch.diag(torch.tensor([1e-8, 1e-8], dtype=dtype)))
    Rm = torch.diag(torch.tensor([15.0**2, 15.0**2, math.radians(0.4) ** 2, 1.0], dtype=dtype))
    return FunctionalModel(f=f, h=h, Q=Qm, R=Rm), F, h


def _gpsdr_data(steps, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    model, F, h = _gpsdr_like(torch.float64)
    x = torch.tensor([0.0, 10, 0, 0, 10, 0, 0, 1], dtype=torch.float64)
    zs = []
    Rc = torch.linalg.cholesky(model.R.detach())
    for k in range(steps):
        x = F @ x
        x[2] = 0.5 * math.sin(0.01 * k)  # gentle manoeuvre in the east acceleration
        zs.append(h(x) + Rc @ torch.randn(4, generator=g, dtype=torch.float64))
    return torch.stack(zs)[None].to(dtype)


def test_julier_negative_center_weight_8_states_2000_steps_finite():
    model, _, _ = _gpsdr_like(torch.float64)
    z = _gpsdr_data(2000, torch.float64)
    x0 = torch.tensor([0.0, 10, 0, 0, 10, 0, 0, 1], dtype=torch.float64)
    for reuse in (False, True):
        flt = UKF(model, sigma_points=Julier(kappa=3.0 - 8), redraw_after_predict=not reuse)
        res = flt(z, x0, torch.eye(8, dtype=torch.float64))
        assert torch.isfinite(res.mean).all() and torch.isfinite(res.cov).all()
        assert torch.isfinite(res.log_likelihood).all()
        err = (res.mean[0, :, [0, 3]] - z[0, :, :2]).abs()
        assert float(err[-500:].mean()) < 15.0  # tracks, does not diverge


def _mp_kalman(z, F, H, Q, R, x0, P0):
    """Kalman filter in 60-digit arithmetic (mpmath): the exact reference."""
    import mpmath as mp

    mp.mp.dps = 60
    M = lambda a: mp.matrix(a.tolist())  # noqa: E731
    F_, H_, Q_, R_ = M(F), M(H), M(Q), M(R)
    x, P = M(x0.reshape(-1, 1)), M(P0)
    out = []
    for zt in z:
        x, P = F_ * x, F_ * P * F_.T + Q_
        S = H_ * P * H_.T + R_
        K = P * H_.T * mp.inverse(S)
        x = x + K * (M(zt.reshape(-1, 1)) - H_ * x)
        P = P - K * S * K.T
        out.append((np.array(x.tolist(), dtype=float).ravel(), np.array(P.tolist(), dtype=float)))
    return out


def test_square_root_ukf_huge_prior_tiny_noise_matches_exact_kalman():
    # P0 = 1e24 I with R = 1e-8: the covariance form loses 16+ digits in the first update.
    dtype = torch.float64
    F = torch.tensor(F_CV, dtype=dtype)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=dtype)
    Qm = torch.eye(4, dtype=dtype) * 1e-2
    Rm = torch.eye(2, dtype=dtype) * 1e-8
    z = torch.tensor([[1.0, 2.0], [2.1, 2.9], [3.0, 4.2], [4.1, 5.0], [5.0, 6.1], [6.2, 6.8]], dtype=dtype)
    model = LinearModel(F=F, H=H, Q=Qm, R=Rm)
    P0 = torch.eye(4, dtype=dtype) * 1e24
    ref = _mp_kalman(z.numpy(), F.numpy(), H.numpy(), Qm.numpy(), Rm.numpy(), np.zeros(4), P0.numpy())
    for sp in (MerweScaled(alpha=1.0, beta=2.0, kappa=0.0), Julier(kappa=-1.0)):
        res = SquareRootUKF(model, sigma_points=sp)(z[None], torch.zeros(4, dtype=dtype), P0)
        assert torch.isfinite(res.mean).all() and torch.isfinite(res.cov).all()
        for t, (xr, Pr) in enumerate(ref):
            np.testing.assert_allclose(res.mean[0, t].detach().numpy(), xr, atol=5e-3, rtol=0)
            cov = res.cov[0, t].detach().numpy()
            # absolute 5e-3 on every entry (the position variances are ~1e-8 and keep the
            # float64 rounding floor of a 1e12-std prior, ~5e-7), and 5e-3 relative on the
            # large first-step velocity variances
            np.testing.assert_allclose(cov, Pr, atol=5e-3, rtol=5e-3)
            assert np.linalg.eigvalsh(cov).min() > 0


@pytest.mark.parametrize("flt_cls", ["ukf", pytest.param("ekf", marks=pytest.mark.slow), pytest.param("cubature", marks=pytest.mark.slow)])
def test_long_float32_nonlinear_loss_and_gradients_finite(flt_cls):
    model, _, _ = _gpsdr_like(torch.float32)
    z = _gpsdr_data(5000, torch.float32, seed=2)
    flt = {"ukf": lambda: UKF(model), "ekf": lambda: EKF(model), "cubature": lambda: UKF(model, sigma_points=Cubature())}[flt_cls]()
    x0 = torch.tensor([0.0, 10, 0, 0, 10, 0, 0, 1])
    res = flt(z, x0, torch.eye(8))
    loss = -res.log_likelihood.mean()
    assert torch.isfinite(loss)
    loss.backward()
    grads = [p.grad for p in flt.parameters() if p.requires_grad]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)


def test_controls_reach_f_and_h_in_every_filter():
    # f(x, u) = x + u["v"] * u["dt"]; h(x, u) = x - u["offset"]: a KF reference with the same inputs
    def f(x, u):
        return x + u["v"] * u["dt"]

    def h(x, u):
        return x - u["offset"]

    B, T = 2, 8
    g = torch.Generator().manual_seed(0)
    u = {
        "v": torch.randn(B, T, 2, generator=g, dtype=torch.float64),
        "dt": torch.full((B, T, 1), 0.5, dtype=torch.float64),
        "offset": torch.randn(B, T, 2, generator=g, dtype=torch.float64),
    }
    z = torch.randn(B, T, 2, generator=g, dtype=torch.float64)
    model = FunctionalModel(f=f, h=h, Q=torch.eye(2, dtype=torch.float64) * 0.1, R=torch.eye(2, dtype=torch.float64), controls=True)
    ref_m, P = torch.zeros(B, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).expand(B, 2, 2)
    ref = []
    for t in range(T):
        ref_m = ref_m + u["v"][:, t] * 0.5
        P = P + 0.1 * torch.eye(2, dtype=torch.float64)
        S = P + torch.eye(2, dtype=torch.float64)
        K = torch.linalg.solve(S, P).mT
        ref_m = ref_m + (K @ (z[:, t] + u["offset"][:, t] - ref_m)[..., None])[..., 0]
        P = P - K @ S @ K.mT
        ref.append(ref_m)
    ref = torch.stack(ref, 1)
    for flt in (EKF(model), UKF(model), UKF(model, redraw_after_predict=False), SquareRootUKF(model), UKF(model, noise="augmented")):
        res = flt(z, torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), controls=u)
        torch.testing.assert_close(res.mean, ref, rtol=0, atol=1e-9)
