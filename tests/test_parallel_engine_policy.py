"""The default engine policy (``auto``: large or repeated plain calls run the compiled engine)
and the parallel / functional paths: ``vmap_filter``, ``per_sample_grads``, ``torch.func.grad``
and :class:`ParallelKalmanFilter` never reach the compiled engine, never mark a filter as one it
failed on, and give the loop's values; :class:`IteratedSmoother`'s sequential filters, which are
plain calls, give the eager values whichever engine runs them."""

from __future__ import annotations

import warnings

import pytest
import torch

from difffilter.engines import build, policy
from difffilter.filters import UKF, KalmanFilter, ParallelKalmanFilter
from difffilter.func import per_sample_grads, stack_parameters, vmap_filter
from difffilter.models import FunctionalModel, LinearModel
from difffilter.smoothers import IteratedSmoother

from .test_engine_policy import _Recording

F64 = torch.float64


@pytest.fixture(autouse=True)
def fresh_policy(monkeypatch):
    for name in ("DIFFFILTER_ENGINE", "DIFFFILTER_AUTO_MIN_WORK", "DIFFFILTER_AUTO_MIN_TOTAL"):
        monkeypatch.delenv(name, raising=False)
    policy.set_engine(None)
    for table in (policy._runners, policy._failed, policy._warned, policy._work):
        table.clear()
    yield
    policy.set_engine(None)
    policy._runners.clear()
    policy._failed.clear()


def _linear(k: int) -> LinearModel:
    return LinearModel(
        F=torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64),
        H=torch.tensor([[1.0, 0.0]], dtype=F64),
        Q=0.01 * (k + 1) * torch.eye(2, dtype=F64),
        R=torch.tensor([[0.2 + 0.1 * k]], dtype=F64),
    )


def _data(bsz: int, steps: int):
    g = torch.Generator().manual_seed(7)
    return torch.randn(bsz, steps, 1, generator=g, dtype=F64), torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)


def test_transforms_and_parallel_filter_never_reach_the_compiled_engine(monkeypatch):
    monkeypatch.setattr(policy, "FusedFilter", _Recording)
    _Recording.calls = []
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "1")  # every plain call is "large"
    z, m0, p0 = _data(3, 6)
    kfs = [KalmanFilter(_linear(k)) for k in range(3)]
    ukfs = [UKF(_linear(k)) for k in range(3)]
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*compiled engine.*")
        out = vmap_filter(kfs[0], stack_parameters(kfs), z, m0, p0)
        grads = per_sample_grads(ukfs[0], stack_parameters(ukfs), lambda r: -r.total_log_likelihood.sum(), z, m0, p0)
        params = {k: v.detach() for k, v in kfs[0].named_parameters()}
        g = torch.func.grad(lambda p: torch.func.functional_call(kfs[0], p, (z, m0, p0)).total_log_likelihood.sum())(params)
        par = ParallelKalmanFilter(_linear(0))
        wide = par(z, m0, torch.eye(2, dtype=F64) * 1e12)  # a diffuse start: its first steps run sequentially
    assert _Recording.calls == [] and not policy._failed
    assert policy.last_engine(par) is None  # the scan never asks the policy
    # the same filters' plain calls still take the compiled path, and agree with the transforms
    ref = kfs[0](z, m0, p0)
    assert _Recording.calls == [(3, 6, 1)] and policy.last_engine(kfs[0]) == "generated"
    assert torch.allclose(out.mean[0], ref.mean, atol=1e-12, rtol=0)
    ref_g = torch.autograd.grad(ref.total_log_likelihood.sum(), list(kfs[0].parameters()))
    for a, b in zip(g.values(), ref_g, strict=True):
        assert torch.allclose(a, b, atol=1e-12, rtol=0)
    assert all(v.shape[0] == 3 for v in grads.values())
    assert torch.allclose(wide.mean, KalmanFilter(_linear(0))(z, m0, torch.eye(2, dtype=F64) * 1e12).mean, atol=1e-9)


@pytest.mark.slow
@pytest.mark.skipif(build.compiler_available() is not None, reason="needs a C++ compiler")
def test_large_vmap_under_auto_equals_loop_and_keeps_the_compiled_engine():
    # B * T = 1e4: the plain calls of the loop run compiled, the vmapped call runs eagerly
    z, m0, p0 = _data(100, 100)
    kfs = [KalmanFilter(_linear(k)) for k in range(3)]
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*compiled engine.*")
        out = vmap_filter(kfs[0], stack_parameters(kfs), z, m0, p0)
        assert policy.last_engine(kfs[0]) == "eager"
        loop = [kf(z, m0, p0) for kf in kfs]
    assert [policy.last_engine(kf) for kf in kfs] == ["generated"] * 3 and not policy._failed
    for k, ref in enumerate(loop):
        assert torch.allclose(out.mean[k], ref.mean, atol=1e-12, rtol=0)
        assert torch.allclose(out.log_likelihood[k], ref.log_likelihood, atol=1e-12, rtol=0)


@pytest.mark.slow
@pytest.mark.skipif(build.compiler_available() is not None, reason="needs a C++ compiler")
@pytest.mark.parametrize("parallel", [True, False])
def test_iterated_smoother_same_on_compiled_and_eager(parallel):
    def f(x):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], x[..., 1] - 0.1 * torch.sin(x[..., 0])], -1)

    def h(x):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)

    model = FunctionalModel(f=f, h=h, Q=torch.eye(2, dtype=F64) * 0.01, R=torch.eye(2, dtype=F64) * 0.1)
    g = torch.Generator().manual_seed(3)
    z = 0.3 * torch.randn(2, 12, 2, generator=g, dtype=F64)
    m0, p0 = torch.zeros(2, dtype=F64), 0.5 * torch.eye(2, dtype=F64)
    results = {}
    for engine in ("eager", "compiled"):
        policy.set_engine(engine)
        sm = IteratedSmoother(model, iterations=3, parallel=parallel)
        out = sm(z, m0, p0)
        grads = torch.autograd.grad(out.mean.square().sum() + out.filtered.total_log_likelihood.sum(), list(model.parameters()))
        results[engine] = (out, grads, policy.last_engine(sm.filter))
    assert results["compiled"][2] == "generated" and results["eager"][2] == "eager"
    (a, ga, _), (b, gb, _) = results["eager"], results["compiled"]
    assert torch.allclose(a.mean, b.mean, atol=1e-10, rtol=0) and torch.allclose(a.cov, b.cov, atol=1e-10, rtol=0)
    for x, y in zip(ga, gb, strict=True):
        assert torch.allclose(x, y, atol=1e-9, rtol=0)
