"""Smoothers against independent references: the dense joint Gaussian of a linear window (exact
conditional, 1e-10 in float64, with masks, controls and carried-over beliefs), filterpy's and
dynamax's RTS / unscented RTS smoothers, and finite-difference gradients."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, RCUKF, UKF, ColoredNoiseUKF, Cubature, Julier, KalmanFilter, MerweScaled, SimplifiedUKF, SquareRootUKF
from difffilter.models import FunctionalModel, LinearModel
from difffilter.smoothers import FixedLagSmoother, RTSSmoother, SmootherResult, UnscentedRTSSmoother, make_smoother
from tests.filter_contract import cv_matrices
from tests.smoother_reference import dense_smoother

HAS_FILTERPY = importlib.util.find_spec("filterpy") is not None
HAS_DYNAMAX = importlib.util.find_spec("dynamax") is not None and importlib.util.find_spec("jax") is not None
F64 = torch.float64
CTRL = torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.3], [0.0, 1.0]], dtype=F64)
M0 = torch.tensor([1.0, -0.5, 2.0, 0.3], dtype=F64)
P0 = torch.tensor([[4.0, 0.3, 0.0, 0.0], [0.3, 1.0, 0.0, 0.1], [0.0, 0.0, 4.0, 0.2], [0.0, 0.1, 0.2, 1.0]], dtype=F64)


def linear_window(B=3, T=9, seed=0, missing=0.3):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(B, T, 2, generator=g, dtype=F64).cumsum(1)
    u = torch.randn(B, T, 2, generator=g, dtype=F64)
    mask = torch.rand(B, T, 2, generator=g) > missing
    if missing > 0:
        mask[0, 2] = False  # a fully missing step
    return torch.where(mask, z, torch.nan), u, mask


def reference(z, u, mask, b, m0=M0, p0=P0, **kw):
    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    return dense_smoother(
        z[b].numpy(), m0.detach().numpy(), p0.detach().numpy(), mats["F"], mats["H"], mats["Q"], mats["R"],
        mask=None if mask is None else mask[b].numpy(), offsets=(u[b] @ CTRL.T).numpy(), **kw,
    )  # fmt: skip


def assert_matches_reference(out: SmootherResult, z, u, mask, tol=1e-10, m0=M0, p0=P0):
    for b in range(z.shape[0]):
        m0b = m0 if m0.ndim == 1 else m0[b]
        p0b = p0 if p0.ndim == 2 else p0[b]
        ref = reference(z, u, mask, b, m0b, p0b)
        np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], rtol=0, atol=tol)
        np.testing.assert_allclose(out.cov[b].detach().numpy(), ref["cov"], rtol=0, atol=tol)
        np.testing.assert_allclose(out.cross_cov[b].detach().numpy(), ref["cross"], rtol=0, atol=tol)
        np.testing.assert_allclose(out.initial_mean[b].detach().numpy(), ref["initial_mean"], rtol=0, atol=tol)
        np.testing.assert_allclose(out.initial_cov[b].detach().numpy(), ref["initial_cov"], rtol=0, atol=tol)
        assert abs(out.log_likelihood[b].sum().item() - ref["log_likelihood"]) < 1e-9


def linear_model(dtype=F64):
    return LinearModel(**{k: v.to(dtype) for k, v in cv_matrices().items()}, B=CTRL.to(dtype))


LINEAR_FILTERS = {
    "kf": lambda m: KalmanFilter(m),
    "ekf": lambda m: EKF(m),
    "ekf-rev": lambda m: EKF(m, jacobian_mode="rev"),
    "ukf-merwe": lambda m: UKF(m, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=1.0)),
    "ukf-julier-reuse": lambda m: UKF(m, sigma_points=Julier(kappa=-1.0), redraw_after_predict=False),
    "ukf-cubature": lambda m: UKF(m, sigma_points=Cubature()),
    "ukf-augmented": lambda m: UKF(m, noise="augmented"),
    "ukf-augmented-reuse": lambda m: UKF(m, noise="augmented", redraw_after_predict=False),
    "simplified-ukf": lambda m: SimplifiedUKF(m),
    "sqrt-ukf": lambda m: SquareRootUKF(m),
}


@pytest.mark.parametrize("name", list(LINEAR_FILTERS))
def test_rts_equals_dense_joint_conditional_with_masks_and_controls(name):
    z, u, mask = linear_window()
    out = make_smoother(LINEAR_FILTERS[name](linear_model()))(z, M0, P0, mask=mask, controls=u)
    assert isinstance(out, SmootherResult) and out.mean.shape == (3, 9, 4) and out.cross_cov.shape == (3, 9, 4, 4)
    assert_matches_reference(out, z, u, mask)
    # the filter's result is kept: its last step is already smoothed
    torch.testing.assert_close(out.mean[:, -1], out.filtered.mean[:, -1], rtol=0, atol=0)


def test_unscented_smoother_equals_rts_on_linear_models():
    z, u, mask = linear_window(T=15, seed=4)
    rts = RTSSmoother(KalmanFilter(linear_model()))(z, M0, P0, mask=mask, controls=u)
    for pts in (MerweScaled(alpha=1.0), Julier(kappa=0.5), Cubature()):
        urts = UnscentedRTSSmoother(UKF(linear_model(), sigma_points=pts))(z, M0, P0, mask=mask, controls=u)
        torch.testing.assert_close(urts.mean, rts.mean, rtol=0, atol=1e-11)
        torch.testing.assert_close(urts.cov, rts.cov, rtol=0, atol=1e-11)
        torch.testing.assert_close(urts.cross_cov, rts.cross_cov, rtol=0, atol=1e-11)


def test_window_from_a_carried_over_belief_is_the_conditional_given_that_prior():
    z, u, mask = linear_window(T=12, seed=2)
    smoother = RTSSmoother(KalmanFilter(linear_model()))
    first = smoother(z[:, :5], M0, P0, mask=mask[:, :5], controls=u[:, :5])
    second = smoother(z[:, 5:], mask=mask[:, 5:], controls=u[:, 5:], belief=first.final_belief)
    carried = first.final_belief
    assert_matches_reference(second, z[:, 5:], u[:, 5:], mask[:, 5:], m0=carried["mean"], p0=carried["cov"])
    # the carried belief is the filter's, so the filter itself is unchanged by windowing
    whole = smoother(z, M0, P0, mask=mask, controls=u)
    torch.testing.assert_close(second.filtered.mean, whole.filtered.mean[:, 5:], rtol=0, atol=1e-12)


def test_rcukf_smoother_equals_the_dense_joint_with_the_faded_process_noise():
    """On a linear model the RC-UKF is a Kalman filter whose step-t process noise is
    ``Q + (eta_t - 1) F P_{t-1} F^T``; its smoother must be that model's exact conditional."""
    mats = cv_matrices()
    model = LinearModel(**mats)
    g = torch.Generator().manual_seed(5)
    z = (3.0 * torch.randn(2, 10, 2, generator=g, dtype=F64)).cumsum(1)  # large residuals: eta > 1
    for per_state in (False, True):
        filt = RCUKF(model, rho=0.6, per_state=per_state)
        out = RTSSmoother(filt)(z, M0, P0)
        eta = out.filtered.fading_factor.detach()
        assert bool((eta > 1.0 + 1e-3).any())
        F, Q = mats["F"], mats["Q"]
        for b in range(2):
            prev = torch.cat([P0[None], out.filtered.cov[b, :-1].detach()])
            spread = F @ prev @ F.T
            root = eta[b].sqrt()
            scale = root[:, :, None] * root[:, None, :] if per_state else eta[b][:, None, None]
            qs = [(Q + (scale[t] - 1.0) * spread[t]).numpy() for t in range(10)]
            ref = dense_smoother(z[b].numpy(), M0.numpy(), P0.numpy(), F.numpy(), mats["H"].numpy(), qs, mats["R"].numpy())
            np.testing.assert_allclose(out.mean[b].detach().numpy(), ref["mean"], rtol=0, atol=1e-10)
            np.testing.assert_allclose(out.cov[b].detach().numpy(), ref["cov"], rtol=0, atol=1e-10)


def test_batch_equals_loop_and_time_chunks_change_nothing():
    z, u, mask = linear_window(B=4, T=11, seed=7)
    ukf = UKF(linear_model())
    whole = RTSSmoother(ukf)(z, M0, P0, mask=mask, controls=u)
    chunked = RTSSmoother(ukf, time_chunk=3)(z, M0, P0, mask=mask, controls=u)
    torch.testing.assert_close(chunked.mean, whole.mean, rtol=0, atol=1e-13)
    for b in range(4):
        one = RTSSmoother(ukf)(z[b : b + 1], M0, P0, mask=mask[b : b + 1], controls=u[b : b + 1])
        torch.testing.assert_close(one.mean[0], whole.mean[b], rtol=0, atol=1e-12)
        torch.testing.assert_close(one.cov[0], whole.cov[b], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["kf", "ukf-merwe"])
def test_float32_matches_float64(name):
    z, u, mask = linear_window(T=20, seed=3)
    ref = make_smoother(LINEAR_FILTERS[name](linear_model()))(z, M0, P0, mask=mask, controls=u)
    f32 = make_smoother(LINEAR_FILTERS[name](linear_model(torch.float32)))(
        z.float(), M0.float(), P0.float(), mask=mask, controls=u.float()
    )  # fmt: skip
    assert f32.mean.dtype == torch.float32 and f32.cross_cov.dtype == torch.float32
    scale = ref.mean.abs().amax()
    assert ((f32.mean.double() - ref.mean).abs().amax() / scale).item() < 1e-5
    assert ((f32.cov.double() - ref.cov).abs().amax() / ref.cov.abs().amax()).item() < 1e-4


def test_nan_under_the_mask_reaches_neither_outputs_nor_gradients():
    z, u, mask = linear_window(T=8, seed=1)
    model = linear_model()
    z = z.clone().requires_grad_(True)
    out = RTSSmoother(EKF(model))(z, M0, P0, mask=mask, controls=u)
    loss = out.mean.sum() + out.cov.sum() + out.cross_cov.sum()
    loss.backward()
    assert torch.isfinite(out.mean).all() and torch.isfinite(z.grad).all()
    assert bool((z.grad[~mask] == 0).all())
    raw = model.dynamics.parametrizations.Q.original
    assert raw.grad is not None and torch.isfinite(raw.grad).all()


def pendulum(dtype=F64, dt=0.05, r=0.02, q=1.0):
    def f(x):
        return torch.stack([x[..., 0] + dt * x[..., 1], x[..., 1] - 9.81 * dt * torch.sin(x[..., 0])], -1)

    def h(x):
        return torch.sin(x[..., :1]) + 0.5 * x[..., 1:] ** 2 / 10

    return (
        FunctionalModel(f=f, h=h, Q=q * torch.tensor([[1e-4, 5e-5], [5e-5, 2e-3]], dtype=dtype), R=torch.tensor([[r]], dtype=dtype)),
        f,
        h,
    )


def pendulum_data(B=2, T=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    _, f, h = pendulum()
    x = torch.tensor([1.2, 0.0], dtype=F64).expand(B, 2)
    zs, xs = [], []
    for _ in range(T):
        x = f(x) + torch.randn(B, 2, generator=g, dtype=F64) * torch.tensor([1e-2, 4e-2], dtype=F64)
        xs.append(x)
        zs.append(h(x) + 0.14 * torch.randn(B, 1, generator=g, dtype=F64))
    return torch.stack(zs, 1), torch.stack(xs, 1)


def test_smoothing_reduces_the_error_on_a_nonlinear_model():
    z, truth = pendulum_data(B=16, T=60)
    model, _, _ = pendulum()
    m0, p0 = torch.tensor([1.0, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.1], dtype=F64))
    for filt in (EKF(model), UKF(model)):
        out = RTSSmoother(filt)(z, m0, p0)
        filt_err = ((out.filtered.mean - truth) ** 2).mean()
        smooth_err = ((out.mean - truth) ** 2).mean()
        assert smooth_err.item() < 0.8 * filt_err.item()


@pytest.mark.skipif(not HAS_FILTERPY, reason="filterpy not installed")
def test_rts_matches_filterpy_kalman_rts_smoother():
    from filterpy.kalman import KalmanFilter as FpKF

    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    z, _, _ = linear_window(B=1, T=25, missing=0.0)
    out = RTSSmoother(KalmanFilter(LinearModel(**cv_matrices())))(z, M0, P0)
    kf = FpKF(dim_x=4, dim_z=2)
    kf.F, kf.H, kf.Q, kf.R = mats["F"], mats["H"], mats["Q"], mats["R"]
    kf.x, kf.P = M0.numpy().copy(), P0.numpy().copy()
    xs, ps, _, _ = kf.batch_filter(z[0].numpy())
    np.testing.assert_allclose(xs, out.filtered.mean[0].detach().numpy(), rtol=0, atol=1e-10)
    sx, sp, _, _ = kf.rts_smoother(xs, ps)
    np.testing.assert_allclose(out.mean[0].detach().numpy(), sx, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.cov[0].detach().numpy(), sp, rtol=0, atol=1e-10)


@pytest.mark.skipif(not HAS_FILTERPY, reason="filterpy not installed")
def test_unscented_rts_matches_filterpy_ukf_rts_smoother():
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    model, f, h = pendulum()
    z, _ = pendulum_data(B=1, T=40, seed=2)
    m0, p0 = torch.tensor([1.0, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64))
    alpha, beta, kappa = 0.8, 2.0, 0.5
    out = RTSSmoother(UKF(model, sigma_points=MerweScaled(alpha=alpha, beta=beta, kappa=kappa)))(z, m0, p0)
    npf = lambda x, dt: f(torch.as_tensor(x)).numpy()  # noqa: E731
    nph = lambda x: h(torch.as_tensor(x)).numpy()  # noqa: E731
    ukf = UnscentedKalmanFilter(dim_x=2, dim_z=1, dt=0.05, fx=npf, hx=nph, points=MerweScaledSigmaPoints(2, alpha, beta, kappa))
    ukf.x, ukf.P = m0.numpy().copy(), p0.numpy().copy()
    ukf.Q, ukf.R = model.Q.detach().numpy(), model.R.detach().numpy()
    xs, ps = ukf.batch_filter(z[0].numpy())
    np.testing.assert_allclose(xs, out.filtered.mean[0].detach().numpy(), rtol=0, atol=1e-10)
    sx, sp, _ = ukf.rts_smoother(xs, ps)
    np.testing.assert_allclose(out.mean[0].detach().numpy(), sx, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.cov[0].detach().numpy(), sp, rtol=0, atol=1e-10)


@pytest.mark.skipif(not HAS_DYNAMAX, reason="dynamax/jax not installed")
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_matches_dynamax_extended_and_unscented_smoothers(kind, monkeypatch):
    import dynamax.nonlinear_gaussian_ssm.inference_ekf as dx_ekf
    import dynamax.nonlinear_gaussian_ssm.inference_ukf as dx_ukf
    import jax
    import jax.numpy as jnp
    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, UKFHyperParams, extended_kalman_smoother, unscented_kalman_smoother

    jax.config.update("jax_enable_x64", True)
    # dynamax regularises its solves (1e-9 added to the innovation and predicted covariances);
    # without it the algorithms are the same
    for mod in (dx_ekf, dx_ukf):
        monkeypatch.setattr(mod, "psd_solve", lambda a, b, solve=mod.psd_solve: solve(a, b, diagonal_boost=0.0))
    model, _, _ = pendulum()
    z, _ = pendulum_data(B=2, T=30, seed=3)
    m0, p0 = torch.tensor([1.0, 0.0], dtype=F64), torch.diag(torch.tensor([0.1, 0.2], dtype=F64))
    alpha, beta, kappa = 1.0, 2.0, 0.0
    filt = EKF(model) if kind == "ekf" else UKF(model, sigma_points=MerweScaled(alpha=alpha, beta=beta, kappa=kappa))
    out = RTSSmoother(filt)(z, m0, p0)
    dt = 0.05

    def f(x):
        return jnp.stack([x[0] + dt * x[1], x[1] - 9.81 * dt * jnp.sin(x[0])])

    def h(x):
        return jnp.stack([jnp.sin(x[0]) + 0.5 * x[1] ** 2 / 10])

    for b in range(2):
        # dynamax conditions on y_0 before predicting: its initial belief is our first prior
        params = ParamsNLGSSM(
            initial_mean=jnp.asarray(out.filtered.prior_mean[b, 0].detach().numpy()),
            initial_covariance=jnp.asarray(out.filtered.prior_cov[b, 0].detach().numpy()),
            dynamics_function=f, dynamics_covariance=jnp.asarray(model.Q.detach().numpy()),
            emission_function=h, emission_covariance=jnp.asarray(model.R.detach().numpy()),
        )  # fmt: skip
        ys = jnp.asarray(z[b].numpy())
        post = (
            extended_kalman_smoother(params, ys)
            if kind == "ekf"
            else unscented_kalman_smoother(params, ys, UKFHyperParams(alpha, beta, kappa))
        )
        np.testing.assert_allclose(out.filtered.mean[b].detach().numpy(), np.asarray(post.filtered_means), rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.mean[b].detach().numpy(), np.asarray(post.smoothed_means), rtol=0, atol=1e-10)
        np.testing.assert_allclose(out.cov[b].detach().numpy(), np.asarray(post.smoothed_covariances), rtol=0, atol=1e-10)


def test_gradients_match_finite_differences():
    z, u, mask = linear_window(B=2, T=6, seed=9)
    z = torch.nan_to_num(z)

    for smoother in (RTSSmoother(EKF(linear_model())), RTSSmoother(UKF(linear_model())), FixedLagSmoother(EKF(linear_model()), lag=2)):
        raw = dict(smoother.filter.named_parameters())

        def fn(q_raw, r_raw, zz, m0, smoother=smoother, raw=raw):
            out = torch.func.functional_call(
                smoother, {f"filter.{k}": v for k, v in zip(raw, (q_raw, r_raw), strict=True)}, (zz, m0, P0), {"mask": mask, "controls": u}
            )
            cross = out.mean[..., 0] if out.cross_cov is None else out.cross_cov[..., 0, 1]
            return out.mean.sum(-1), out.cov.diagonal(dim1=-2, dim2=-1).sum(-1), cross

        assert list(raw) == ["model.dynamics.parametrizations.Q.original", "model.measurement.parametrizations.R.original"]
        args = tuple(p.detach().clone().requires_grad_(True) for p in raw.values()) + (
            z.clone().requires_grad_(True),
            M0.clone().requires_grad_(True),
        )
        assert torch.autograd.gradcheck(fn, args, atol=1e-6, rtol=1e-5)


def test_fixed_lag_equals_the_dense_conditional_on_the_first_t_plus_lag_measurements():
    z, u, mask = linear_window(B=2, T=10, seed=6)
    for lag in (0, 1, 3, 9, 15):
        out = FixedLagSmoother(KalmanFilter(linear_model()), lag=lag)(z, M0, P0, mask=mask, controls=u)
        assert out.lag == lag and out.cross_cov is None
        for b in range(2):
            for t in range(10):
                ref = reference(z, u, mask, b, upto=min(t + lag, 9))
                np.testing.assert_allclose(out.mean[b, t].detach().numpy(), ref["mean"][t], rtol=0, atol=1e-10)
                np.testing.assert_allclose(out.cov[b, t].detach().numpy(), ref["cov"][t], rtol=0, atol=1e-10)
    full = RTSSmoother(UKF(linear_model()))(z, M0, P0, mask=mask, controls=u)
    long = FixedLagSmoother(UKF(linear_model()), lag=12)(z, M0, P0, mask=mask, controls=u)
    torch.testing.assert_close(long.mean, full.mean, rtol=0, atol=1e-12)


def test_fixed_lag_online_steps_equal_the_batch_result():
    z, u, mask = linear_window(B=3, T=12, seed=8)
    model = linear_model()
    lag = 3
    smoother = FixedLagSmoother(UKF(model), lag=lag)
    batch = smoother(z, M0, P0, mask=mask, controls=u)
    state = smoother.init_state(M0, P0, batch_size=3)
    for t in range(12):
        state, mean, cov = smoother.step(state, z[:, t], mask[:, t], u[:, t])
        target = max(t - lag, 0)
        if t >= lag:
            torch.testing.assert_close(mean, batch.mean[:, target], rtol=0, atol=1e-12)
            torch.testing.assert_close(cov, batch.cov[:, target], rtol=0, atol=1e-12)
        else:
            ref = reference(z, u, mask, 0, upto=t)
            np.testing.assert_allclose(mean[0].detach().numpy(), ref["mean"][0], rtol=0, atol=1e-10)
    torch.testing.assert_close(state["belief"]["mean"], batch.final_belief["mean"], rtol=0, atol=1e-12)


def test_bad_inputs_raise_naming_the_problem():
    model = linear_model()
    with pytest.raises(ValueError, match="lag"):
        FixedLagSmoother(KalmanFilter(model), lag=-1)
    with pytest.raises(ValueError, match="smoother kind"):
        make_smoother(KalmanFilter(model), "two_filter")
    with pytest.raises(ValueError, match="lag"):
        make_smoother(KalmanFilter(model), "fixed_lag")
    with pytest.raises(TypeError, match="ColoredNoiseUKF"):
        RTSSmoother(ColoredNoiseUKF(LinearModel(**cv_matrices())))
    with pytest.raises(TypeError, match="UKF-family"):
        UnscentedRTSSmoother(EKF(model))
    with pytest.raises(TypeError, match="GaussianFilter|KalmanFilter"):
        RTSSmoother(model)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="initial_mean"):
        RTSSmoother(KalmanFilter(model))(torch.zeros(1, 3, 2, dtype=F64))
