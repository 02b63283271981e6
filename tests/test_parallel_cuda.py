"""CUDA: the parallel filter and smoother, the iterated smoother, ``vmap`` over parameter sets,
per-sample gradients, the default engine policy and ``FusedFilter``'s inductor engine on CUDA
tensors, each against the same computation on the CPU (float64).  Skipped without a CUDA device
(CI has none); ``experiments/gpu_check.sh`` runs them on a GPU machine."""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter, policy
from difffilter.filters import UKF, KalmanFilter, ParallelKalmanFilter
from difffilter.func import per_sample_grads, stack_parameters, vmap_filter
from difffilter.models import FunctionalModel, LinearModel
from difffilter.smoothers import IteratedSmoother, ParallelRTSSmoother

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (none on the CI machine)")

F64 = torch.float64
DEV = "cuda"


def _linear(k: int = 0) -> LinearModel:
    # F and H are buffers, shared by vmapped parameter sets: only Q and R (parameters) vary with k
    g = torch.Generator().manual_seed(0)
    a = torch.randn(3, 3, generator=g, dtype=F64)
    return LinearModel(
        F=0.7 * torch.eye(3, dtype=F64) + 0.2 * torch.randn(3, 3, generator=g, dtype=F64),
        H=torch.randn(2, 3, generator=g, dtype=F64),
        Q=0.1 * a @ a.T + 0.05 * (k + 1) * torch.eye(3, dtype=F64),
        R=torch.tensor([[0.5, 0.1], [0.1, 0.3 + 0.1 * k]], dtype=F64),
    )


def _data(bsz: int, steps: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(bsz, steps, 2, generator=g, dtype=F64)
    mask = torch.rand(bsz, steps, 2, generator=g) > 0.3
    return torch.where(mask, z, torch.full_like(z, float("nan"))), mask, torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)


def _cuda(*xs):  # type: ignore[no-untyped-def]
    return tuple(x.to(DEV) for x in xs)


def _close(a: torch.Tensor, b: torch.Tensor, tol: float) -> None:
    assert a.device.type == "cuda"
    assert torch.allclose(a.cpu(), b, atol=tol, rtol=0), float((a.cpu() - b).abs().max())


def test_parallel_filter_smoother_and_gradients_on_cuda_equal_cpu():
    z, mask, m0, p0 = _data(4, 300)
    outs, grads = [], []
    for dev in ("cpu", DEV):
        model = _linear().to(dev)
        out = ParallelRTSSmoother(ParallelKalmanFilter(model))(z.to(dev), m0.to(dev), p0.to(dev), mask=mask.to(dev))
        grads.append(torch.autograd.grad(out.filtered.total_log_likelihood.sum() + out.mean.sum(), list(model.parameters())))
        outs.append(out)
    cpu, gpu = outs
    for name in ("mean", "cov", "cross_cov"):
        _close(getattr(gpu, name), getattr(cpu, name), 1e-9)
    _close(gpu.filtered.log_likelihood, cpu.filtered.log_likelihood, 1e-9)
    for a, b in zip(grads[1], grads[0], strict=True):
        _close(a, b, 1e-8)
    # and the sequential filter on the same device
    seq = KalmanFilter(_linear().to(DEV))(*_cuda(z), *_cuda(m0, p0), mask=mask.to(DEV))
    _close(gpu.filtered.mean, seq.mean.cpu(), 1e-9)


@pytest.mark.parametrize("method", ["extended", "sigma"])
def test_iterated_smoother_on_cuda_equals_cpu(method):
    def f(x):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], x[..., 1] - 0.1 * torch.sin(x[..., 0])], -1)

    def h(x):
        return torch.stack([torch.sin(x[..., 0]), x[..., 1]], -1)

    g = torch.Generator().manual_seed(3)
    z = 0.3 * torch.randn(3, 64, 2, generator=g, dtype=F64)
    outs = []
    for dev in ("cpu", DEV):
        model = FunctionalModel(f=f, h=h, Q=torch.eye(2, dtype=F64) * 0.01, R=torch.eye(2, dtype=F64) * 0.1).to(dev)
        sm = IteratedSmoother(model, method=method, iterations=4)
        outs.append(sm(z.to(dev), torch.zeros(2, dtype=F64, device=dev), 0.5 * torch.eye(2, dtype=F64, device=dev)))
    _close(outs[1].mean, outs[0].mean, 1e-9)
    _close(outs[1].cov, outs[0].cov, 1e-9)


def test_vmap_and_per_sample_grads_on_cuda_equal_loop():
    z, mask, m0, p0 = _cuda(*_data(3, 40))
    for build in (KalmanFilter, ParallelKalmanFilter, UKF):
        mods = [build(_linear(k).to(DEV)) for k in range(8)]
        params = stack_parameters(mods)
        out = vmap_filter(mods[0], params, z, m0, p0, mask=mask)
        ref = torch.stack([m(z, m0, p0, mask=mask).mean for m in mods])
        assert out.mean.device.type == "cuda" and torch.allclose(out.mean, ref, atol=1e-12, rtol=0), build.__name__

        def loss(r):  # type: ignore[no-untyped-def]
            return -r.total_log_likelihood.sum()

        grads = per_sample_grads(mods[0], params, loss, z, m0, p0, mask=mask)
        for k, mod in enumerate(mods):
            named = dict(mod.named_parameters())
            sep = torch.autograd.grad(loss(mod(z, m0, p0, mask=mask)), list(named.values()))
            for name, gk in zip(named, sep, strict=True):
                assert torch.allclose(grads[name][k], gk, atol=1e-12, rtol=0), (build.__name__, k, name)


def test_default_engine_on_cuda_runs_eagerly_and_equals_cpu(monkeypatch):
    # the auto policy compiles CPU calls only: a large CUDA call is the eager filter, no warning
    monkeypatch.delenv("DIFFFILTER_ENGINE", raising=False)
    policy.set_engine(None)
    z, mask, m0, p0 = _data(128, 100)  # B * T = 12800 >= the auto threshold
    kf_gpu, kf_cpu = KalmanFilter(_linear().to(DEV)), KalmanFilter(_linear())
    gpu = kf_gpu(*_cuda(z), *_cuda(m0, p0), mask=mask.to(DEV))
    assert policy.last_engine(kf_gpu) == "eager"
    policy.set_engine("eager")
    try:
        cpu = kf_cpu(z, m0, p0, mask=mask)
    finally:
        policy.set_engine(None)
    _close(gpu.mean, cpu.mean, 1e-9)
    _close(gpu.log_likelihood, cpu.log_likelihood, 1e-9)


def test_inductor_engine_on_cuda_equals_eager():
    # FusedFilter's CUDA path: the filter's step compiled by torch.compile (inductor, Triton)
    z, mask, m0, p0 = _cuda(*_data(16, 30))
    ukf = UKF(_linear().to(DEV))
    ref = ukf(z, m0, p0, mask=mask)
    fused = FusedFilter(ukf, engine="inductor")
    out = fused(z, m0, p0, mask=mask)
    assert torch.allclose(out.mean, ref.mean, atol=1e-9, rtol=0)
    assert torch.allclose(out.log_likelihood, ref.log_likelihood, atol=1e-9, rtol=0)
    g_ref = torch.autograd.grad(ref.total_log_likelihood.sum(), list(ukf.parameters()))
    g_out = torch.autograd.grad(fused(z, m0, p0, mask=mask).total_log_likelihood.sum(), list(ukf.parameters()))
    for a, b in zip(g_out, g_ref, strict=True):
        assert torch.allclose(a, b, atol=1e-8, rtol=0)
