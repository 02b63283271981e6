"""Coloured-measurement-noise UKF (p001): reduction to the UKF, exactness against the dense joint
Gaussian of an AR(1)-noise linear model, NIS consistency, Psi learning signal, battery."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from difffilter.filters import UKF, Cubature, Julier, MerweScaled
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.models import FunctionalModel

from .filter_contract import FilterContract, cv_matrices, make_data

F64 = torch.float64
SP = MerweScaled(alpha=1.0)
BEACONS = torch.tensor([[60.0, -15.0], [-40.0, 80.0]], dtype=F64)


def beacon_model(q: float = 0.05, r: float = 0.5, dtype=F64) -> FunctionalModel:
    def f(x):
        return torch.stack([x[..., 0] + 0.5 * x[..., 1], x[..., 1], x[..., 2] + 0.5 * x[..., 3], x[..., 3]], -1)

    def h(x):
        p = torch.stack([x[..., 0], x[..., 2]], -1)
        return (p[..., None, :] - BEACONS.to(x.dtype)).norm(dim=-1)

    Q = q * torch.block_diag(*[torch.tensor([[0.5**3 / 3, 0.5**2 / 2], [0.5**2 / 2, 0.5]], dtype=F64)] * 2)
    return FunctionalModel(f=f, h=h, Q=Q.to(dtype), R=r * torch.eye(2, dtype=dtype))


@pytest.mark.parametrize(
    "sp", [MerweScaled(alpha=1.0), MerweScaled(alpha=0.3, beta=2.0, kappa=1.0), Julier(kappa=1.0), Cubature()], ids=repr
)
def test_psi_zero_reduces_to_the_ukf(sp):
    model = beacon_model()
    z = make_data(3, 15, 2, seed=2) + torch.tensor([60.0, 80.0], dtype=F64)
    mask = torch.rand(3, 15, 2, generator=torch.Generator().manual_seed(1)) > 0.25
    zn = torch.where(mask, z, torch.nan)
    m0, P0 = torch.tensor([1.0, 0.5, -1.0, 0.2], dtype=F64), torch.eye(4, dtype=F64) * 3
    col = ColoredNoiseUKF(model, psi=0.0, sigma_points=sp)
    assert col.psi.detach().eq(0).all()
    res, ref = col(zn, m0, P0, mask=mask), UKF(model, sigma_points=sp)(zn, m0, P0, mask=mask)
    for key in ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis"):
        torch.testing.assert_close(getattr(res, key), getattr(ref, key), rtol=0, atol=1e-10)


def _dense_posteriors(F, H_seq, Q, R, psi, m0, P0, z):
    """Exact ``E[x_t | z_1..t]``, ``Cov`` and ``log p(z_1..T)`` for ``x_t = F x_{t-1} + w``,
    ``z_t = H_t x_t + v_t``, ``v_t = Psi v_{t-1} + eta_t``, ``v_1`` stationary, by conditioning
    the dense joint Gaussian of the latent vector ``[x_0, w_1..w_T, v_1, eta_2..eta_T]``.
    ``psi [m]`` or per step ``[T, m]``; ``R [m, m]`` or per step ``[T, m, m]`` (``Cov(eta_t)``;
    ``v_1`` has ``R_1 / (1 - psi_1 psi_1^T)``)."""
    T, m = z.shape
    n = F.shape[0]
    psi_t = np.broadcast_to(psi, (T, m))
    R_t = np.broadcast_to(R, (T, m, m))
    V = R_t[0] / (1.0 - np.outer(psi_t[0], psi_t[0]))
    blocks = [P0] + [Q] * T + [V] + list(R_t[1:])
    D = n * (T + 1) + m * T
    cov = np.zeros((D, D))
    i = 0
    for b in blocks:
        cov[i : i + len(b), i : i + len(b)] = b
        i += len(b)
    mean = np.concatenate([m0, np.zeros(D - n)])
    ax = np.zeros((n, D))
    ax[:, :n] = np.eye(n)
    av = np.zeros((m, D))
    xs, zs = [], []
    for t in range(T):
        ax = F @ ax
        ax[:, n * (t + 1) : n * (t + 2)] += np.eye(n)
        av = np.diag(psi_t[t]) @ av if t > 0 else av
        av[:, n * (T + 1) + m * t : n * (T + 1) + m * (t + 1)] += np.eye(m)
        xs.append(ax.copy())
        zs.append(H_seq[t] @ ax + av)
    out_m, out_c = [], []
    for t in range(T):
        A = np.concatenate(zs[: t + 1])
        S = A @ cov @ A.T
        K = xs[t] @ cov @ A.T @ np.linalg.inv(S)
        out_m.append(xs[t] @ mean + K @ (z[: t + 1].reshape(-1) - A @ mean))
        out_c.append(xs[t] @ cov @ xs[t].T - K @ A @ cov @ xs[t].T)
    A = np.concatenate(zs)
    S = A @ cov @ A.T
    d = z.reshape(-1) - A @ mean
    loglik = -0.5 * (d @ np.linalg.solve(S, d) + np.linalg.slogdet(S)[1] + len(d) * math.log(2 * math.pi))
    return np.array(out_m), np.array(out_c), loglik


def test_linear_model_matches_dense_joint_gaussian_with_time_varying_controls():
    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    F, H, Q, R = mats["F"], mats["H"], mats["Q"], mats["R"]  # R has correlated components
    psi = np.array([0.7, -0.4])
    T, B = 8, 2
    scale = 1.0 + 0.3 * torch.rand(B, T, 2, generator=torch.Generator().manual_seed(3), dtype=F64)  # per-step gains in h

    def f(x, u):
        return x @ torch.tensor(F).mT

    def h(x, u):
        return (x @ torch.tensor(H).mT) * u

    model = FunctionalModel(f=f, h=h, Q=torch.tensor(Q), R=torch.tensor(R), controls=True)
    z = make_data(B, T, 2, seed=9)
    m0, P0 = np.array([0.5, 1.0, -1.0, 0.2]), np.diag([2.0, 0.5, 2.0, 0.5])
    res = ColoredNoiseUKF(model, psi=torch.tensor(psi), sigma_points=SP)(z, torch.tensor(m0), torch.tensor(P0), controls=scale)
    for b in range(B):
        hs = [np.diag(scale[b, t].numpy()) @ H for t in range(T)]
        mu, cov, ll = _dense_posteriors(F, hs, Q, R, psi, m0, P0, z[b].numpy())
        np.testing.assert_allclose(res.mean[b].detach().numpy(), mu, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.cov[b].detach().numpy(), cov, rtol=0, atol=1e-9)
        assert abs(res.log_likelihood[b].sum().item() - ll) < 1e-8


def simulate_colored(B, T, psi, seed, q=0.05, r=0.5):
    """Trajectories of the beacon model with AR(1) range noise (stationary start)."""
    g = torch.Generator().manual_seed(seed)
    model = beacon_model(q, r)
    lq = torch.linalg.cholesky(model.Q.detach())
    x = torch.tensor([5.0, 1.0, 5.0, -0.5], dtype=F64) + torch.randn(B, 4, generator=g, dtype=F64) @ torch.diag(
        torch.tensor([1.0, 0.3, 1.0, 0.3], dtype=F64)
    )
    v = math.sqrt(r / (1 - psi**2)) * torch.randn(B, 2, generator=g, dtype=F64)
    zs = []
    for t in range(T):
        x = model.f(x) + torch.randn(B, 4, generator=g, dtype=F64) @ lq.mT
        if t > 0:
            v = psi * v + math.sqrt(r) * torch.randn(B, 2, generator=g, dtype=F64)
        zs.append(model.h(x).detach() + v)
    m0 = torch.tensor([5.0, 1.0, 5.0, -0.5], dtype=F64)
    P0 = torch.diag(torch.tensor([1.0, 0.09, 1.0, 0.09], dtype=F64))
    return torch.stack(zs, 1).detach(), m0, P0


def test_nis_consistent_with_true_psi_and_not_for_plain_ukf():
    B, T = 24, 60
    z, m0, P0 = simulate_colored(B, T, 0.7, seed=5)
    model = beacon_model()
    band = chi2.ppf([0.025, 0.975], 2 * B * T) / (B * T)
    col = ColoredNoiseUKF(model, psi=0.7, sigma_points=SP)(z, m0, P0)
    plain = UKF(model, sigma_points=SP)(z, m0, P0)
    nis_col, nis_ukf = col.nis.mean().item(), plain.nis.mean().item()
    print(f"time-averaged NIS (m = 2, 95% band [{band[0]:.3f}, {band[1]:.3f}]): coloured UKF {nis_col:.3f}, plain UKF {nis_ukf:.3f}")
    assert band[0] < nis_col < band[1]
    assert not band[0] < nis_ukf < band[1]


def test_likelihood_prefers_the_true_psi_and_gradient_points_to_it():
    z, m0, P0 = simulate_colored(8, 40, 0.7, seed=6)
    model = beacon_model()
    lls = {p: ColoredNoiseUKF(model, psi=p, sigma_points=SP)(z, m0, P0).log_likelihood.sum().item() for p in (0.0, 0.35, 0.7, 0.9)}
    assert max(lls, key=lls.get) == 0.7
    col = ColoredNoiseUKF(model, psi=0.3, sigma_points=SP)
    col(z, m0, P0).log_likelihood.sum().backward()
    grad = col.parametrizations.psi.original.grad
    assert torch.isfinite(grad).all() and (grad > 0).all()  # ascent moves psi up towards 0.7


def test_missing_previous_measurement_falls_back_to_stationary_update():
    model = beacon_model()
    z, m0, P0 = simulate_colored(2, 6, 0.6, seed=8)
    col = ColoredNoiseUKF(model, psi=0.6, sigma_points=SP)
    belief = col.initial_belief(m0, P0, batch_size=2)
    first, prior, info = col.step(belief, z[:, 0])
    # the first step equals a plain UKF update with the stationary noise R / (1 - psi^2)
    stat = beacon_model(r=0.5 / (1 - 0.36))
    ref, _, ref_info = UKF(stat, sigma_points=SP).step(UKF(stat, sigma_points=SP).initial_belief(m0, P0, batch_size=2), z[:, 0])
    torch.testing.assert_close(first["mean"], ref["mean"], rtol=0, atol=1e-10)
    torch.testing.assert_close(info.log_likelihood, ref_info.log_likelihood, rtol=0, atol=1e-10)
    # a gap in component 1 makes the next update undifferenced in that component only
    gap = torch.tensor([[True, False], [True, True]])
    second, _, _ = col.step(first, torch.where(gap, z[:, 1], torch.nan), gap)
    assert second["prev_observed"].equal(gap)
    third, _, info3 = col.step(second, z[:, 2])
    assert torch.isfinite(third["mean"]).all() and torch.isfinite(info3.log_likelihood).all()


def test_bad_psi():
    model = beacon_model()
    with pytest.raises(ValueError, match="psi"):
        ColoredNoiseUKF(model, psi=1.0)
    with pytest.raises(ValueError, match="psi"):
        ColoredNoiseUKF(model, psi=torch.zeros(3, dtype=F64))


class TestColoredPsiZero(FilterContract):
    def make_filter(self, model):
        return ColoredNoiseUKF(model, psi=0.0, sigma_points=SP)


class TestColoredPsi(FilterContract):
    """Psi != 0: the white-noise Kalman references do not apply; the rest of the battery does."""

    test_equals_closed_form_kalman = None
    test_log_likelihood_equals_dense_joint_gaussian = None
    test_mask_equals_closed_form_subset_update = None

    def make_filter(self, model):
        return ColoredNoiseUKF(model, psi=torch.tensor([0.5, -0.3], dtype=model.Q.dtype), sigma_points=SP)
