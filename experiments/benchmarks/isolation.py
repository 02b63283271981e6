"""Batch-isolation cases of issue 27: filters x corruptions, shared by the tests and the battery.

Trajectory 1 of a batch of three is corrupted at one step.  The other trajectories' values (mean,
covariance, log-likelihood) and gradients (shared parameters, measurements, initial means) must
equal a run of the clean trajectories alone to 1e-12, and the corrupted one must be flagged in
``extras["untrusted"]``; an input the filter contract forbids (a NaN measurement under a True
mask, a non-finite initial covariance) must instead be refused with a ``ValueError`` naming
trajectory 1.  :func:`check_isolated` raises ``AssertionError`` on any violation, so
``tests/test_reliability_isolation_matrix.py`` and ``experiments/reliability_battery.py`` run the
same cases.
"""

from __future__ import annotations

import re
from typing import Any

import torch

from difffilter.filters import EKF, UKF, ColoredNoiseUKF, KalmanFilter, SquareRootUKF
from difffilter.mixers import IMM
from difffilter.models import LinearModel

__all__ = [
    "BAD",
    "CLEAN",
    "COMPILED",
    "EAGER",
    "FILTERS",
    "FLAGGED",
    "REFUSED",
    "check_isolated",
    "corrupted_batch",
    "isolation_model",
    "make_filter",
]

F64, F32 = torch.float64, torch.float32
BAD, CLEAN = 1, [0, 2]
FILTERS = ("KalmanFilter", "EKF", "UKF", "SquareRootUKF", "IMM(KF, UKF)", "ColoredNoiseUKF")
FLAGGED = ("huge measurement", "NaN control", "inf control")
REFUSED = ("NaN measurement under a True mask", "inf in P0")
EAGER = [(k, d, c) for k in FILTERS for d in (F64, F32) for c in FLAGGED + REFUSED]
COMPILED = [(k, c) for k in FILTERS for c in FLAGGED + REFUSED]


def isolation_model(dtype: torch.dtype) -> LinearModel:
    """2-D constant velocity ``[px, vx, py, vy]`` (dt 0.5, q 0.3), both positions measured with
    correlated noise (r 0.8, correlation 0.2), and a control matrix so controls reach the state."""
    dt, q, r = 0.5, 0.3, 0.8
    f1 = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=F64)
    q1 = q * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=F64)
    mats = {
        "F": torch.block_diag(f1, f1),
        "Q": torch.block_diag(q1, q1) + 1e-9 * torch.eye(4, dtype=F64),
        "H": torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=F64),
        "R": r * torch.tensor([[1.0, 0.2], [0.2, 1.0]], dtype=F64),
        "B": torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.5], [0.0, 1.0]], dtype=F64),
    }
    return LinearModel(**{k: v.to(dtype) for k, v in mats.items()})


def make_filter(kind: str, dtype: torch.dtype) -> Any:
    """One of :data:`FILTERS` on :func:`isolation_model`."""
    if kind == "IMM(KF, UKF)":
        pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=dtype)
        return IMM([KalmanFilter(isolation_model(dtype)), UKF(isolation_model(dtype))], pi, torch.tensor([0.5, 0.5], dtype=dtype))
    if kind == "ColoredNoiseUKF":
        return ColoredNoiseUKF(isolation_model(dtype), psi=0.3)
    return {"KalmanFilter": KalmanFilter, "EKF": EKF, "UKF": UKF, "SquareRootUKF": SquareRootUKF}[kind](isolation_model(dtype))


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
        raise ValueError(f"corruption: expected one of {FLAGGED + REFUSED}, got {corruption!r}")
    return {"z": z, "u": u, "m0": m0, "p0": p0, "mask": mask}


def _run(filt: Any, data: dict[str, torch.Tensor], rows: list[int]) -> tuple[Any, list[torch.Tensor]]:
    """Result and the gradients of the summed log-likelihood of ``rows`` (parameters, z, m0)."""
    z = data["z"].clone().requires_grad_(True)
    m0 = data["m0"].clone().requires_grad_(True)
    out = filt(z, m0, data["p0"], mask=data["mask"], controls=data["u"])
    params = [p for p in filt.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out.log_likelihood[rows].sum(), [*params, z, m0])
    return out, [*grads[: len(params)], grads[len(params)][rows], grads[len(params) + 1][rows]]


def check_isolated(filt: Any, dtype: torch.dtype, corruption: str) -> None:
    """Raise ``AssertionError`` unless ``filt`` isolates (or refuses, naming trajectory 1) ``corruption``."""
    data = corrupted_batch(dtype, corruption)
    if corruption in REFUSED:
        try:
            filt(data["z"], data["m0"], data["p0"], mask=data["mask"], controls=data["u"])
        except ValueError as err:
            if not re.search(r"\[1[\],]", str(err)):
                raise AssertionError(f"refused without naming trajectory 1: {err}") from err
            return
        raise AssertionError(f"{corruption}: the batch was not refused")
    out, grads = _run(filt, data, CLEAN)
    alone, alone_grads = _run(filt, {k: v[CLEAN] for k, v in data.items()}, list(range(len(CLEAN))))
    for name in ("mean", "cov", "log_likelihood"):
        torch.testing.assert_close(getattr(out, name)[CLEAN], getattr(alone, name), rtol=0, atol=1e-12, msg=name)
    for got, want in zip(grads, alone_grads, strict=True):
        assert torch.isfinite(got).all(), "a corrupted trajectory made another's gradient non-finite"
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert bool(out.extras["untrusted"][BAD].any()), "the corrupted trajectory is not flagged"
    assert not bool(out.extras["untrusted"][CLEAN].any()), "a clean trajectory is flagged"
