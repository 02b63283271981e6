"""Batch isolation, the full matrix of issue 27: filters x corruptions x dtypes x engines.

Trajectory 1 of a batch of three is corrupted at one step; the others' values (mean, covariance,
log-likelihood) and gradients (shared parameters, measurements, initial means) must equal a run
of the clean trajectories alone to 1e-12 (in practice bit-identical), and the corrupted one must
be flagged in ``extras["untrusted"]`` -- or, for an input the contract forbids (a NaN measurement
under a True mask, a non-finite initial covariance), the batch is refused with a ``ValueError``
that names trajectory 1 (nothing silent either way).

The compiled-engine cases build one kernel per filter and are marked slow.
"""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.engines.build import compiler_available
from difffilter.filters import EKF, UKF, ColoredNoiseUKF, KalmanFilter, SquareRootUKF
from difffilter.mixers import IMM

from .test_reliability_isolation import _model

F64, F32 = torch.float64, torch.float32
BAD, CLEAN = 1, [0, 2]
FILTERS = ("KalmanFilter", "EKF", "UKF", "SquareRootUKF", "IMM(KF, UKF)", "ColoredNoiseUKF")
FLAGGED = ("huge measurement", "NaN control", "inf control")
REFUSED = ("NaN measurement under a True mask", "inf in P0")


def make_filter(kind: str, dtype: torch.dtype):  # type: ignore[no-untyped-def]
    if kind == "IMM(KF, UKF)":
        pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=dtype)
        return IMM([KalmanFilter(_model(dtype)), UKF(_model(dtype))], pi, torch.tensor([0.5, 0.5], dtype=dtype))
    if kind == "ColoredNoiseUKF":
        return ColoredNoiseUKF(_model(dtype), psi=0.3)
    return {"KalmanFilter": KalmanFilter, "EKF": EKF, "UKF": UKF, "SquareRootUKF": SquareRootUKF}[kind](_model(dtype))


def corrupted_batch(dtype: torch.dtype, corruption: str, batch: int = 3, steps: int = 6) -> dict[str, torch.Tensor]:
    """Measurements, controls, mask, initial means and covariances; trajectory 1 corrupted at step 2."""
    g = torch.Generator().manual_seed(0)
    z = torch.randn(batch, steps, 2, generator=g, dtype=F64).to(dtype)
    u = (0.1 * torch.randn(batch, steps, 2, generator=g, dtype=F64)).to(dtype)
    m0 = (0.1 * torch.randn(batch, 4, generator=g, dtype=F64)).to(dtype)
    p0 = torch.eye(4, dtype=dtype).expand(batch, 4, 4).clone()
    mask = torch.ones(batch, steps, 2, dtype=torch.bool)
    if corruption == "huge measurement":
        z[BAD, 2, 0] = 1e300 if dtype == F64 else 1e30
    elif corruption == "NaN control":
        u[BAD, 2, 1] = float("nan")
    elif corruption == "inf control":
        u[BAD, 2, 0] = float("inf")
    elif corruption == "NaN measurement under a True mask":
        z[BAD, 2, 0] = float("nan")
    elif corruption == "inf in P0":
        p0[BAD, 0, 0] = float("inf")
    else:
        raise ValueError(corruption)
    return {"z": z, "u": u, "m0": m0, "p0": p0, "mask": mask}


def _run(filt, data: dict[str, torch.Tensor], rows: list[int]):  # type: ignore[no-untyped-def]
    """Result and the gradients of the summed log-likelihood of ``rows`` (parameters, z, m0)."""
    z = data["z"].clone().requires_grad_(True)
    m0 = data["m0"].clone().requires_grad_(True)
    out = filt(z, m0, data["p0"], mask=data["mask"], controls=data["u"])
    params = [p for p in filt.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.log_likelihood[rows].sum(), [*params, z, m0])
    return out, [*grads[: len(params)], grads[len(params)][rows], grads[len(params) + 1][rows]]


def check_isolated(filt, dtype: torch.dtype, corruption: str) -> None:  # type: ignore[no-untyped-def]
    data = corrupted_batch(dtype, corruption)
    if corruption in REFUSED:
        with pytest.raises(ValueError, match=r"\[1[\],]"):  # names trajectory 1
            filt(data["z"], data["m0"], data["p0"], mask=data["mask"], controls=data["u"])
        return
    out, grads = _run(filt, data, CLEAN)
    alone, alone_grads = _run(filt, {k: v[CLEAN] for k, v in data.items()}, list(range(len(CLEAN))))
    for name in ("mean", "cov", "log_likelihood"):
        torch.testing.assert_close(getattr(out, name)[CLEAN], getattr(alone, name), rtol=0, atol=1e-12, msg=name)
    for got, want in zip(grads, alone_grads, strict=True):
        assert torch.isfinite(got).all(), "a corrupted trajectory made another's gradient non-finite"
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert bool(out.extras["untrusted"][BAD].any()), "the corrupted trajectory is not flagged"
    assert not bool(out.extras["untrusted"][CLEAN].any())


EAGER = [(k, d, c) for k in FILTERS for d in (F64, F32) for c in FLAGGED + REFUSED]


@pytest.mark.parametrize(("kind", "dtype", "corruption"), EAGER, ids=[f"{k}-{str(d)[6:]}-{c}" for k, d, c in EAGER])
def test_eager_isolation(kind: str, dtype: torch.dtype, corruption: str) -> None:
    check_isolated(make_filter(kind, dtype), dtype, corruption)


COMPILED = [(k, c) for k in FILTERS for c in FLAGGED + REFUSED]


@pytest.mark.slow
@pytest.mark.skipif(compiler_available() is not None, reason="no C++ compiler")
@pytest.mark.parametrize(("kind", "corruption"), COMPILED, ids=[f"{k}-{c}" for k, c in COMPILED])
def test_compiled_isolation(kind: str, corruption: str) -> None:
    fused = FusedFilter(make_filter(kind, F64), engine="generated")
    check_isolated(fused, F64, corruption)
    if corruption not in REFUSED:
        assert fused.last_engine == "generated"
