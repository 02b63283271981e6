"""IMM mixer (p003): exact reductions, filterpy, exhaustive mode-sequence enumeration, log-space
robustness, gradients, state embeddings and the shared filter battery."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.filters import UKF, KalmanFilter, MerweScaled, SquareRootUKF
from difffilter.filters.adaptive import RCUKF
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.mixers import IMM, SubspaceEmbedding
from difffilter.models import FunctionalModel, LinearModel

from .filter_contract import FilterContract, make_data

F64 = torch.float64


def cv1d(q: float, r: float, dtype=F64) -> LinearModel:
    F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    Q = q * torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1.0]], dtype=F64) + 1e-9 * torch.eye(2, dtype=F64)
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    return LinearModel(F=F.to(dtype), H=H.to(dtype), Q=Q.to(dtype), R=torch.tensor([[r]], dtype=dtype))


def _mats(model: LinearModel) -> tuple[np.ndarray, ...]:
    d, m = model.dynamics, model.measurement
    return tuple(t.detach().double().numpy() for t in (d.F, m.H, model.Q, model.R))


def simulate_jump_linear(models, Pi, mu0, T, B, seed, m0, P0):
    """Draw mode sequences and data from a jump-Markov linear system (numpy)."""
    rng = np.random.default_rng(seed)
    mats = [_mats(mo) for mo in models]
    zs, modes = [], []
    for _ in range(B):
        x = rng.multivariate_normal(m0, P0)
        mode = rng.choice(len(mu0), p=mu0)
        zb, mb = [], []
        for _t in range(T):
            mode = rng.choice(len(mu0), p=Pi[mode])
            F, H, Q, R = mats[mode]
            x = F @ x + rng.multivariate_normal(np.zeros(len(x)), Q)
            zb.append(H @ x + rng.multivariate_normal(np.zeros(H.shape[0]), R))
            mb.append(mode)
        zs.append(zb)
        modes.append(mb)
    return torch.tensor(np.array(zs)), np.array(modes)


# -- exact reductions -----------------------------------------------------------------------------


def _beacon_model() -> FunctionalModel:
    def f(x):
        return torch.stack([x[..., 0] + 0.5 * x[..., 1], x[..., 1], x[..., 2] + 0.5 * x[..., 3], x[..., 3]], -1)

    def h(x):
        p = torch.stack([x[..., 0], x[..., 2]], -1)
        b = torch.tensor([[20.0, -5.0], [-10.0, 30.0]], dtype=x.dtype)
        return (p[..., None, :] - b).norm(dim=-1)

    return FunctionalModel(f=f, h=h, Q=0.1 * torch.eye(4, dtype=F64), R=0.5 * torch.eye(2, dtype=F64))


@pytest.mark.parametrize("kind", ["ukf", "sr_ukf"])
def test_identical_modes_equal_single_filter_and_markov_prior(kind):
    model = _beacon_model()
    make = (lambda: UKF(model, sigma_points=MerweScaled(alpha=1.0))) if kind == "ukf" else (lambda: SquareRootUKF(model))
    Pi = torch.tensor([[0.8, 0.15, 0.05], [0.1, 0.7, 0.2], [0.3, 0.3, 0.4]], dtype=F64)
    mu0 = torch.tensor([0.6, 0.3, 0.1], dtype=F64)
    imm = IMM([make(), make(), make()], Pi, mu0, prob_floor=0.0)
    z = make_data(3, 12, 2, seed=1) + torch.tensor([20.0, 30.0], dtype=F64)
    m0, P0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    out, ref = imm(z, m0, P0), make()(z, m0, P0)
    for key in ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood"):
        torch.testing.assert_close(getattr(out, key), getattr(ref, key), rtol=0, atol=1e-10)
    probs, expect = [], mu0
    for _ in range(12):
        expect = Pi.T @ expect
        probs.append(expect)
    torch.testing.assert_close(out.mode_probs, torch.stack(probs).expand(3, 12, 3), rtol=0, atol=1e-10)


@pytest.mark.parametrize("kind", ["rcukf", "colored"])
def test_identical_modes_keep_each_filters_memory(kind):
    """Filters with memory (RC-UKF's residual covariance, the coloured-noise UKF's previous
    measurement) keep it per mode across mixing: identical modes reproduce the single filter."""
    model = _beacon_model()
    sp = MerweScaled(alpha=1.0)
    make = (
        (lambda: RCUKF(model, sigma_points=sp, rho=0.6)) if kind == "rcukf" else (lambda: ColoredNoiseUKF(model, psi=0.6, sigma_points=sp))
    )
    imm = IMM([make(), make()], torch.tensor([[0.9, 0.1], [0.3, 0.7]], dtype=F64), torch.tensor([0.5, 0.5], dtype=F64))
    z = make_data(2, 15, 2, seed=4) * 2.0 + torch.tensor([20.0, 30.0], dtype=F64)
    m0, P0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    out, ref = imm(z, m0, P0), make()(z, m0, P0)
    torch.testing.assert_close(out.mean, ref.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
    if kind == "rcukf":
        assert (ref.fading_factor > 1).any()


def _filterpy_imm(models, Pi, mu0, m0, P0, z):
    from filterpy.kalman import IMMEstimator
    from filterpy.kalman import KalmanFilter as FPKalman

    kfs = []
    for mo in models:
        F, H, Q, R = _mats(mo)
        kf = FPKalman(dim_x=F.shape[0], dim_z=H.shape[0])
        kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
        kf.x, kf.P = m0.copy(), P0.copy()
        kfs.append(kf)
    imm = IMMEstimator(kfs, mu0.copy(), Pi.copy())  # filterpy's M[i, j] enters as cbar = mu @ M: P(j | i)
    xs, ps, mus = [], [], []
    for t in range(z.shape[0]):
        imm.predict()
        imm.update(z[t])
        xs.append(imm.x_post.copy())
        ps.append(imm.P_post.copy())
        mus.append(imm.mu.copy())
    return np.array(xs), np.array(ps), np.array(mus)


def test_matches_filterpy_imm_every_step():
    models = [cv1d(0.01, 0.2), cv1d(2.0, 3.0)]
    Pi = np.array([[0.9, 0.1], [0.2, 0.8]])
    mu0 = np.array([0.7, 0.3])
    m0, P0 = np.array([0.0, 1.0]), np.diag([4.0, 1.0])
    z, _ = simulate_jump_linear(models, Pi, mu0, 30, 2, seed=3, m0=m0, P0=P0)
    imm = IMM([KalmanFilter(mo) for mo in models], torch.tensor(Pi), torch.tensor(mu0), prob_floor=0.0)
    out = imm(z, torch.tensor(m0), torch.tensor(P0))
    for b in range(2):
        xs, ps, mus = _filterpy_imm(models, Pi, mu0, m0, P0, z[b].numpy())
        np.testing.assert_allclose(out.mean[b].detach().numpy(), xs, rtol=0, atol=1e-8)
        np.testing.assert_allclose(out.cov[b].detach().numpy(), ps, rtol=0, atol=1e-8)
        np.testing.assert_allclose(out.mode_probs[b].detach().numpy(), mus, rtol=0, atol=1e-8)


def exact_mode_posteriors(models, Pi, mu0, m0, P0, z, u=None):
    """P(m_t = j | z_1..t) by enumerating all M^t mode sequences (one Kalman filter each);
    ``u [T, k]`` optional inputs of the models' ``B``."""
    M = len(models)
    means, covs = m0[None], P0[None]
    logw, last = np.zeros(1), np.zeros(1, dtype=int)  # one hypothesis before the first step
    out = []
    for t in range(z.shape[0]):
        mats = [_mats(mo) + (_offset(mo, None if u is None else u[t]),) for mo in models]
        prev = np.repeat(np.arange(len(logw)), M)
        mode = np.tile(np.arange(M), len(logw))
        trans = np.log(Pi[last[prev], mode]) if t > 0 else np.log(mu0 @ Pi)[mode]
        lw = logw[prev] + trans
        nm, nc = [], []
        for k in range(len(mode)):
            F, H, Q, R, c = mats[mode[k]]
            x, P = F @ means[prev[k]] + c, F @ covs[prev[k]] @ F.T + Q
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            e = z[t] - H @ x
            lw[k] += -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] + len(e) * math.log(2 * math.pi))
            nm.append(x + K @ e)
            nc.append((np.eye(len(x)) - K @ H) @ P)
        means, covs, logw, last = np.array(nm), np.array(nc), lw, mode
        w = np.exp(lw - lw.max())
        out.append(np.array([w[mode == j].sum() for j in range(M)]) / w.sum())
    return np.array(out)


def _offset(model: LinearModel, u) -> np.ndarray:
    B = model.dynamics.B
    n = model.dynamics.F.shape[0]
    return np.zeros(n) if B is None or u is None else B.double().numpy() @ u


def _velocity_modes(speed: float) -> list[LinearModel]:
    """Random walk with a mode-dependent velocity ``x_k = x_{k-1} +- speed * u_k`` (u = 1)."""
    eye = torch.eye(1, dtype=F64)
    return [LinearModel(F=eye, H=eye, Q=0.3 * eye, R=0.3 * eye, B=torch.tensor([[s * speed]], dtype=F64)) for s in (1.0, -1.0)]


def _simulate_with_inputs(models, Pi, mu0, T, B, seed, m0, P0):
    rng = np.random.default_rng(seed)
    zs = []
    for _ in range(B):
        x, mode, zb = rng.multivariate_normal(m0, P0), rng.choice(len(mu0), p=mu0), []
        for _t in range(T):
            mode = rng.choice(len(mu0), p=Pi[mode])
            F, H, Q, R = _mats(models[mode])
            x = F @ x + _offset(models[mode], np.ones(1)) + rng.multivariate_normal(np.zeros(len(x)), Q)
            zb.append(H @ x + rng.multivariate_normal(np.zeros(H.shape[0]), R))
        zs.append(zb)
    return torch.tensor(np.array(zs))


def test_mode_probabilities_close_to_exhaustive_enumeration():
    T, B = 10, 4
    Pi, mu0 = np.array([[0.9, 0.1], [0.15, 0.85]]), np.array([0.5, 0.5])
    devs = {}
    # well separated: +-1 m/step velocity modes (asserted); noise-level modes (R 0.1 vs 9, Q x100),
    # where the IMM's merging is a coarse approximation of the exact posterior (reported only)
    for name, models, u in (("velocity", _velocity_modes(1.0), np.ones((T, 1))), ("noise-level", [cv1d(0.01, 0.1), cv1d(1.0, 9.0)], None)):
        n = models[0].state_dim
        m0, P0 = np.array([0.0, 1.0])[:n], np.diag([1.0, 0.5][:n])
        if u is None:
            z, _ = simulate_jump_linear(models, Pi, mu0, T, B, seed=11, m0=m0, P0=P0)
        else:
            z = _simulate_with_inputs(models, Pi, mu0, T, B, seed=11, m0=m0, P0=P0)
        imm = IMM([KalmanFilter(mo) for mo in models], torch.tensor(Pi), torch.tensor(mu0), prob_floor=0.0)
        ctl = None if u is None else torch.tensor(u).expand(B, T, 1)
        probs = imm(z, torch.tensor(m0), torch.tensor(P0), controls=ctl).mode_probs.detach().numpy()
        devs[name] = max(np.abs(probs[b] - exact_mode_posteriors(models, Pi, mu0, m0, P0, z[b].numpy(), u)).max() for b in range(B))
    print(f"IMM vs exact 2^{T}-sequence enumeration, max |mode prob deviation|: " + ", ".join(f"{k} {v:.4f}" for k, v in devs.items()))
    assert devs["velocity"] < 0.05


# -- robustness and gradients ------------------------------------------------------------------------


def _garbage_bank(dtype=F64, floor=1e-6):
    good = cv1d(0.05, 0.5, dtype)
    F = torch.tensor([[1.0, -1.0], [0.0, -1.0]], dtype=dtype)  # velocity reversed every step
    bad = LinearModel(
        F=F, H=torch.tensor([[1.0, 0.0]], dtype=dtype), Q=0.05 * torch.eye(2, dtype=dtype), R=torch.tensor([[0.5]], dtype=dtype)
    )
    Pi = torch.tensor([[0.95, 0.05], [0.05, 0.95]], dtype=dtype)
    return IMM([KalmanFilter(good), KalmanFilter(bad)], Pi, torch.tensor([0.5, 0.5], dtype=dtype), prob_floor=floor)


def _ramp(B, T, dtype=F64, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=F64)
    return (2.0 * t[None, :, None] + 0.7 * torch.randn(B, T, 1, generator=g, dtype=F64)).to(dtype)


def test_garbage_mode_loses_and_probabilities_are_valid():
    imm = _garbage_bank(floor=1e-4)
    out = imm(_ramp(4, 40), torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 10)
    p = out.mode_probs.detach()
    assert (p[:, -1, 0] > 0.95).all()
    assert (p.sum(-1) - 1).abs().max() < 1e-6
    assert p.min() >= 1e-4 / (1 + 2e-4) * (1 - 1e-9)


def test_gradcheck_wrt_transition_logits():
    imm = _garbage_bank()
    z = _ramp(2, 5)
    raw = imm.parametrizations.transition.original

    def fn(logits):
        res = torch.func.functional_call(
            imm, {"parametrizations.transition.original": logits}, (z, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
        )
        return res.log_likelihood.sum(), res.mode_probs.sum(1), res.mean.sum()

    assert torch.autograd.gradcheck(fn, (raw.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-6)


def test_long_float32_run_has_finite_gradients():
    imm = _garbage_bank(torch.float32)
    z = _ramp(2, 2000, torch.float32)
    out = imm(z, torch.zeros(2), torch.eye(2) * 10)
    (out.log_likelihood.sum() + out.mean.sum()).backward()
    grads = [p.grad for p in imm.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert torch.isfinite(out.mode_probs).all()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_thousand_sigma_outlier_gives_finite_outputs_and_gradients(dtype):
    imm = _garbage_bank(dtype)
    z = _ramp(2, 30, dtype)
    z[0, 15] += 1e3 * math.sqrt(0.5)  # log-likelihood ~ -5e5, i.e. likelihood far below 1e-320
    out = imm(z, torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype) * 10)
    assert out.log_likelihood[0, 15] < -1e5
    for t in (out.mean, out.cov, out.mode_probs, out.log_likelihood):
        assert torch.isfinite(t).all()
    out.log_likelihood.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in imm.parameters() if p.grad is not None)


# -- embeddings ------------------------------------------------------------------------------------


def _cv_ca(q_ca: float = 0.5):
    f1 = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    f2 = torch.tensor([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], dtype=F64)
    cv = LinearModel(
        F=torch.block_diag(f1, f1),
        H=torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64),
        Q=0.01 * torch.eye(4, dtype=F64),
        R=0.25 * torch.eye(2, dtype=F64),
    )
    qa = torch.diag(torch.tensor([1e-4, 1e-3, q_ca], dtype=F64))
    H6 = torch.zeros(2, 6, dtype=F64)
    H6[0, 0] = H6[1, 3] = 1.0
    ca = LinearModel(F=torch.block_diag(f2, f2), H=H6, Q=torch.block_diag(qa, qa), R=0.25 * torch.eye(2, dtype=F64))
    return cv, ca


def test_embedding_with_decoupled_extra_states_is_exact():
    cv, _ = _cv_ca()
    emb = SubspaceEmbedding([0, 1, 3, 4], 6, fill_variance=2.0)
    # a 6-state mode = CV on [0, 1, 3, 4] plus two unobserved static states: same likelihoods
    perm = [0, 1, 3, 4]
    F6, Q6 = torch.eye(6, dtype=F64), torch.eye(6, dtype=F64) * 0.3
    F6[np.ix_(perm, perm)] = cv.dynamics.F
    Q6[np.ix_(perm, perm)] = cv.Q
    H6 = torch.zeros(2, 6, dtype=F64)
    H6[:, perm] = cv.measurement.H
    six = LinearModel(F=F6, H=H6, Q=Q6, R=cv.R.detach())
    Pi = torch.tensor([[0.9, 0.1], [0.3, 0.7]], dtype=F64)
    mu0 = torch.tensor([0.4, 0.6], dtype=F64)
    imm = IMM([KalmanFilter(cv), KalmanFilter(six)], Pi, mu0, embed=[emb.embed, None], project=[emb.project, None], prob_floor=0.0)
    z = make_data(2, 15, 2, seed=5)
    m0, P0 = torch.zeros(6, dtype=F64), torch.eye(6, dtype=F64) * 2.0
    out = imm(z, m0, P0)
    ref = KalmanFilter(cv)(z, m0[perm], P0[np.ix_(perm, perm)])
    torch.testing.assert_close(out.mean[..., perm], ref.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.mode_means[..., 0, :][..., perm], ref.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.log_likelihood, ref.log_likelihood, rtol=0, atol=1e-10)
    expect, probs = mu0, []
    for _ in range(15):
        expect = Pi.T @ expect
        probs.append(expect)
    torch.testing.assert_close(out.mode_probs, torch.stack(probs).expand(2, 15, 2), rtol=0, atol=1e-10)
    assert out.mode_covs.shape == (2, 15, 2, 6, 6)


def test_cv_ca_bank_tracks_manoeuvre():
    cv, ca = _cv_ca()
    emb = SubspaceEmbedding([0, 1, 3, 4], 6, fill_variance=0.05)
    imm = IMM(
        [KalmanFilter(cv), KalmanFilter(ca)],
        torch.tensor([[0.95, 0.05], [0.05, 0.95]], dtype=F64),
        torch.tensor([0.5, 0.5], dtype=F64),
        embed=[emb.embed, None],
        project=[emb.project, None],
    )
    # straight at 1 m/s, then 2 m/s^2 along x from t = 30 to 50, then straight again
    t = torch.arange(80, dtype=F64)
    acc = ((t >= 30) & (t < 50)).to(F64) * 2.0
    vx = 1.0 + torch.cumsum(acc, 0)
    px = torch.cumsum(vx, 0)
    g = torch.Generator().manual_seed(2)
    z = torch.stack([px, 0.5 * t], -1)[None] + 0.5 * torch.randn(1, 80, 2, generator=g, dtype=F64)
    out = imm(z, torch.tensor([0.0, 1.0, 0.0, 0.0, 0.5, 0.0], dtype=F64), torch.eye(6, dtype=F64) * 4)
    p_ca = out.mode_probs[0, :, 1].detach()
    assert p_ca[35:50].mean() > 0.8 and p_ca[15:30].mean() < 0.5
    assert torch.isfinite(out.cov).all() and (torch.linalg.eigvalsh(out.cov) > 0).all()


# -- parameters and inputs ---------------------------------------------------------------------------


def test_transition_and_initial_probs_are_settable_and_validated():
    cv = cv1d(0.1, 1.0)
    Pi = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=F64)
    imm = IMM([KalmanFilter(cv), KalmanFilter(cv1d(1.0, 1.0))], Pi, torch.tensor([0.5, 0.5], dtype=F64))
    torch.testing.assert_close(imm.transition.detach(), Pi, rtol=0, atol=1e-12)
    new = torch.tensor([[0.6, 0.4], [0.3, 0.7]], dtype=F64)
    imm.transition = new
    torch.testing.assert_close(imm.transition.detach(), new, rtol=0, atol=1e-12)
    torch.testing.assert_close(imm.log_transition().exp().detach(), new, rtol=0, atol=1e-12)
    imm.initial_probs = torch.tensor([0.25, 0.75], dtype=F64)
    torch.testing.assert_close(imm.initial_probs.detach(), torch.tensor([0.25, 0.75], dtype=F64), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="transition"):
        IMM([KalmanFilter(cv)] * 2, torch.tensor([[0.9, 0.2], [0.2, 0.8]], dtype=F64), torch.tensor([0.5, 0.5], dtype=F64))
    with pytest.raises(ValueError, match="initial_probs"):
        IMM([KalmanFilter(cv)] * 2, Pi, torch.tensor([1.0], dtype=F64))
    with pytest.raises(ValueError, match="embed"):
        cv4, ca6 = _cv_ca()
        IMM([KalmanFilter(cv4), KalmanFilter(ca6)], Pi, torch.tensor([0.5, 0.5], dtype=F64))
    with pytest.raises(ValueError, match="prob_floor"):
        IMM([KalmanFilter(cv)] * 2, Pi, torch.tensor([0.5, 0.5], dtype=F64), prob_floor=0.6)
    with pytest.raises(TypeError, match="filters"):
        IMM([cv], torch.ones(1, 1, dtype=F64), torch.ones(1, dtype=F64))


def test_missing_steps_propagate_mode_probabilities_by_the_chain():
    imm = _garbage_bank(floor=0.0)
    z = _ramp(1, 10)
    mask = torch.ones(1, 10, dtype=torch.bool)
    mask[0, 6:] = False
    out = imm(torch.where(mask[..., None], z, torch.nan), torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), mask=mask)
    for t in range(6, 10):
        torch.testing.assert_close(out.mode_probs[0, t], imm.transition.detach().T @ out.mode_probs[0, t - 1], rtol=0, atol=1e-12)


# -- shared battery ----------------------------------------------------------------------------------


class TestIMMIdenticalModes(FilterContract):
    def make_filter(self, model):
        Pi = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=model.Q.dtype)
        return IMM(
            [KalmanFilter(model), UKF(model, sigma_points=MerweScaled(alpha=1.0))], Pi, torch.tensor([0.5, 0.5], dtype=model.Q.dtype)
        )


class TestIMMDistinctModes(FilterContract):
    """Two different modes: the linear-Gaussian equivalences do not apply; the rest does."""

    test_equals_closed_form_kalman = None
    test_log_likelihood_equals_dense_joint_gaussian = None
    test_mask_equals_closed_form_subset_update = None

    def make_filter(self, model):
        d, m = model.dynamics, model.measurement
        other = LinearModel(F=d.F, H=m.H, Q=model.Q.detach() * 20.0, R=model.R.detach() * 3.0)
        Pi = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=d.F.dtype)
        return IMM([KalmanFilter(model), UKF(other, sigma_points=MerweScaled(alpha=1.0))], Pi, torch.tensor([0.5, 0.5], dtype=d.F.dtype))
