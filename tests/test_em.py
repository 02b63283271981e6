"""EM for Q, R (and an IMM's transition) against references written from the equations: a numpy
Kalman filter, RTS smoother and lag-one covariance (de Jong's ``P_{t,t-1|T} = P_{t|T} J_{t-1}^T``)
with Shumway and Stoffer's sufficient statistics ``S11, S10, S00``; the maximum of the exact
log-likelihood found by scipy; recovery of the simulating values; monotone likelihood."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, UKF, KalmanFilter
from difffilter.learn import fit_em
from difffilter.mixers import IMM
from difffilter.models import FunctionalModel, LinearModel
from difffilter.sim import simulate
from difffilter.smoothers import IMMSmoother, RTSSmoother, measurement_residual_moments, transition_residual_moments

F64 = torch.float64
F_ = np.array([[0.9, 0.2], [0.0, 0.7]])
H_ = np.array([[1.0, 0.0], [0.5, 1.0]])
Q_TRUE = np.array([[0.5, 0.1], [0.1, 0.3]])
R_TRUE = np.array([[1.0, 0.3], [0.3, 0.8]])
M0 = np.array([1.0, -1.0])
P0 = np.array([[2.0, 0.2], [0.2, 1.0]])


def t(x, dtype=F64):
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def linear(Q=Q_TRUE, R=R_TRUE, dtype=F64, **kw):
    return LinearModel(F=t(F_, dtype), H=t(H_, dtype), Q=t(Q, dtype), R=t(R, dtype), **kw)


def data(B=6, T=60, seed=0, missing=0.0):
    return simulate(linear(), num_steps=T, batch_size=B, initial_mean=t(M0), initial_cov=t(P0), seed=seed, missing_prob=missing)


# -- independent numpy reference ---------------------------------------------------------------
def np_smoother(z, obs, m0, p0, F, H, Q, R, offsets=None):
    """Kalman filter + RTS + lag-one covariance for one trajectory; x_{-1} ~ N(m0, p0),
    x_k = F x_{k-1} + offsets_k + w_k."""
    T = len(z)
    off = np.zeros((T, len(m0))) if offsets is None else offsets
    mf, pf, mp, pp, ll = [], [], [], [], 0.0
    m, p = m0, p0
    for k in range(T):
        m_pr, p_pr = F @ m + off[k], F @ p @ F.T + Q
        o = obs[k]
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ p_pr @ Ho.T + Ro
            e = z[k][o] - Ho @ m_pr
            K = np.linalg.solve(S, Ho @ p_pr).T
            m, p = m_pr + K @ e, p_pr - K @ S @ K.T
            ll += -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
        else:
            m, p = m_pr, p_pr
        mf.append(m), pf.append(p), mp.append(m_pr), pp.append(p_pr)
    ms, ps = [None] * (T + 1), [None] * (T + 1)  # index k + 1 holds x_k; index 0 holds x_{-1}
    lag = [None] * T  # lag[k] = Cov(x_k, x_{k-1} | all)
    ms[T], ps[T] = mf[-1], pf[-1]
    for k in range(T - 1, -1, -1):
        m_prev, p_prev = (mf[k - 1], pf[k - 1]) if k > 0 else (m0, p0)
        J = p_prev @ F.T @ np.linalg.inv(pp[k])
        lag[k] = ps[k + 1] @ J.T
        ms[k] = m_prev + J @ (ms[k + 1] - mp[k])
        ps[k] = p_prev + J @ (ps[k + 1] - pp[k]) @ J.T
    return np.array(ms), np.array(ps), np.array(lag), ll


def np_em_statistics(z, obs, m0, p0, F, H, Q, R, offsets=None):
    """Per-step A_t from S11 - S10 F^T - F S10^T + F S00 F^T (about the offset), M_t, and the
    log-likelihood."""
    ms, ps, lag, ll = np_smoother(z, obs, m0, p0, F, H, Q, R, offsets)
    off = np.zeros((len(z), len(m0))) if offsets is None else offsets
    A, M = [], []
    for k in range(len(z)):
        y = ms[k + 1] - off[k]  # x_k - c_k has the same covariances as x_k
        s11 = np.outer(y, y) + ps[k + 1]
        s10 = np.outer(y, ms[k]) + lag[k]
        s00 = np.outer(ms[k], ms[k]) + ps[k]
        A.append(s11 - s10 @ F.T - F @ s10.T + F @ s00 @ F.T)
        zk = np.where(obs[k], z[k], 0.0)
        r = zk - H @ ms[k + 1]
        mk = np.outer(r, r) + H @ ps[k + 1] @ H.T
        M.append(mk * np.outer(obs[k], obs[k]))
    return np.array(A), np.array(M), ll, ms[0], ps[0]


def np_loglik(zs, obs, m0, p0, F, H, Q, R):
    """Exact log-likelihood of fully observed trajectories ``zs [B, T, m]`` (Kalman filter only)."""
    if not obs.all():
        return sum(np_smoother(z, o, m0, p0, F, H, Q, R)[3] for z, o in zip(zs, obs, strict=True))
    # every trajectory at once: the same recursion with a leading batch dimension
    B = len(zs)
    m, p, total = np.tile(m0, (B, 1)), np.tile(p0, (B, 1, 1)), 0.0
    for k in range(zs.shape[1]):
        m, p = m @ F.T, F @ p @ F.T + Q
        S = H @ p @ H.T + R
        e = zs[:, k] - m @ H.T
        K = np.linalg.solve(S, H @ p).transpose(0, 2, 1)
        m, p = m + (K @ e[..., None])[..., 0], p - K @ S @ K.transpose(0, 2, 1)
        quad = (e[:, None, :] @ np.linalg.solve(S, e[..., None]))[:, 0, 0]
        total += float(np.sum(-0.5 * (quad + np.linalg.slogdet(2 * np.pi * S)[1])))
    return total


# -- E-step and one M-step against the reference ------------------------------------------------
@pytest.mark.parametrize("missing", [0.0, 0.3])
def test_e_step_statistics_match_numpy_rts_with_lag_one(missing):
    d = data(B=3, T=25, missing=missing)
    Q0, R0 = np.diag([1.0, 2.0]), np.array([[2.0, -0.4], [-0.4, 1.5]])
    kf = KalmanFilter(linear(Q0, R0))
    with torch.no_grad():
        sm = RTSSmoother(kf)(d.measurements, d.initial_mean, d.initial_cov, mask=d.mask)
        A = transition_residual_moments(kf, sm)
        M = measurement_residual_moments(kf, sm, d.measurements, d.mask)
    obs = np.ones((3, 25, 2), bool) if d.mask is None else np.repeat(d.mask.numpy()[..., None], 2, -1)
    for b in range(3):
        A_ref, M_ref, ll, _, _ = np_em_statistics(d.measurements[b].numpy(), obs[b], M0, P0, F_, H_, Q0, R0)
        np.testing.assert_allclose(A[b].numpy(), A_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(M[b].numpy(), M_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(float(sm.filtered.log_likelihood[b].sum()), ll, rtol=1e-10)
    assert torch.isfinite(M).all()


def test_one_em_iteration_is_the_closed_form_m_step():
    d = data(B=4, T=30, missing=0.2)
    Q0, R0 = np.diag([1.0, 2.0]), np.array([[2.0, -0.4], [-0.4, 1.5]])
    kf = KalmanFilter(linear(Q0, R0))
    res = fit_em(kf, d.measurements, d.initial_mean, d.initial_cov, mask=d.mask, num_iters=1, learn=["Q", "R"])
    obs = np.repeat(d.mask.numpy()[..., None], 2, -1)
    stats = [np_em_statistics(d.measurements[b].numpy(), obs[b], M0, P0, F_, H_, Q0, R0) for b in range(4)]
    Q_ref = sum(s[0].sum(0) for s in stats) / (4 * 30)
    R_ref = sum(s[1].sum(0) for s in stats) / obs[..., 0].sum()  # missing steps contribute nothing
    np.testing.assert_allclose(kf.model.Q.detach().numpy(), Q_ref, rtol=1e-8)
    np.testing.assert_allclose(kf.model.R.detach().numpy(), R_ref, rtol=1e-8)
    assert res.num_iters == 1 and len(res.log_likelihoods) == 2
    np.testing.assert_allclose(res.log_likelihoods[0], sum(s[2] for s in stats), rtol=1e-10)
    ll_after = np_loglik(d.measurements.numpy(), obs, M0, P0, F_, H_, Q_ref, R_ref)
    np.testing.assert_allclose(res.log_likelihoods[1], ll_after, rtol=1e-8)
    np.testing.assert_allclose(res.values["model.dynamics.Q"].numpy(), Q_ref, rtol=1e-8)


def test_diffuse_prior_leaves_out_the_first_transition():
    d = data(B=2, T=30, seed=15)
    Q0, R0 = np.diag([1.0, 2.0]), np.diag([2.0, 1.5])
    kf = KalmanFilter(linear(Q0, R0))
    wide = 1e10 * np.eye(2)  # wide enough for the filter to start in exact diffuse form
    fit_em(kf, d.measurements, d.initial_mean, t(wide), num_iters=1)
    obs = np.ones((30, 2), bool)
    stats = [np_em_statistics(d.measurements[b].numpy(), obs, M0, wide, F_, H_, Q0, R0) for b in range(2)]
    np.testing.assert_allclose(kf.model.Q.detach().numpy(), sum(s[0][1:].sum(0) for s in stats) / 58, rtol=1e-4)
    np.testing.assert_allclose(kf.model.R.detach().numpy(), sum(s[1].sum(0) for s in stats) / 60, rtol=1e-4)
    with pytest.raises(ValueError, match="diffuse"):
        fit_em(kf, d.measurements, d.initial_mean, t(wide), learn=["Q", "initial_cov"])


def test_controls_enter_the_e_step():
    B_ = np.array([[0.5], [1.0]])
    u = torch.sin(torch.arange(30, dtype=F64) / 3.0)[None, :, None].expand(2, 30, 1).contiguous()
    truth = linear(B=t(B_))
    d = simulate(truth, num_steps=30, batch_size=2, initial_mean=t(M0), initial_cov=t(P0), seed=13, controls=u)
    Q0, R0 = np.diag([1.0, 2.0]), np.diag([2.0, 1.5])
    kf = KalmanFilter(linear(Q0, R0, B=t(B_)))
    fit_em(kf, d.measurements, d.initial_mean, d.initial_cov, controls=u, num_iters=1)
    obs = np.ones((30, 2), bool)
    stats = [np_em_statistics(d.measurements[b].numpy(), obs, M0, P0, F_, H_, Q0, R0, u[b].numpy() @ B_.T) for b in range(2)]
    np.testing.assert_allclose(kf.model.Q.detach().numpy(), sum(s[0].sum(0) for s in stats) / 60, rtol=1e-8)
    np.testing.assert_allclose(kf.model.R.detach().numpy(), sum(s[1].sum(0) for s in stats) / 60, rtol=1e-8)


# -- exact EM: monotone, its fixed point is the maximum of the likelihood -----------------------
@pytest.mark.parametrize("structure", ["full", "diagonal", "scalar"])
def test_linear_em_log_likelihood_never_decreases(structure):
    d = data(B=4, T=40, seed=1)
    model = linear(np.diag([2.0, 0.5]), np.diag([0.3, 3.0]), Q_structure=structure, R_structure=structure)
    res = fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=12, tol=0.0)
    ll = np.array(res.log_likelihoods)
    assert len(ll) == 13 and ll[-1] > ll[0] + 1.0
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))


def test_per_component_mask_full_r_is_exact_em():
    d = data(B=4, T=40, seed=2)
    g = torch.Generator().manual_seed(5)
    mask = torch.rand(4, 40, 2, generator=g) > 0.35
    z = torch.where(mask, d.measurements, torch.full_like(d.measurements, float("nan")))
    model = linear(np.diag([2.0, 0.5]), np.array([[0.5, -0.2], [-0.2, 3.0]]))
    res = fit_em(KalmanFilter(model), z, d.initial_mean, d.initial_cov, mask=mask, num_iters=10, tol=0.0)
    ll = np.array(res.log_likelihoods)
    assert np.isfinite(ll).all() and torch.isfinite(model.R).all()
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:])) and ll[-1] > ll[0]
    # a diagonal R counts each observed component: its M-step is sum_obs M_ii / #obs_i
    model_d = linear(np.diag([2.0, 0.5]), np.diag([0.5, 3.0]), R_structure="diagonal")
    kf = KalmanFilter(model_d)
    with torch.no_grad():
        sm = RTSSmoother(kf)(z, d.initial_mean, d.initial_cov, mask=mask)
        M = measurement_residual_moments(kf, sm, z, mask)
    want = torch.diagonal(M, dim1=-2, dim2=-1).sum((0, 1)) / mask.sum((0, 1))
    fit_em(kf, z, d.initial_mean, d.initial_cov, mask=mask, num_iters=1, learn=["R"])
    torch.testing.assert_close(torch.diagonal(model_d.R), want)


SCALAR_F, SCALAR_H = np.array([[0.8]]), np.array([[1.0]])


@pytest.fixture(scope="module")
def scalar_ml():
    """Data of a scalar AR(1) model and the maximum of its exact log-likelihood over (Q, R), by scipy."""
    optimize = pytest.importorskip("scipy.optimize")
    m0, p0 = np.zeros(1), np.eye(1)
    truth = LinearModel(F=t(SCALAR_F), H=t(SCALAR_H), Q=t([[0.4]]), R=t([[1.0]]))
    d = simulate(truth, num_steps=60, batch_size=4, initial_mean=t(m0), initial_cov=t(p0), seed=3)
    zs, obs = d.measurements.numpy(), np.ones((4, 60, 1), bool)

    def nll(theta):
        return -np_loglik(zs, obs, m0, p0, SCALAR_F, SCALAR_H, np.exp(theta[:1])[:, None], np.exp(theta[1:])[:, None])

    opt = optimize.minimize(nll, np.log([0.2, 2.0]), method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-11, "maxiter": 2000})
    return d, np.exp(opt.x), -opt.fun


def test_scalar_em_fixed_point_is_the_scipy_maximum_likelihood(scalar_ml):
    d, (q_ml, r_ml), _ = scalar_ml
    # the maximum is an EM fixed point: one EM step from it does not move
    model = LinearModel(F=t(SCALAR_F), H=t(SCALAR_H), Q=t([[q_ml]]), R=t([[r_ml]]))
    fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=1)
    np.testing.assert_allclose([float(model.Q.detach()), float(model.R.detach())], [q_ml, r_ml], rtol=2e-4)
    # while one step from elsewhere does
    model = LinearModel(F=t(SCALAR_F), H=t(SCALAR_H), Q=t([[2 * q_ml]]), R=t([[r_ml]]))
    fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=1)
    assert abs(float(model.Q.detach()) / q_ml - 1) > 0.05


@pytest.mark.slow
def test_scalar_em_from_far_climbs_to_the_scipy_maximum(scalar_ml):
    d, (q_ml, r_ml), ll_ml = scalar_ml
    model = LinearModel(F=t(SCALAR_F), H=t(SCALAR_H), Q=t([[0.05]]), R=t([[4.0]]))
    res = fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=30, tol=0.0)
    gap = ll_ml - np.array(res.log_likelihoods)
    # never above the maximum, monotone, and 98 % of the way there after 30 iterations (EM's
    # convergence is linear and slow along the ridge where Q and R trade off)
    assert gap.min() >= -1e-8 and np.all(np.diff(gap) <= 1e-9) and gap[-1] < 0.02 * gap[0]
    np.testing.assert_allclose([float(model.Q.detach()), float(model.R.detach())], [q_ml, r_ml], rtol=0.3)


@pytest.mark.slow
def test_linear_em_recovers_the_simulating_q_and_r():
    d = data(B=32, T=150, seed=4)
    model = linear(np.diag([2.0, 2.0]), np.diag([4.0, 0.2]))
    res = fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=60, tol=1e-9)
    # 4800 transitions; Q and R trade off against each other, so the ML estimate scatters by
    # about 0.05 around the truth here: tolerance 0.12 on every entry
    np.testing.assert_allclose(model.Q.detach().numpy(), Q_TRUE, atol=0.12)
    np.testing.assert_allclose(model.R.detach().numpy(), R_TRUE, atol=0.12)
    assert res.cpu_seconds > 0


def test_linear_em_from_far_reaches_the_neighbourhood_of_the_truth():
    d = data(B=8, T=100, seed=4)
    model = linear(np.diag([1.0, 1.0]), np.diag([2.0, 0.4]))
    res = fit_em(KalmanFilter(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=20, tol=0.0)
    # start: entries up to 1.0 away (R_11 twice the truth, R_22 half of it); after 20 iterations
    # every entry within 0.15 of the truth (800 steps: the ML estimate itself scatters by ~0.05)
    np.testing.assert_allclose(model.Q.detach().numpy(), Q_TRUE, atol=0.15)
    np.testing.assert_allclose(model.R.detach().numpy(), R_TRUE, atol=0.15)
    assert res.log_likelihoods[-1] > res.log_likelihoods[0] + 100


def test_initial_moments_estimated_and_monotone():
    d = data(B=8, T=20, seed=6)
    model = linear(np.diag([2.0, 0.5]), np.diag([0.3, 3.0]))
    res = fit_em(
        KalmanFilter(model), d.measurements, torch.zeros(2, dtype=F64), 5 * torch.eye(2, dtype=F64), num_iters=8, tol=0.0,
        learn=["Q", "R", "initial_mean", "initial_cov"],
    )  # fmt: skip
    ll = np.array(res.log_likelihoods)
    assert np.all(np.diff(ll) >= -1e-9 * np.abs(ll[1:]))
    assert res.initial_mean.shape == (2,) and res.initial_cov.shape == (2, 2)
    assert float(torch.linalg.eigvalsh(res.initial_cov).min()) > 0
    assert torch.equal(res.values["initial_mean"], res.initial_mean)


def test_float32_matches_float64():
    d = data(B=4, T=40, seed=7)
    out = {}
    for dtype in (torch.float32, F64):
        model = linear(np.diag([2.0, 0.5]), np.diag([0.3, 3.0]), dtype=dtype)
        fit_em(KalmanFilter(model), d.measurements.to(dtype), d.initial_mean.to(dtype), d.initial_cov.to(dtype), num_iters=3, tol=0.0)
        assert model.Q.dtype == dtype
        out[dtype] = (model.Q.detach().double(), model.R.detach().double())
    torch.testing.assert_close(out[torch.float32][0], out[F64][0], rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(out[torch.float32][1], out[F64][1], rtol=1e-3, atol=1e-4)


def test_nan_under_mask_never_reaches_the_estimates():
    d = data(B=3, T=30, seed=8, missing=0.3)
    assert torch.isnan(d.measurements).any()
    z_clean = torch.where(d.mask[..., None], d.measurements, torch.zeros_like(d.measurements))
    outs = []
    for z in (d.measurements, z_clean):
        model = linear(np.diag([2.0, 0.5]), np.diag([0.3, 3.0]))
        fit_em(KalmanFilter(model), z, d.initial_mean, d.initial_cov, mask=d.mask, num_iters=2)
        outs.append((model.Q.detach(), model.R.detach()))
    assert torch.isfinite(outs[0][0]).all() and torch.isfinite(outs[0][1]).all()
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)


# -- nonlinear (approximate E-step) ------------------------------------------------------------
def pendulum(q, r, dtype=F64):
    """A pendulum (angle, rate) seen through sin(angle) and the rate; analytic Jacobians."""
    dt = 0.1

    def f(x):
        return torch.stack([x[..., 0] + dt * x[..., 1], x[..., 1] - dt * 9.81 * torch.sin(x[..., 0])], -1)

    def f_jac(x):
        one = torch.ones_like(x[..., 0])
        rows = [torch.stack([one, dt * one], -1), torch.stack([-dt * 9.81 * torch.cos(x[..., 0]), one], -1)]
        return torch.stack(rows, -2)

    def h(x):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)

    def h_jac(x):
        one, zero = torch.ones_like(x[..., 0]), torch.zeros_like(x[..., 0])
        return torch.stack([torch.stack([torch.cos(x[..., 0]), zero], -1), torch.stack([zero, one], -1)], -2)

    return FunctionalModel(
        f=f, h=h, f_jacobian=f_jac, h_jacobian=h_jac, Q=t(np.diag(q), dtype), R=t(np.diag(r), dtype),
        Q_structure="diagonal", R_structure="diagonal",
    )  # fmt: skip


@pytest.mark.parametrize("kind", [UKF, pytest.param(EKF, marks=pytest.mark.slow)])
def test_nonlinear_em_improves_likelihood_and_approaches_truth(kind):
    q_true, r_true = np.array([0.01, 0.01]), np.array([0.05, 0.05])
    q0, r0 = q_true * [3.0, 1 / 3], r_true * [1 / 3, 3.0]
    m0, p0 = t([0.5, 0.0]), t(np.diag([0.1, 0.1]))
    d = simulate(pendulum(q_true, r_true), num_steps=60, batch_size=8, initial_mean=m0, initial_cov=p0, seed=9)
    model = pendulum(q0, r0)
    res = fit_em(kind(model), d.measurements, d.initial_mean, d.initial_cov, num_iters=20, tol=0.0)
    assert res.log_likelihoods[-1] > res.log_likelihoods[0] + 100
    q, r = torch.diagonal(model.Q).detach().numpy(), torch.diagonal(model.R).detach().numpy()
    # approximate EM (its likelihood need not rise at every step, and its fixed point is that of
    # the filter's approximation, not the truth's ML): every value moved towards the truth, R
    # within 25 %, Q within a factor 2.5 after 20 iterations
    assert np.all(np.abs(np.log(q / q_true)) < np.abs(np.log(q0 / q_true)))
    assert np.all(np.abs(np.log(r / r_true)) < np.abs(np.log(r0 / r_true)))
    np.testing.assert_allclose(r, r_true, rtol=0.25)
    assert np.all(np.abs(np.log(q / q_true)) < np.log(2.5))


def test_unscented_e_step_equals_linearised_on_a_linear_model():
    d = data(B=2, T=15, seed=10)
    Q0, R0 = np.diag([1.0, 2.0]), np.diag([2.0, 1.5])
    kf, ukf = KalmanFilter(linear(Q0, R0)), UKF(linear(Q0, R0))
    stats = []
    with torch.no_grad():
        for filt in (kf, ukf):
            sm = RTSSmoother(filt)(d.measurements, d.initial_mean, d.initial_cov)
            stats.append((transition_residual_moments(filt, sm), measurement_residual_moments(filt, sm, d.measurements)))
    torch.testing.assert_close(stats[1], stats[0], rtol=1e-7, atol=1e-9)


# -- IMM: transition matrix from expected transition counts ------------------------------------
PI_TRUE = np.array([[0.95, 0.05], [0.1, 0.9]])


def switching_walk(B, T, seed, qs=(0.01, 4.0), r=0.1):
    """A random walk whose process-noise variance switches between ``qs`` by the chain PI_TRUE."""
    g = torch.Generator().manual_seed(seed)
    s = torch.zeros(B, dtype=torch.long)
    x = torch.zeros(B, dtype=F64)
    zs = []
    for _ in range(T):
        s = torch.where(torch.rand(B, generator=g) < torch.tensor(PI_TRUE[:, 1])[s], 1, 0)
        x = x + torch.randn(B, generator=g, dtype=F64) * torch.tensor(qs, dtype=F64)[s].sqrt()
        zs.append(x + r**0.5 * torch.randn(B, generator=g, dtype=F64))
    modes = [KalmanFilter(LinearModel(F=t([[1.0]]), H=t([[1.0]]), Q=t([[q]]), R=t([[r]]))) for q in qs]
    imm = IMM(modes, transition=t([[0.7, 0.3], [0.3, 0.7]]), initial_probs=t([0.5, 0.5]))
    return imm, torch.stack(zs, 1)[..., None]


@pytest.mark.slow
def test_imm_transition_estimate_close_to_truth():
    imm, z = switching_walk(6, 300, 11)
    res = fit_em(imm, z, torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64), num_iters=10)
    np.testing.assert_allclose(imm.transition.detach().numpy(), PI_TRUE, atol=0.05)
    assert set(res.values) == {"transition", "initial_probs"}
    assert res.log_likelihoods[-1] > res.log_likelihoods[0]


def test_imm_transition_moves_towards_truth_and_stays_stochastic():
    imm, z = switching_walk(3, 120, 12)
    start = imm.transition.detach().clone()
    res = fit_em(imm, z, torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64), num_iters=2, learn=["transition"])
    pi = imm.transition.detach()
    assert float((pi - torch.tensor(PI_TRUE)).abs().max()) < 0.5 * float((start - torch.tensor(PI_TRUE)).abs().max())
    torch.testing.assert_close(pi.sum(-1), torch.ones(2, dtype=F64))
    assert set(res.values) == {"transition"} and res.log_likelihoods[-1] > res.log_likelihoods[0]
    torch.testing.assert_close(imm.initial_probs.detach(), torch.tensor([0.5, 0.5], dtype=F64))


def test_imm_smoother_pair_probabilities_are_consistent():
    imm, z = switching_walk(2, 40, 14)
    with torch.no_grad():
        out = IMMSmoother(imm)(z, torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
    pairs = out.mode_pair_probs  # [B, T, j (at t-1), i (at t)]
    assert pairs.shape == (2, 40, 2, 2) and bool((pairs >= 0).all())
    torch.testing.assert_close(pairs.sum(-2), out.mode_probs)
    before = torch.cat([out.initial_mode_probs[:, None], out.mode_probs[:, :-1]], 1)
    torch.testing.assert_close(pairs.sum(-1), before)


# -- bad input ----------------------------------------------------------------------------------
def test_bad_inputs_raise_naming_the_argument():
    d = data(B=2, T=5)
    kf = KalmanFilter(linear())
    args = (d.measurements, d.initial_mean, d.initial_cov)
    with pytest.raises(ValueError, match="learn"):
        fit_em(kf, *args, learn=["not_a_parameter"])
    with pytest.raises(ValueError, match="learn"):
        fit_em(kf, *args, learn="Q")
    with pytest.raises(ValueError, match="num_iters"):
        fit_em(kf, *args, num_iters=0)
    with pytest.raises(ValueError, match="tol"):
        fit_em(kf, *args, tol=-1.0)
    with pytest.raises(ValueError, match="learn"):  # a fixed covariance is not a parameter
        fit_em(KalmanFilter(linear(Q_structure="fixed")), *args, learn=["Q"])
    with pytest.raises(ValueError, match="FactorCovariance"):
        fit_em(KalmanFilter(linear(Q_structure="factor")), *args, learn=["Q"])
    with pytest.raises(TypeError, match="filter_or_model"):
        fit_em("kf", *args)  # type: ignore[arg-type]


def test_docs_example_runs():
    text = (Path(__file__).resolve().parents[1] / "docs" / "em_and_search.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 1
    namespace: dict = {}
    exec(compile(blocks[0], "docs/em_and_search.md", "exec"), namespace)  # noqa: S102 - our own docs
    em = namespace["em"]
    assert em.log_likelihoods[-1] > em.log_likelihoods[0]
    assert 1.0 < float(namespace["kf"].model.R.detach()) < 16.0
    assert len(namespace["found"].table) == 5


def test_a_falling_log_likelihood_restores_the_best_iterate(monkeypatch):
    """An approximate E-step can lower the likelihood; fit_em then returns the best iterate, not
    the last.  The fall is forced here: the third M-step of Q returns a far too large Q."""
    import difffilter.learn.em as em

    z = data()
    calls = {"n": 0}
    real_step = em.process_noise_step

    def step(*args, **kw):
        calls["n"] += 1
        new = real_step(*args, **kw)
        return new * 50.0 if calls["n"] == 3 else new

    monkeypatch.setattr(em, "process_noise_step", step)
    filt = KalmanFilter(linear(Q=2 * Q_TRUE, R=2 * R_TRUE))
    res = fit_em(filt, z.measurements, t(M0), t(P0), num_iters=3, learn=["Q", "R"], tol=0.0)
    ll = np.array(res.log_likelihoods)
    assert len(ll) == 4 and ll[3] < ll[2]  # the forced M-step lowered it
    assert not res.monotone and res.best_iteration == int(np.argmax(ll)) == 2
    # the filter holds the best iterate's values: a fresh run of the filter reproduces its likelihood
    again = filt(z.measurements, t(M0), t(P0)).log_likelihood.sum().item()
    np.testing.assert_allclose(again, ll[2], rtol=1e-12)
    np.testing.assert_allclose(res.values["model.dynamics.Q"].numpy(), filt.model.dynamics.Q.detach().numpy(), rtol=0, atol=0)

    monkeypatch.setattr(em, "process_noise_step", real_step)
    exact = fit_em(KalmanFilter(linear(Q=2 * Q_TRUE, R=2 * R_TRUE)), z.measurements, t(M0), t(P0), num_iters=3, tol=0.0)
    assert exact.monotone and exact.best_iteration == 3
