"""Shared test battery: every filter class inherits these checks by subclassing
:class:`FilterContract` and implementing :meth:`make_filter`.

References are independent of the code under test: a closed-form Kalman filter written here in
plain numpy, and the dense joint Gaussian of the whole measurement sequence.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.models import LinearModel
from difffilter.params import constrained_values


def cv_matrices(dt: float = 0.5, q: float = 0.3, r: float = 0.8, observe: str = "pos") -> dict[str, torch.Tensor]:
    """2-D constant-velocity model [px, vx, py, vy]; ``observe="pos"`` measures both positions,
    ``"x"`` only px (a partially observed state)."""
    f1 = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=torch.float64)
    q1 = q * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=torch.float64)
    F = torch.block_diag(f1, f1)
    Q = torch.block_diag(q1, q1) + 1e-9 * torch.eye(4, dtype=torch.float64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    if observe == "x":
        H = H[:1]
    R = r * torch.eye(H.shape[0], dtype=torch.float64)
    if H.shape[0] == 2:
        R[0, 1] = R[1, 0] = 0.2 * r
    return {"F": F, "H": H, "Q": Q, "R": R}


def numpy_kalman(z: np.ndarray, m0: np.ndarray, P0: np.ndarray, F, H, Q, R, mask: np.ndarray | None = None):
    """Textbook KF on one trajectory ``z [T, m]`` (observed subset per step if ``mask``)."""
    x, P = m0.copy(), P0.copy()
    means, covs, lls = [], [], []
    for t in range(z.shape[0]):
        x = F @ x
        P = F @ P @ F.T + Q
        obs = np.ones(z.shape[1], bool) if mask is None else mask[t]
        ll = 0.0
        if obs.any():
            Ho, Ro, zo = H[obs], R[np.ix_(obs, obs)], z[t, obs]
            S = Ho @ P @ Ho.T + Ro
            K = P @ Ho.T @ np.linalg.inv(S)
            e = zo - Ho @ x
            x = x + K @ e
            P = (np.eye(len(x)) - K @ Ho) @ P
            P = 0.5 * (P + P.T)
            ll = -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] + len(e) * math.log(2 * math.pi))
        means.append(x.copy())
        covs.append(P.copy())
        lls.append(ll)
    return np.array(means), np.array(covs), np.array(lls)


def make_data(B: int, T: int, m: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    base = torch.cumsum(torch.randn(B, T, m, generator=g, dtype=torch.float64), 1)
    return base.to(dtype)


class FilterContract:
    """Battery run for every filter.  Subclasses set ``make_filter(model) -> filter``."""

    #: tolerance against the closed-form KF on linear-Gaussian models
    linear_tol = 1e-8
    #: float32 vs float64 relative tolerance ("well-conditioned" cases)
    float32_tol = 1e-4
    #: absolute tolerance of gradcheck's finite differences
    gradcheck_atol = 1e-5

    def make_filter(self, model):  # pragma: no cover - abstract
        raise NotImplementedError

    def linear_model(self, observe: str = "pos", r: float = 0.8, dtype=torch.float64) -> LinearModel:
        mats = cv_matrices(observe=observe, r=r)
        return LinearModel(**{k: v.to(dtype) for k, v in mats.items()})

    @pytest.mark.parametrize("observe,r", [("pos", 0.8), ("x", 0.8), ("pos", 1e-6)])
    def test_equals_closed_form_kalman(self, observe, r):
        model = self.linear_model(observe, r)
        mats = cv_matrices(observe=observe, r=r)
        z = make_data(3, 25, mats["H"].shape[0])
        m0 = torch.tensor([1.0, -0.5, 2.0, 0.3], dtype=torch.float64)
        P0 = torch.diag(torch.tensor([4.0, 1.0, 4.0, 1.0], dtype=torch.float64))
        res = self.make_filter(model)(z, m0, P0)
        for b in range(z.shape[0]):
            npm = {k: v.numpy() for k, v in mats.items()}
            mu, cov, ll = numpy_kalman(z[b].numpy(), m0.numpy(), P0.numpy(), **npm)
            scale = max(1.0, float(np.abs(mu).max()))
            assert np.abs(res.mean[b].detach().numpy() - mu).max() < self.linear_tol * scale * 10
            assert np.abs(res.cov[b].detach().numpy() - cov).max() < self.linear_tol * 10
            assert np.abs(res.log_likelihood[b].detach().numpy() - ll).max() < self.linear_tol * 100

    def test_log_likelihood_equals_dense_joint_gaussian(self):
        model = self.linear_model()
        mats = {k: v.numpy() for k, v in cv_matrices().items()}
        T, m = 12, 2
        z = make_data(1, T, m, seed=3)
        m0 = np.array([0.5, 1.0, -1.0, 0.2])
        P0 = np.diag([2.0, 0.5, 2.0, 0.5])
        F, H, Q, R = mats["F"], mats["H"], mats["Q"], mats["R"]
        # Joint Gaussian of all measurements: z_t = H x_t + v_t, x_t = F^t x_0 + sum F^{t-s} w_s.
        n = 4
        Phi = [np.linalg.matrix_power(F, t + 1) for t in range(T)]
        mean = np.concatenate([H @ Phi[t] @ m0 for t in range(T)])
        cov_x = [[None] * T for _ in range(T)]
        for s in range(T):
            for t in range(T):
                c = Phi[s] @ P0 @ Phi[t].T
                for k in range(min(s, t) + 1):
                    c = c + np.linalg.matrix_power(F, s - k) @ Q @ np.linalg.matrix_power(F, t - k).T
                cov_x[s][t] = c
        big = np.block([[H @ cov_x[s][t] @ H.T + (R if s == t else np.zeros((m, m))) for t in range(T)] for s in range(T)])
        d = z[0].numpy().reshape(-1) - mean
        sign, logdet = np.linalg.slogdet(big)
        ref = -0.5 * (d @ np.linalg.solve(big, d) + logdet + T * m * math.log(2 * math.pi))
        res = self.make_filter(model)(z, torch.tensor(m0), torch.tensor(P0))
        assert sign > 0 and n == 4
        assert abs(float(res.log_likelihood.sum().detach()) - ref) < 1e-7

    def test_batch_equals_loop(self):
        model = self.linear_model()
        z = make_data(4, 10, 2, seed=5)
        m0 = torch.randn(4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        P0 = torch.eye(4, dtype=torch.float64).expand(4, 4, 4) * torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)[:, None, None]
        flt = self.make_filter(model)
        full = flt(z, m0, P0)
        for b in range(4):
            one = flt(z[b : b + 1], m0[b : b + 1], P0[b : b + 1])
            torch.testing.assert_close(one.mean[0], full.mean[b], rtol=0, atol=1e-10)
            torch.testing.assert_close(one.log_likelihood[0], full.log_likelihood[b], rtol=0, atol=1e-10)

    def test_float32_matches_float64(self):
        model64 = self.linear_model()
        model32 = self.linear_model(dtype=torch.float32)
        z = make_data(2, 20, 2, seed=7)
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64) * 2
        r64 = self.make_filter(model64)(z, m0, P0)
        r32 = self.make_filter(model32)(z.float(), m0.float(), P0.float())
        assert r32.mean.dtype == torch.float32
        rel = (r32.mean.double() - r64.mean).abs().max() / r64.mean.abs().max()
        assert rel < self.float32_tol
        ll_rel = (r32.log_likelihood.double() - r64.log_likelihood).abs().max() / r64.log_likelihood.abs().max()
        assert ll_rel < self.float32_tol

    def test_mask_nan_never_reaches_outputs_or_gradients(self):
        model = self.linear_model()
        z = make_data(3, 15, 2, seed=11)
        mask = torch.rand(3, 15, 2, generator=torch.Generator().manual_seed(2)) > 0.4
        mask[0, 3:7] = False  # fully missing steps
        zn = torch.where(mask, z, torch.full_like(z, float("nan")))
        flt = self.make_filter(model)
        res = flt(zn, torch.zeros(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64), mask=mask)
        assert torch.isfinite(res.mean).all() and torch.isfinite(res.cov).all()
        res.log_likelihood.sum().backward()
        for p in flt.parameters():
            if p.grad is not None:
                assert torch.isfinite(p.grad).all()
        # masked values are ignored: any value under the mask gives the same result
        z2 = torch.where(mask, z, torch.full_like(z, 1e6))
        res2 = flt(z2, torch.zeros(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64), mask=mask)
        torch.testing.assert_close(res.mean.detach(), res2.mean.detach(), rtol=0, atol=1e-12)
        # a fully missing step is predict-only
        torch.testing.assert_close(res.mean[0, 4], res.prior_mean[0, 4], rtol=0, atol=1e-12)
        assert float(res.log_likelihood[0, 4].detach().abs()) == 0.0

    def test_mask_equals_closed_form_subset_update(self):
        model = self.linear_model()
        mats = {k: v.numpy() for k, v in cv_matrices().items()}
        z = make_data(2, 15, 2, seed=13)
        mask = torch.rand(2, 15, 2, generator=torch.Generator().manual_seed(4)) > 0.3
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64) * 3
        res = self.make_filter(model)(z, m0, P0, mask=mask)
        for b in range(2):
            mu, cov, ll = numpy_kalman(z[b].numpy(), m0.numpy(), P0.numpy(), mask=mask[b].numpy(), **mats)
            assert np.abs(res.mean[b].detach().numpy() - mu).max() < self.linear_tol * 100
            assert np.abs(res.log_likelihood[b].detach().numpy() - ll).max() < self.linear_tol * 100

    def test_gradcheck_log_likelihood_wrt_raw_noise(self):
        model = self.linear_model()
        flt = self.make_filter(model)
        z = make_data(2, 6, 2, seed=17)
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64)
        named = _raw_named(flt)
        assert named, "filter exposes no raw parameters"
        names = [n for n, _ in named]

        def fn(*values):
            out = torch.func.functional_call(flt, dict(zip(names, values, strict=True)), (z, m0, P0))
            return out.log_likelihood.sum()

        inputs = tuple(p.detach().clone().requires_grad_(True) for _, p in named)
        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=self.gradcheck_atol, rtol=1e-4)

    def test_bad_inputs_raise_clear_errors(self):
        model = self.linear_model()
        flt = self.make_filter(model)
        z = make_data(2, 5, 2)
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64)
        with pytest.raises(ValueError, match="measurements"):
            flt(z[..., :1], m0, P0)
        with pytest.raises(ValueError, match="initial_mean"):
            flt(z, torch.zeros(3, dtype=torch.float64), P0)
        with pytest.raises(ValueError, match="initial_cov"):
            flt(z, m0, -P0)
        with pytest.raises(ValueError, match="initial_cov"):
            flt(z, m0, torch.ones(4, 3, dtype=torch.float64))
        bad = z.clone()
        bad[1, 2, 0] = float("nan")
        with pytest.raises(ValueError, match="measurements"):
            flt(bad, m0, P0)
        with pytest.raises(ValueError, match="mask"):
            flt(z, m0, P0, mask=torch.ones(2, 4, dtype=torch.bool))
        with pytest.raises(TypeError, match="dtype"):
            flt(z.float(), m0.float(), P0.float())

    def test_one_bad_trajectory_does_not_contaminate_batch(self):
        model = self.linear_model()
        flt = self.make_filter(model)
        z = make_data(3, 10, 2, seed=19)
        z[1] = z[1] * 1e150  # absurd trajectory: may overflow, must stay in its own row
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64)
        full = flt(z, m0, P0)
        ref = flt(z[[0, 2]], m0, P0)
        torch.testing.assert_close(full.mean[[0, 2]], ref.mean, rtol=0, atol=1e-10)

    def test_step_matches_forward(self):
        model = self.linear_model()
        flt = self.make_filter(model)
        z = make_data(2, 6, 2, seed=23)
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64)
        res = flt(z, m0, P0)
        belief = flt.initial_belief(m0, P0, batch_size=2)
        for t in range(6):
            belief, prior, info = flt.step(belief, z[:, t])
            torch.testing.assert_close(belief["mean"], res.mean[:, t], rtol=0, atol=1e-12)
            torch.testing.assert_close(info.log_likelihood, res.log_likelihood[:, t], rtol=0, atol=1e-12)

    def test_window_carry_over_equals_full_run(self):
        model = self.linear_model()
        flt = self.make_filter(model)
        z = make_data(2, 12, 2, seed=29)
        m0 = torch.zeros(4, dtype=torch.float64)
        P0 = torch.eye(4, dtype=torch.float64)
        full = flt(z, m0, P0)
        first = flt(z[:, :5], m0, P0)
        second = flt(z[:, 5:], belief=first.final_belief)
        torch.testing.assert_close(second.mean, full.mean[:, 5:], rtol=0, atol=1e-12)

    def test_constrained_values_listed(self):
        flt = self.make_filter(self.linear_model())
        vals = constrained_values(flt)
        assert any(k.endswith("Q") for k in vals) and any(k.endswith("R") for k in vals)


def _raw_named(module):
    return [(n, p) for n, p in module.named_parameters() if n.endswith("original")]
