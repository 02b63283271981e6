"""Tests of the kinematic motion models and the Singer transition / process-noise functions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from torch.func import jacrev, vmap

from difffilter.linalg import block_diag
from difffilter.models.motion import (
    ConstantAcceleration,
    ConstantVelocity,
    CurrentStatistical,
    Singer,
    axis_block_diag,
    constant_acceleration_noise,
    constant_acceleration_transition,
    current_statistical_variance,
    singer_noise_from_variance,
    singer_process_noise,
    singer_transition,
)

F64 = torch.float64
X_GRID = np.logspace(-6, 3, 37)


def van_loan(a: np.ndarray, g: np.ndarray, psd: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference ``(F, Q)`` for ``dx = A x dt + G dW`` by Van Loan's matrix exponential (float64).

    For stiff ``A`` (``|A| dt`` large, where ``exp`` of the block matrix overflows) the interval is
    halved until ``|A| h <= 0.5`` and the result doubled back: ``Q(2h) = F(h) Q(h) F(h)^T + Q(h)``.
    """
    n = a.shape[0]
    h, k = dt, 0
    while np.abs(a).max() * h > 0.5:
        h, k = h / 2, k + 1
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -a * h
    m[:n, n:] = psd * g @ g.T * h
    m[n:, n:] = a.T * h
    e = scipy.linalg.expm(m)
    f = e[n:, n:].T
    q = f @ e[:n, n:]
    for _ in range(k):
        q = f @ q @ f.T + q
        f = f @ f
    return f, q


def singer_reference(alpha: float, dt: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -alpha]])
    return van_loan(a, np.array([[0.0], [0.0], [1.0]]), 2.0 * alpha * sigma**2, dt)


# ---------------------------------------------------------------------------------- Singer functions
@pytest.mark.parametrize("dt", [0.1, 1.0, 7.0])
def test_singer_matches_van_loan_over_the_whole_range(dt: float) -> None:
    sigma = 1.7
    for x in X_GRID:
        alpha = x / dt
        f_ref, q_ref = singer_reference(alpha, dt, sigma)
        f = singer_transition(torch.tensor(alpha, dtype=F64), dt).numpy()
        q = singer_process_noise(torch.tensor(alpha, dtype=F64), dt, sigma).numpy()
        np.testing.assert_allclose(f, f_ref, rtol=1e-9, atol=1e-14 * max(1.0, dt * dt), err_msg=f"x={x}")
        # Every entry of the Singer Q is positive, so an entrywise relative test is meaningful.
        assert (q_ref > 0).all()
        np.testing.assert_allclose(q, q_ref, rtol=1e-9, atol=0, err_msg=f"x={x}")


@pytest.mark.parametrize("dt", [0.01, 0.1, 1.0, 10.0])
def test_singer_float32_is_accurate_and_positive_definite(dt: float) -> None:
    x = torch.logspace(-6, 3, 800, dtype=F64)
    a32, t32 = (x / dt).float(), torch.tensor(dt, dtype=torch.float32)
    a64, t64 = a32.double(), t32.double()  # the same rounded inputs, so only the function's error is measured
    for sigma in (0.01, 1.0, 30.0):
        s32 = torch.tensor(sigma, dtype=torch.float32)
        q64 = singer_process_noise(a64, t64, s32.double())
        q32 = singer_process_noise(a32, t32, s32)
        f64, f32 = singer_transition(a64, t64), singer_transition(a32, t32)
        assert q32.dtype == torch.float32 and f32.dtype == torch.float32
        rel = ((q32.double() - q64) / q64).abs().amax()
        assert rel < 3e-6, rel
        rel_f = (f32.double() - f64).abs() / f64.abs().clamp_min(1e-30)
        # exp(-x) has condition number x: the rounding of x = alpha T in float32 alone costs x eps
        assert rel_f[..., :2, :].max() < 3e-6, rel_f[..., :2, :].max()
        assert bool((rel_f[..., 2, 2] < 3e-6 + 1.2e-7 * x).all())
        _, info = torch.linalg.cholesky_ex(q32)
        assert int((info != 0).sum()) == 0
        # eigenvalues of the float32 matrix (computed exactly in float64) are all positive
        d = torch.diagonal(q32.double(), dim1=-2, dim2=-1).sqrt()
        corr = q32.double() / d[..., :, None] / d[..., None, :]
        assert torch.linalg.eigvalsh(corr)[..., 0].min() > 1e-3


def test_singer_limits() -> None:
    dt = 0.5
    tiny = torch.tensor(1e-9, dtype=F64)
    torch.testing.assert_close(singer_transition(tiny, dt), constant_acceleration_transition(torch.tensor(dt, dtype=F64)))
    torch.testing.assert_close(
        singer_transition(torch.zeros((), dtype=F64), dt), constant_acceleration_transition(torch.tensor(dt, dtype=F64))
    )
    # alpha -> 0 with the driving density 2 alpha sigma^2 held fixed: the white-jerk (CA) noise
    q = singer_process_noise(tiny, dt, 1.0) / (2 * tiny)
    torch.testing.assert_close(q, constant_acceleration_noise(torch.tensor(dt, dtype=F64)), rtol=1e-8, atol=0)
    assert float(singer_process_noise(torch.zeros((), dtype=F64), dt, 3.0).abs().max()) == 0.0
    # alpha T -> infinity: the acceleration decorrelates within a step; its variance is sigma^2
    big = singer_process_noise(torch.tensor(1e4, dtype=F64), dt, 3.0)
    torch.testing.assert_close(big[2, 2], torch.tensor(9.0, dtype=F64))


def test_singer_is_continuous_at_the_branch_switch() -> None:
    dt = 1.0
    below = torch.tensor(2.0 - 1e-9, dtype=F64)
    above = torch.tensor(2.0 + 1e-9, dtype=F64)
    torch.testing.assert_close(singer_process_noise(below, dt, 1.0), singer_process_noise(above, dt, 1.0), rtol=1e-8, atol=0)
    torch.testing.assert_close(singer_transition(below, dt), singer_transition(above, dt), rtol=1e-8, atol=1e-15)


@pytest.mark.parametrize("alpha", [0.0, 1e-7, 0.3, 1.9999, 2.0001, 15.0, 900.0])
def test_singer_gradients_are_finite_and_correct(alpha: float) -> None:
    a = torch.tensor([alpha], dtype=F64, requires_grad=True)
    dt = torch.tensor([1.0], dtype=F64, requires_grad=True)
    s = torch.tensor([0.8], dtype=F64, requires_grad=True)
    out = singer_process_noise(a, dt, s).sum() + singer_transition(a, dt).sum()
    grads = torch.autograd.grad(out, (a, dt, s))
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    if alpha > 0:  # central differences need alpha - h >= 0
        assert torch.autograd.gradcheck(lambda a_, t_, s_: singer_process_noise(a_, t_, s_), (a, dt, s))
        assert torch.autograd.gradcheck(lambda a_, t_: singer_transition(a_, t_), (a, dt))
    for dtype in (torch.float32, F64):  # no nan from the branch torch.where discards
        a32 = torch.tensor([alpha], dtype=dtype, requires_grad=True)
        (singer_process_noise(a32, 1.0, 1.0).sum() + singer_transition(a32, 1.0).sum()).backward()
        assert bool(torch.isfinite(a32.grad).all())


def test_singer_broadcasting_and_variance_form() -> None:
    alpha = torch.tensor([[0.01], [1.0]], dtype=F64)
    dt = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    q = singer_process_noise(alpha, dt, 2.0)
    assert q.shape == (2, 3, 3, 3)
    torch.testing.assert_close(q[1, 2], singer_process_noise(torch.tensor(1.0, dtype=F64), 0.3, 2.0))
    torch.testing.assert_close(singer_noise_from_variance(alpha, dt, 4.0), q)
    assert singer_transition(alpha, dt).shape == (2, 3, 3, 3)


def test_white_noise_models_match_van_loan() -> None:
    dt = 0.7
    a_ca = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    f_ref, q_ref = van_loan(a_ca, np.array([[0.0], [0.0], [1.0]]), 2.5, dt)
    model = ConstantAcceleration(axes=1, dt=dt, q=2.5, dtype=F64)
    np.testing.assert_allclose(model.Q.detach().numpy(), q_ref, rtol=1e-12)
    np.testing.assert_allclose(model.matrix().numpy(), f_ref, rtol=1e-12, atol=1e-15)
    a_cv = np.array([[0.0, 1.0], [0.0, 0.0]])
    f_ref, q_ref = van_loan(a_cv, np.array([[0.0], [1.0]]), 0.4, dt)
    cv = ConstantVelocity(axes=1, dt=dt, q=0.4, dtype=F64)
    np.testing.assert_allclose(cv.Q.detach().numpy(), q_ref, rtol=1e-12)
    np.testing.assert_allclose(cv.matrix().numpy(), f_ref, rtol=1e-12, atol=1e-15)


def test_block_helpers() -> None:
    a = torch.arange(8.0, dtype=F64).reshape(2, 2, 2)
    full = axis_block_diag(a)
    torch.testing.assert_close(full, torch.block_diag(a[0], a[1]))
    b = torch.ones(3, 1, 1, dtype=F64)
    out = block_diag(a[0], b)
    assert out.shape == (3, 3, 3)
    torch.testing.assert_close(out[1], torch.block_diag(a[0], b[1]))


# ---------------------------------------------------------------------------------- models
def _models() -> list[torch.nn.Module]:
    return [
        ConstantVelocity(axes=3, dt=0.2, q=[0.5, 1.0, 2.0], dtype=F64),
        ConstantAcceleration(axes=2, dt=0.2, q=[0.5, 1.0], dtype=F64),
        Singer(axes=3, dt=0.2, tau=[0.5, 20.0, 3000.0], sigma_a=[1.0, 2.0, 0.1], dtype=F64),
        CurrentStatistical(axes=2, dt=0.2, tau=[5.0, 50.0], a_max=[3.0, 4.0], dtype=F64),
    ]


@pytest.mark.parametrize("index", range(4))
def test_analytic_jacobian_matches_autograd(index: int) -> None:
    model = _models()[index]
    gen = torch.Generator().manual_seed(index)
    x = torch.randn(5, model.state_dim, generator=gen, dtype=F64)
    auto = vmap(jacrev(lambda xi: model(xi)))(x)
    torch.testing.assert_close(model.jacobian(x), auto, rtol=0, atol=1e-8)
    # per-step sample interval through u["dt"], sigma-point layout [B, S, n] with u [B, 1, 1]
    dts = torch.tensor([[0.05], [0.1], [0.3], [1.0], [2.0]], dtype=F64)
    u = {"dt": dts}
    auto_u = vmap(jacrev(lambda xi, ui: model(xi, ui)), in_dims=(0, 0))(x, u)
    torch.testing.assert_close(model.jacobian(x, u), auto_u, rtol=0, atol=1e-8)
    xs = torch.randn(5, 7, model.state_dim, generator=gen, dtype=F64)
    out = model(xs, {"dt": dts[:, None]})
    loop = torch.stack([model(xs[i], {"dt": dts[i : i + 1]}) for i in range(5)])
    torch.testing.assert_close(out, loop)


@pytest.mark.parametrize("index", range(4))
def test_models_float32_float64_and_positive_definite_noise(index: int) -> None:
    m64 = _models()[index]
    m32 = _models()[index].float()
    x = torch.randn(4, m64.state_dim, dtype=F64)
    for model, xx in ((m64, x), (m32, x.float())):
        out, q = model(xx), model.process_noise(xx)
        assert out.dtype == xx.dtype and q.dtype == xx.dtype
        assert bool((torch.linalg.cholesky_ex(q)[1] == 0).all())
    torch.testing.assert_close(m32(x.float()).double(), m64(x), rtol=1e-5, atol=1e-5)


def test_singer_model_blocks_and_parameters() -> None:
    model = Singer(axes=2, dt=0.1, tau=[10.0, 100.0], sigma_a=[1.0, 0.5], dtype=F64)
    q = model.process_noise(torch.zeros(6, dtype=F64))
    alpha = torch.tensor([0.1, 0.01], dtype=F64)
    torch.testing.assert_close(q[:3, :3], singer_process_noise(alpha[0], 0.1, 1.0))
    torch.testing.assert_close(q[3:, 3:], singer_process_noise(alpha[1], 0.1, 0.5))
    assert float(q[:3, 3:].detach().abs().max()) == 0.0
    torch.testing.assert_close(model.matrix()[3:, 3:], singer_transition(alpha[1], 0.1))
    # tau and sigma_a are learnable and receive gradients through Q and F
    (q.sum() + model.matrix().sum()).backward()
    grads = [p.grad for p in model.parameters()]
    assert len(grads) == 2 and all(g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0 for g in grads)
    with pytest.raises(ValueError):
        Singer(axes=2, tau=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError):
        Singer(axes=4)
    with pytest.raises(ValueError):
        Singer(tau=1e5)  # outside the Interval(0.1, 1e4)


def test_constant_acceleration_paper_form() -> None:
    model = ConstantAcceleration.paper(axes=2, dt=0.1, sigma_a=0.7, dtype=F64)
    qa = constant_acceleration_noise(torch.tensor(0.1, dtype=F64))
    torch.testing.assert_close(model.Q, torch.block_diag(2 * 0.49 * qa, 2 * 0.49 * qa))


def test_current_statistical_model() -> None:
    dt = 0.5
    model = CurrentStatistical(axes=2, dt=dt, tau=[4.0, 40.0], a_max=[3.0, 5.0], sigma_min=0.01, dtype=F64)
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(6, 6, generator=gen, dtype=F64)
    ca = torch.block_diag(*[constant_acceleration_transition(torch.tensor(dt, dtype=F64))] * 2)
    # a_bar = the state's own acceleration: Phi x + U a is the CA transition exactly
    torch.testing.assert_close(model(x), x @ ca.T)
    alpha = 1.0 / torch.tensor([4.0, 40.0], dtype=F64)
    phi = torch.block_diag(*singer_transition(alpha, dt))
    a_bar = x[:, 2::3]
    torch.testing.assert_close(model(x, {"a_mean": a_bar}), x @ ca.T, rtol=1e-12, atol=1e-12)
    a_in = torch.randn(6, 2, generator=gen, dtype=F64)
    u = {"a_mean": a_in}
    gain = (constant_acceleration_transition(torch.tensor(dt, dtype=F64)) - singer_transition(alpha, dt))[..., :, 2]  # [2, 3]
    expect = x @ phi.T + (gain * a_in[:, :, None]).flatten(-2)
    torch.testing.assert_close(model(x, u), expect)
    torch.testing.assert_close(model.jacobian(x, u), phi.expand(6, 6, 6))
    # adaptive variance: symmetric in a_hat, clamped beyond a_max, (4 - pi)/pi a_max^2 at 0
    k = (4 - math.pi) / math.pi
    a_max = torch.tensor([3.0, 5.0], dtype=F64)
    var = current_statistical_variance(torch.tensor([[1.0, -2.0], [-1.0, 2.0], [7.0, -9.0]], dtype=F64), a_max, 0.0)
    torch.testing.assert_close(var[0], var[1])
    torch.testing.assert_close(var[0], k * torch.tensor([4.0, 9.0], dtype=F64))
    assert float(var[2].abs().max()) == 0.0
    x0 = torch.zeros(6, dtype=F64)
    q0 = model.process_noise(x0)
    v0 = k * a_max**2 + 0.01**2
    torch.testing.assert_close(q0[3:, 3:], singer_noise_from_variance(alpha[1], dt, v0[1]))
    paper = CurrentStatistical(axes=2, dt=dt, tau=4.0, a_max=3.0, noise="paper", dtype=F64)
    qa = constant_acceleration_noise(torch.tensor(dt, dtype=F64))
    torch.testing.assert_close(paper.process_noise(x0)[:3, :3], 2 * (k * 9.0 + 1e-4) * qa)
    # batched state-dependent Q, and gradients reach tau and a_max
    qb = model.process_noise(x)
    assert qb.shape == (6, 6, 6)
    torch.testing.assert_close(qb[4], model.process_noise(x[4]))
    qb.sum().backward()
    assert all(p.grad is not None and bool(torch.isfinite(p.grad).all()) for p in model.parameters())
    with pytest.raises(ValueError):
        CurrentStatistical(noise="other")
