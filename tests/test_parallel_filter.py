"""ParallelKalmanFilter / ParallelRTSSmoother against the sequential KalmanFilter / RTSSmoother,
and the associative scan against a plain loop."""

from __future__ import annotations

import pytest
import torch

from difffilter.filters import KalmanFilter, ParallelKalmanFilter
from difffilter.filters.scan import associative_scan
from difffilter.models import LinearModel, TimeVaryingLinearModel
from difffilter.smoothers import ParallelRTSSmoother, RTSSmoother

F64 = torch.float64
FILTER_FIELDS = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")
SMOOTHER_FIELDS = ("mean", "cov", "cross_cov", "initial_mean", "initial_cov")


def _model(dtype: torch.dtype = F64, *, controls: bool = True, seed: int = 0) -> LinearModel:
    g = torch.Generator().manual_seed(seed)
    n, m, k = 3, 2, 1
    f = 0.6 * torch.eye(n, dtype=dtype) + 0.3 * torch.randn(n, n, generator=g, dtype=dtype)
    a = torch.randn(n, n, generator=g, dtype=dtype)
    return LinearModel(
        F=f,
        H=torch.randn(m, n, generator=g, dtype=dtype),
        Q=0.1 * a @ a.T + 0.05 * torch.eye(n, dtype=dtype),
        R=torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=dtype),
        B=torch.randn(n, k, generator=g, dtype=dtype) if controls else None,
    )


def _data(steps: int, *, bsz: int = 3, dtype: torch.dtype = F64, seed: int = 1, partial: bool = True):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(bsz, steps, 2, generator=g, dtype=dtype)
    u = torch.randn(bsz, steps, 1, generator=g, dtype=dtype)
    mask = torch.rand(bsz, steps, 2, generator=g) > 0.3 if partial else torch.rand(bsz, steps, generator=g) > 0.3
    z = torch.where(mask if partial else mask[..., None], z, torch.full_like(z, float("nan")))  # NaN under False
    return z, u, mask


def _close(a, b, fields, tol):
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert torch.allclose(x, y, rtol=0, atol=tol), f"{name}: max diff {float((x - y).abs().max()):.3e}"


@pytest.mark.parametrize("reverse", [False, True])
def test_associative_scan_equals_loop(reverse):
    # matrix products are associative but not commutative: order errors show
    g = torch.Generator().manual_seed(0)
    for steps in range(1, 18):
        x = torch.randn(2, steps, 3, 3, generator=g, dtype=F64)
        (out,) = associative_scan(lambda a, b: (a[0] @ b[0],), (x,), reverse=reverse)
        order = range(steps - 1, -1, -1) if reverse else range(steps)
        acc, ref = None, [None] * steps
        for t in order:
            acc = x[:, t] if acc is None else acc @ x[:, t]
            ref[t] = acc
        assert torch.allclose(out, torch.stack(ref, 1), atol=1e-12), steps


@pytest.mark.parametrize("steps", [1, 2, 5, 16, 37])
@pytest.mark.parametrize("partial", [True, False])
def test_parallel_filter_and_smoother_equal_sequential(steps, partial):
    model = _model()
    z, u, mask = _data(steps, partial=partial)
    m0, p0 = torch.tensor([0.5, -1.0, 0.2], dtype=F64), torch.eye(3, dtype=F64) * 2.0
    seq = RTSSmoother(KalmanFilter(model))(z, m0, p0, mask=mask, controls=u)
    par = ParallelRTSSmoother(ParallelKalmanFilter(model))(z, m0, p0, mask=mask, controls=u)
    _close(seq.filtered, par.filtered, FILTER_FIELDS, 1e-9)
    _close(seq, par, SMOOTHER_FIELDS, 1e-9)
    assert torch.equal(seq.filtered.final_belief["mean"], seq.filtered.mean[:, -1])
    assert torch.allclose(par.filtered.final_belief["cov"], seq.filtered.final_belief["cov"], atol=1e-9)
    assert par.filtered.untrusted.shape == (3, steps) and not par.filtered.untrusted.any()


def test_gradients_equal_sequential():
    model = _model()
    z, u, mask = _data(12)
    m0 = torch.zeros(3, dtype=F64, requires_grad=True)
    p0 = torch.eye(3, dtype=F64)
    grads = []
    for filt, smoother in ((KalmanFilter(model), RTSSmoother), (ParallelKalmanFilter(model), ParallelRTSSmoother)):
        out = smoother(filt)(z, m0, p0, mask=mask, controls=u)
        loss = -out.total_log_likelihood.sum() + (out.mean**2).sum() + out.cov.diagonal(dim1=-2, dim2=-1).sum()
        params = [p for _, p in filt.named_parameters()] + [m0]
        grads.append(torch.autograd.grad(loss, params))
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, atol=1e-9, rtol=0)


def test_gradcheck_small():
    model = _model(controls=False)
    z, _, mask = _data(4, bsz=1)

    def fn(q_raw, r_raw, m0):
        filt = ParallelKalmanFilter(model)
        sm = ParallelRTSSmoother(filt)
        params = {"filter.model.dynamics.parametrizations.Q.original": q_raw, "filter.model.measurement.parametrizations.R.original": r_raw}
        out = torch.func.functional_call(sm, params, (z, m0, torch.eye(3, dtype=F64)), {"mask": mask})
        return out.total_log_likelihood, out.mean[..., 0], out.cov[..., 1, 1]

    named = dict(ParallelKalmanFilter(model).named_parameters())
    q = named["model.dynamics.parametrizations.Q.original"].detach().clone().requires_grad_()
    r = named["model.measurement.parametrizations.R.original"].detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (q, r, torch.zeros(3, dtype=F64, requires_grad=True)))


def test_time_varying_matrices_and_belief_carry_over():
    g = torch.Generator().manual_seed(3)
    bsz, steps, n, m = 2, 9, 2, 1
    a = torch.randn(bsz, steps, n, n, generator=g, dtype=F64)
    u = {
        "F": torch.eye(n, dtype=F64) + 0.2 * torch.randn(bsz, steps, n, n, generator=g, dtype=F64),
        "c": torch.randn(bsz, steps, n, generator=g, dtype=F64),
        "Q": 0.1 * a @ a.mT + 0.01 * torch.eye(n, dtype=F64),
        "H": torch.randn(bsz, steps, m, n, generator=g, dtype=F64),
        "d": torch.randn(bsz, steps, m, generator=g, dtype=F64),
        "R": 0.2 + torch.rand(bsz, steps, m, m, generator=g, dtype=F64),
    }
    model = TimeVaryingLinearModel(state_dim=n, measurement_dim=m)
    z = torch.randn(bsz, steps, m, generator=g, dtype=F64)
    m0, p0 = torch.zeros(n, dtype=F64), torch.eye(n, dtype=F64)
    seq = RTSSmoother(KalmanFilter(model))(z, m0, p0, controls=u)
    par = ParallelRTSSmoother(ParallelKalmanFilter(model))(z, m0, p0, controls=u)
    _close(seq.filtered, par.filtered, FILTER_FIELDS, 1e-9)
    _close(seq, par, SMOOTHER_FIELDS, 1e-9)
    # two windows with the carried belief equal one window
    filt = ParallelKalmanFilter(model)
    first = filt(z[:, :4], m0, p0, controls={k: v[:, :4] for k, v in u.items()})
    second = filt(z[:, 4:], controls={k: v[:, 4:] for k, v in u.items()}, belief=first.final_belief)
    assert torch.allclose(torch.cat([first.mean, second.mean], 1), seq.filtered.mean, atol=1e-9)


def test_diffuse_prior_runs_exact_sequential_phase():
    model = _model(controls=False)
    z, _, mask = _data(10)
    p0 = torch.diag(torch.tensor([1e12, 1.0, 1e12], dtype=F64))
    seq = KalmanFilter(model)(z, torch.zeros(3, dtype=F64), p0, mask=mask)
    par = ParallelKalmanFilter(model)(z, torch.zeros(3, dtype=F64), p0, mask=mask)
    _close(seq, par, ("mean", "log_likelihood", "nis"), 1e-7)
    assert torch.allclose(seq.cov, par.cov, rtol=1e-7, atol=1e-9)


def test_float32_sanity():
    model64, model32 = _model(), _model(torch.float32)
    z, u, mask = _data(50)
    m0 = torch.zeros(3)
    ref = ParallelRTSSmoother(ParallelKalmanFilter(model64))(z, m0.double(), torch.eye(3, dtype=F64), mask=mask, controls=u)
    out = ParallelRTSSmoother(ParallelKalmanFilter(model32))(z.float(), m0, torch.eye(3), mask=mask, controls=u.float())
    assert out.mean.dtype == torch.float32
    assert torch.allclose(out.mean.double(), ref.mean, atol=1e-4)
    assert torch.allclose(out.filtered.log_likelihood.double(), ref.filtered.log_likelihood, atol=1e-3)


def test_bad_inputs():
    model = _model()
    filt = ParallelKalmanFilter(model)
    z, u, mask = _data(4)
    m0, p0 = torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match="measurements must have shape"):
        filt(z[..., :1], m0, p0, controls=u)
    with pytest.raises(ValueError, match="non-finite value"):
        filt(z, m0, p0, controls=u)  # NaNs without a mask
    with pytest.raises(ValueError, match="mask must have shape"):
        filt(z, m0, p0, mask=mask[:, :2], controls=u)
    with pytest.raises(TypeError, match="dtype"):
        filt(z.float(), m0, p0, mask=mask, controls=u)
    with pytest.raises(ValueError, match="initial_mean and initial_cov are required"):
        filt(z, mask=mask, controls=u)
    with pytest.raises(TypeError, match="KalmanFilter"):
        ParallelRTSSmoother(torch.nn.Linear(2, 2))  # type: ignore[arg-type]


def test_masked_nan_never_reaches_values_or_gradients():
    model = _model()
    z, u, mask = _data(8)
    z = z.clone().requires_grad_()
    out = ParallelRTSSmoother(ParallelKalmanFilter(model))(z, torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64), mask=mask, controls=u)
    assert torch.isfinite(out.mean).all() and torch.isfinite(out.filtered.log_likelihood).all()
    (gz,) = torch.autograd.grad(out.mean.sum() + out.total_log_likelihood.sum(), z)
    assert torch.isfinite(gz).all() and (gz[~mask] == 0).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (none on the CI machine)")
def test_cuda_equals_cpu():
    model = _model()
    z, u, mask = _data(64)
    m0, p0 = torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)
    ref = ParallelRTSSmoother(ParallelKalmanFilter(model))(z, m0, p0, mask=mask, controls=u)
    dev = "cuda"
    out = ParallelRTSSmoother(ParallelKalmanFilter(model.to(dev)))(z.to(dev), m0.to(dev), p0.to(dev), mask=mask.to(dev), controls=u.to(dev))
    assert torch.allclose(out.mean.cpu(), ref.mean, atol=1e-9)
    assert torch.allclose(out.filtered.log_likelihood.cpu(), ref.filtered.log_likelihood, atol=1e-9)


def test_long_window_equals_sequential():
    # T = 1000 with partial masks: the scan's rounding does not grow past the tolerance
    model = _model()
    z, u, mask = _data(1000, bsz=2, seed=4)
    m0, p0 = torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)
    seq = RTSSmoother(KalmanFilter(model))(z, m0, p0, mask=mask, controls=u)
    par = ParallelRTSSmoother(ParallelKalmanFilter(model))(z, m0, p0, mask=mask, controls=u)
    _close(seq.filtered, par.filtered, FILTER_FIELDS, 1e-9)
    _close(seq, par, SMOOTHER_FIELDS, 1e-9)
    assert float((seq.filtered.total_log_likelihood - par.filtered.total_log_likelihood).detach().abs().max()) < 1e-9
