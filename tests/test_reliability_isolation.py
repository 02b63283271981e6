"""Batch isolation: one corrupted trajectory never reaches another trajectory's gradient.

Trajectory 1 of a batch of three gets a measurement at 1e300 (float64) / 1e30 (float32), or a NaN
control, at one step.  The gradients of the other trajectories' summed log-likelihood (what the
learner's batch mean keeps) with respect to the shared parameters, the measurements and the
initial means must equal those of the clean trajectories filtered alone, and the corrupted
trajectory must be flagged in ``extras["untrusted"]``.  Before the fix, 10 of these cases gave
NaN parameter gradients (the corrupted trajectory's ``0 * inf`` in the shared parameters' sum).
"""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.engines.build import compiler_available
from difffilter.filters import UKF, KalmanFilter, SquareRootUKF
from difffilter.mixers import IMM
from experiments.benchmarks.isolation import isolation_model as _model

F64, F32 = torch.float64, torch.float32
BAD = 1


def _filter(kind: str, dtype: torch.dtype):  # type: ignore[no-untyped-def]
    if kind == "IMM(KF, UKF)":
        pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=dtype)
        return IMM([KalmanFilter(_model(dtype)), UKF(_model(dtype))], pi, torch.tensor([0.5, 0.5], dtype=dtype))
    return {"KalmanFilter": KalmanFilter, "UKF": UKF, "SquareRootUKF": SquareRootUKF}[kind](_model(dtype))


def _data(dtype: torch.dtype, corruption: str, batch: int = 3, steps: int = 6):  # type: ignore[no-untyped-def]
    g = torch.Generator().manual_seed(0)
    z = torch.randn(batch, steps, 2, generator=g, dtype=F64).to(dtype)
    u = (0.1 * torch.randn(batch, steps, 2, generator=g, dtype=F64)).to(dtype)
    if corruption == "huge measurement":
        z[BAD, 2, 0] = 1e300 if dtype == F64 else 1e30
    elif corruption == "NaN control":
        u[BAD, 2, 1] = float("nan")
    m0 = (0.1 * torch.randn(batch, 4, generator=g, dtype=F64)).to(dtype)
    p0 = torch.eye(4, dtype=dtype).expand(batch, 4, 4).clone()
    return z, u, m0, p0


def _grads(filt, z, u, m0, p0, keep):  # type: ignore[no-untyped-def]
    z = z.clone().requires_grad_(True)
    m0 = m0.clone().requires_grad_(True)
    out = filt(z, m0, p0, controls=u)
    params = [p for p in filt.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.log_likelihood[keep].sum(), [*params, z, m0])
    return out, grads[: len(params)], grads[len(params)][keep], grads[len(params) + 1][keep]


def _check_isolated(filt, dtype: torch.dtype, corruption: str) -> None:  # type: ignore[no-untyped-def]
    z, u, m0, p0 = _data(dtype, corruption)
    clean = [b for b in range(z.shape[0]) if b != BAD]
    out, g_par, g_z, g_m0 = _grads(filt, z, u, m0, p0, clean)
    alone, a_par, a_z, a_m0 = _grads(filt, z[clean], u[clean], m0[clean], p0[clean], list(range(len(clean))))
    tol = 1e-9 if dtype == F64 else 2e-4
    for got, want in [*zip(g_par, a_par, strict=True), (g_z, a_z), (g_m0, a_m0)]:
        assert torch.isfinite(got).all(), "a corrupted trajectory made another's gradient non-finite"
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)
    torch.testing.assert_close(out.mean[clean], alone.mean, rtol=tol, atol=tol)
    assert bool(out.extras["untrusted"][BAD].any()), "the corrupted trajectory is not flagged"
    assert not bool(out.extras["untrusted"][clean].any())


CASES = [
    (kind, dtype, corruption)
    for kind in ("KalmanFilter", "UKF", "SquareRootUKF")
    for dtype in (F64, F32)
    for corruption in ("huge measurement", "NaN control")
]


@pytest.mark.parametrize(("kind", "dtype", "corruption"), CASES, ids=[f"{k}-{str(d)[6:]}-{c}" for k, d, c in CASES])
def test_a_corrupted_trajectory_leaves_the_others_gradients_alone(kind: str, dtype: torch.dtype, corruption: str) -> None:
    _check_isolated(_filter(kind, dtype), dtype, corruption)


@pytest.mark.parametrize("corruption", ["huge measurement", "NaN control"])
def test_an_imm_isolates_its_trajectories_too(corruption: str) -> None:
    _check_isolated(_filter("IMM(KF, UKF)", F64), F64, corruption)


def test_the_corrupted_trajectorys_values_are_kept_and_pass_no_gradient() -> None:
    filt = _filter("KalmanFilter", F64)
    z, u, m0, p0 = _data(F64, "NaN control")
    with torch.no_grad():
        plain = filt(z, m0, p0, controls=u)
    out = filt(z, m0, p0, controls=u)
    torch.testing.assert_close(out.mean, plain.mean, equal_nan=True)
    assert not torch.isfinite(out.log_likelihood[BAD]).all()
    # the whole batch's loss is NaN as it must be, but the clean rows still train
    params = [p for p in filt.parameters() if p.requires_grad]
    finite = torch.isfinite(out.log_likelihood).all(1)
    (g,) = torch.autograd.grad(out.log_likelihood[finite].sum(), params[:1])
    assert torch.isfinite(g).all()


@pytest.mark.slow
@pytest.mark.skipif(compiler_available() is not None, reason="no C++ compiler")
@pytest.mark.parametrize("corruption", ["huge measurement", "NaN control"])
def test_the_compiled_engine_isolates_trajectories(corruption: str) -> None:
    _check_isolated(FusedFilter(SquareRootUKF(_model(F64)), engine="generated"), F64, corruption)


def test_a_field_shared_by_the_batch_is_checked_once_with_the_same_verdict() -> None:
    """A covariance expanded over the batch (stride 0, the shared Kalman path) gives the flags that
    its materialised copy gives: all trajectories when it holds a NaN, none otherwise."""
    from difffilter.filters import FilterResult
    from difffilter.filters.isolation import nonfinite_trajectories

    bsz, steps = 5, 3
    mean = torch.zeros(bsz, steps, 2, dtype=F64)
    mean[3, 1, 0] = float("inf")
    for bad_cov in (False, True):
        common = torch.eye(2, dtype=F64).repeat(steps, 1, 1)
        if bad_cov:
            common[2, 0, 1] = float("nan")
        cov = common.expand(bsz, steps, 2, 2)
        assert cov.stride(0) == 0
        zeros = torch.zeros(bsz, steps, dtype=F64)
        fields = {"prior_mean": mean, "log_likelihood": zeros, "nis": zeros, "num_observed": zeros, "final_belief": {}}
        shared = FilterResult(mean=mean, cov=cov, prior_cov=cov, **fields)
        copied = FilterResult(mean=mean, cov=cov.clone(), prior_cov=cov.clone(), **fields)
        expected = [True] * bsz if bad_cov else [False, False, False, True, False]
        assert nonfinite_trajectories(shared).tolist() == nonfinite_trajectories(copied).tolist() == expected
