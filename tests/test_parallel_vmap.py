"""torch.func.vmap over parameter sets (difffilter.func) against a Python loop over the filters."""

from __future__ import annotations

import pytest
import torch

from difffilter.filters import EKF, UKF, FilterResult, IteratedEKF, KalmanFilter, ParallelKalmanFilter, SquareRootUKF
from difffilter.func import per_sample_grads, stack_parameters, vmap_filter
from difffilter.mixers import IMM
from difffilter.models import LinearModel
from difffilter.smoothers import IteratedSmoother, ParallelRTSSmoother, RTSSmoother, SmootherResult

F64 = torch.float64
K = 8


def _model(k: int) -> LinearModel:
    g = torch.Generator().manual_seed(k)
    a = torch.randn(2, 2, generator=g, dtype=F64)
    return LinearModel(
        F=torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64),
        H=torch.tensor([[1.0, 0.0]], dtype=F64),
        Q=0.05 * a @ a.T + 0.01 * (k + 1) * torch.eye(2, dtype=F64),
        R=torch.tensor([[0.2 + 0.1 * k]], dtype=F64),
    )


def _data():
    g = torch.Generator().manual_seed(99)
    z = torch.randn(3, 7, 1, generator=g, dtype=F64)
    mask = torch.rand(3, 7, generator=g) > 0.3
    return torch.where(mask[..., None], z, torch.full_like(z, float("nan"))), mask


def _leaves(result):
    if isinstance(result, SmootherResult):
        yield from (("mean", result.mean), ("cov", result.cov), ("cross_cov", result.cross_cov), ("initial_cov", result.initial_cov))
        result = result.filtered
    assert isinstance(result, FilterResult)
    for name in ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed"):
        yield name, getattr(result, name)
    for name, value in result.final_belief.items():
        yield f"final_belief[{name}]", value
    for name, value in result.extras.items():
        yield f"extras[{name}]", value


BUILDERS = {
    "KalmanFilter": KalmanFilter,
    "ParallelKalmanFilter": ParallelKalmanFilter,
    "EKF": EKF,
    "IteratedEKF": IteratedEKF,
    "UKF": UKF,
    "SquareRootUKF": SquareRootUKF,
    "RTSSmoother": lambda m: RTSSmoother(KalmanFilter(m)),
    "ParallelRTSSmoother": lambda m: ParallelRTSSmoother(ParallelKalmanFilter(m)),
    "IteratedSmoother": lambda m: IteratedSmoother(m, iterations=2),
}


@pytest.mark.parametrize("name", list(BUILDERS))
def test_vmap_equals_loop(name):
    modules = [BUILDERS[name](_model(k)) for k in range(K)]
    params = stack_parameters(modules)
    z, mask = _data()
    m0, p0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)
    out = vmap_filter(modules[0], params, z, m0, p0, mask=mask)
    loop = [mod(z, m0, p0, mask=mask) for mod in modules]
    for (label, batched), *refs in zip(_leaves(out), *(_leaves(r) for r in loop), strict=True):
        ref = torch.stack([r[1] for r in refs])
        assert batched.shape == ref.shape, label
        if ref.dtype == torch.bool:
            assert torch.equal(batched, ref), label
        else:
            assert torch.allclose(batched, ref, atol=1e-12, rtol=0), f"{name} {label}: {float((batched - ref).abs().max()):.2e}"


@pytest.mark.parametrize("name", ["KalmanFilter", "ParallelKalmanFilter", "UKF", "ParallelRTSSmoother"])
def test_per_sample_grads_equal_separate_backward(name):
    modules = [BUILDERS[name](_model(k)) for k in range(K)]
    params = stack_parameters(modules)
    z, mask = _data()
    m0, p0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)

    def loss(result):
        return -result.total_log_likelihood.sum() + (result.mean**2).sum()

    grads = per_sample_grads(modules[0], params, loss, z, m0, p0, mask=mask)
    for k, mod in enumerate(modules):
        named = dict(mod.named_parameters())
        ref = torch.autograd.grad(loss(mod(z, m0, p0, mask=mask)), list(named.values()))
        for (pname, _), g in zip(named.items(), ref, strict=True):
            assert torch.allclose(grads[pname][k], g, atol=1e-12, rtol=0), (k, pname)


def test_vmap_imm_with_separate_models():
    def imm(k):
        return IMM(
            [KalmanFilter(_model(k)), EKF(_model(k + 1))],
            transition=torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=F64),
            initial_probs=torch.tensor([0.6, 0.4], dtype=F64),
        )

    modules = [imm(k) for k in range(3)]
    z, mask = _data()
    out = vmap_filter(modules[0], stack_parameters(modules), z, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), mask=mask)
    ref = torch.stack([m(z, torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), mask=mask).mean for m in modules])
    assert torch.allclose(out.mean, ref, atol=1e-12, rtol=0)


def test_errors():
    z, mask = _data()
    m0, p0 = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)
    kf = KalmanFilter(_model(0))
    params = stack_parameters([kf, KalmanFilter(_model(1))])
    with pytest.raises(ValueError, match="not a parameter"):
        vmap_filter(kf, {"nope": torch.zeros(2, 1)}, z, m0, p0, mask=mask)
    bad = dict(params)
    first = next(iter(bad))
    bad[first] = torch.cat([bad[first], bad[first]])
    with pytest.raises(ValueError, match="same leading size"):
        vmap_filter(kf, bad, z, m0, p0, mask=mask)
    with pytest.raises(ValueError, match="one structure"):
        stack_parameters([kf, UKF(_model(1))])
    with pytest.raises(ValueError, match="non-empty"):
        vmap_filter(kf, {}, z, m0, p0)
    shared = _model(2)
    tied = IMM(
        [KalmanFilter(shared), EKF(shared)],
        transition=torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=F64),
        initial_probs=torch.tensor([0.5, 0.5], dtype=F64),
    )
    with pytest.raises(TypeError, match="shares a parameter"):
        vmap_filter(tied, stack_parameters([tied]), z, m0, p0)
    with pytest.raises(ValueError, match="scalar"):
        per_sample_grads(kf, params, lambda r: r.log_likelihood, z, m0, p0, mask=mask)
    # the unmodified module still runs (parameters restored) and validates values again
    with pytest.raises(ValueError, match="non-finite"):
        kf(z, m0, p0)
