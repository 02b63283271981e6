"""Sigma-point filters at huge innovations: exact on a linear model, or flagged.

A measurement 1e10 away from the prediction on a linear-Gaussian model used to leave the UKF
family 2e2-1.7e3 m off in float64 (3e10 m in float32) with nothing in ``extras["untrusted"]``,
and ``IMM(KF, UKF)`` 1e8-1e9 m off: the sigma points ``x +- gamma L_i`` of a mean near 1e10
keep only ``eps |x| / sigma`` of their deviations, and the gain's error is then multiplied by
the innovation.  Reference: the closed-form Kalman filter (numpy, float64) on the same
(dtype-rounded) inputs.  A step counts as right when every mean component is within
``64 eps max_i |x_i| + 1e-2 sigma`` of the reference (the rounding of a state of that size;
the Kalman filter itself stays below 2 % of it); otherwise it must be flagged, at that
step or before.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.filters import UKF, KalmanFilter, SimplifiedUKF, SquareRootUKF
from difffilter.mixers import IMM
from difffilter.models import FunctionalModel, LinearModel

from .filter_contract import cv_matrices, numpy_kalman

F64, F32 = torch.float64, torch.float32
STEPS, OUTLIER = 10, 4


def _data(dtype: torch.dtype) -> torch.Tensor:
    z = torch.randn(2, STEPS, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    z[0, OUTLIER, 0] = 1e10
    return z.to(dtype)


def _reference(z: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    fhqr = (mats["F"], mats["H"], mats["Q"], mats["R"])
    runs = [numpy_kalman(z[b].double().numpy(), np.zeros(4), np.eye(4), *fhqr) for b in range(z.shape[0])]
    return tuple(np.stack([r[i] for r in runs]) for i in range(3))  # type: ignore[return-value]


def _build(name: str, dtype: torch.dtype):  # type: ignore[no-untyped-def]
    mats = {k: v.to(dtype) for k, v in cv_matrices().items()}
    model = lambda: LinearModel(**mats)  # noqa: E731
    return {
        "UKF": lambda: UKF(model()),
        "SquareRootUKF": lambda: SquareRootUKF(model()),
        "SimplifiedUKF": lambda: SimplifiedUKF(model()),
        "IMM(KF, UKF)": lambda: IMM(
            [KalmanFilter(model()), UKF(model())],
            torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=dtype),
            torch.tensor([0.5, 0.5], dtype=dtype),
        ),
    }[name]()


def _wrong_steps(res, z: torch.Tensor) -> np.ndarray:  # type: ignore[no-untyped-def]
    """``[B, T]`` steps whose mean is beyond tolerance of the closed-form KF."""
    ref_mean, ref_cov, _ = _reference(z)
    eps = torch.finfo(z.dtype).eps
    sigma = np.sqrt(np.diagonal(ref_cov, axis1=-2, axis2=-1))
    err = np.abs(res.mean.detach().double().numpy() - ref_mean)
    scale = np.abs(ref_mean).max(-1, keepdims=True)  # the step's magnitude sets its rounding
    return (err > 64 * eps * scale + 1e-2 * sigma).any(-1)


@pytest.mark.parametrize("dtype", [F64, F32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", ["UKF", "SquareRootUKF", "SimplifiedUKF"])
def test_the_ukf_family_is_exact_after_a_1e10_outlier_on_a_linear_model(name: str, dtype: torch.dtype) -> None:
    z = _data(dtype)
    with torch.no_grad():
        res = _build(name, dtype)(z, torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))
    wrong = _wrong_steps(res, z)
    assert not wrong.any(), f"steps off the closed-form KF: {np.argwhere(wrong).tolist()}"
    _, _, ref_ll = _reference(z)
    ll = res.log_likelihood.double().numpy()
    assert np.allclose(ll, ref_ll, rtol=64 * torch.finfo(dtype).eps, atol=1e-3 if dtype == F64 else 5e-2)


@pytest.mark.parametrize("dtype", [F64, F32], ids=["float64", "float32"])
def test_an_imm_after_a_1e10_outlier_is_exact_or_flagged(dtype: torch.dtype) -> None:
    z = _data(dtype)
    with torch.no_grad():
        res = _build("IMM(KF, UKF)", dtype)(z, torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))
    wrong = _wrong_steps(res, z)
    flagged = res.extras["untrusted"].cumsum(1).numpy() > 0
    assert not (wrong & ~flagged).any(), f"silent wrong steps: {np.argwhere(wrong & ~flagged).tolist()}"
    assert bool(res.extras["untrusted"][0, OUTLIER])  # the mode probabilities at 5e19 nats are rounding noise
    assert not bool(res.extras["untrusted"][1].any())  # the clean trajectory is untouched


def _opaque_model(dtype: torch.dtype) -> FunctionalModel:
    """The linear model given as functions without ``matrix()``: the UKF cannot know it is
    linear, so it must flag what it cannot resolve."""
    m = {k: v.to(dtype) for k, v in cv_matrices().items()}
    return FunctionalModel(f=lambda x: x @ m["F"].mT, h=lambda x: x @ m["H"].mT, Q=m["Q"], R=m["R"])


@pytest.mark.parametrize("dtype", [F64, F32], ids=["float64", "float32"])
@pytest.mark.parametrize("cls", [UKF, SquareRootUKF])
def test_a_nonlinear_update_at_a_huge_offset_is_flagged_where_it_is_off(cls, dtype: torch.dtype) -> None:  # type: ignore[no-untyped-def]
    z = _data(dtype)
    with torch.no_grad():
        res = cls(_opaque_model(dtype))(z, torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))
    wrong = _wrong_steps(res, z)
    flagged = res.extras["untrusted"].numpy()
    assert not (wrong & ~flagged).any(), f"silent wrong steps: {np.argwhere(wrong & ~flagged).tolist()}"
    assert not flagged[:, :OUTLIER].any() and not flagged[1].any()  # ordinary steps stay unflagged
