"""Extreme scales the battery of issue 27 found silent: each case is within tolerance of an
independent reference or flagged in ``extras["untrusted"]``.

* ``ColoredNoiseUKF`` at ``P0 = Q = 1e-30``: the state is deterministic to 1e-15, so the exact
  answer is the noise-free trajectory ``F^t m0`` and the AR(1) density of ``z_t - H x_t`` (closed
  form).  The eager filter was 0.8-1.5 off in the mean (sigma 1e-14) and 0.6-0.9 nats off: its
  cross-covariance came from sigma-point deviations that had lost their digits to the mean, the
  joint of the update turned indefinite and its factor fell back to the identity, unflagged.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.engines.build import compiler_available
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.models import LinearModel

from .filter_contract import cv_matrices, make_data
from .test_colored import beacon_model

F64 = torch.float64
TINY = 1e-30
PSI = np.array([0.7, -0.4])


def _tiny_colored() -> tuple[ColoredNoiseUKF, torch.Tensor, torch.Tensor, torch.Tensor]:
    mats = cv_matrices()
    mats["Q"] = TINY * torch.eye(4, dtype=F64)
    filt = ColoredNoiseUKF(LinearModel(**mats), psi=torch.tensor(PSI))
    m0 = torch.tensor([0.5, 1.0, -1.0, 0.2], dtype=F64)
    return filt, make_data(2, 12, 2, seed=9), m0, TINY * torch.eye(4, dtype=F64)


def deterministic_colored_reference(z: np.ndarray, m0: np.ndarray, F, H, R, psi) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Means ``[T, n]`` and per-step log-likelihoods ``[T]`` of ``z [T, m]`` for a state without
    noise (``x_t = F^t m0`` exactly) and AR(1) measurement noise ``v_t = z_t - H x_t`` with a
    stationary start: ``v_1 ~ N(0, R / (1 - psi psi^T))``, ``v_t - psi v_(t-1) ~ N(0, R)``."""
    xs, lls, x, prev = [], [], m0, None
    for t in range(z.shape[0]):
        x = F @ x
        v = z[t] - H @ x
        cov, e = (R / (1.0 - np.outer(psi, psi)), v) if prev is None else (R, v - psi * prev)
        lls.append(-0.5 * (e @ np.linalg.solve(cov, e) + np.linalg.slogdet(cov)[1] + len(e) * math.log(2 * math.pi)))
        xs.append(x)
        prev = v
    return np.array(xs), np.array(lls)


def _check_tiny(res, z: torch.Tensor, m0: torch.Tensor) -> None:  # type: ignore[no-untyped-def]
    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    for b in range(z.shape[0]):
        ref_x, ref_ll = deterministic_colored_reference(z[b].numpy(), m0.numpy(), mats["F"], mats["H"], mats["R"], PSI)
        sigma = np.sqrt(np.diagonal(res.cov[b].detach().numpy(), axis1=-2, axis2=-1))
        assert sigma.max() < 1e-13  # the filter stays as certain as the model is
        np.testing.assert_allclose(res.mean[b].detach().numpy(), ref_x, rtol=0, atol=1e-14)
        np.testing.assert_allclose(res.log_likelihood[b].detach().numpy(), ref_ll, rtol=0, atol=1e-9)
    assert not bool(res.extras["untrusted"].any())


def test_colored_ukf_at_tiny_prior_and_process_noise_is_exact() -> None:
    filt, z, m0, p0 = _tiny_colored()
    with torch.no_grad():
        _check_tiny(filt(z, m0, p0), z, m0)


@pytest.mark.slow
@pytest.mark.skipif(compiler_available() is not None, reason="no C++ compiler")
def test_the_compiled_colored_ukf_agrees_at_tiny_covariances() -> None:
    filt, z, m0, p0 = _tiny_colored()
    fused = FusedFilter(filt, engine="generated")
    with torch.no_grad():
        res = fused(z, m0, p0)
    assert fused.last_engine == "generated"
    _check_tiny(res, z, m0)


def test_a_nonlinear_colored_ukf_at_tiny_covariances_is_right_or_flagged() -> None:
    """Range measurements of a state known to 1e-15: the sigma-point images of ``h`` lose their
    digits to ``|h|``; a step beyond 1e-2 sigma of the deterministic answer must be flagged."""
    model = beacon_model(q=TINY, r=0.5)
    filt = ColoredNoiseUKF(model, psi=0.6)
    m0 = torch.tensor([5.0, 1.0, 5.0, -0.5], dtype=F64)
    with torch.no_grad():
        x = m0[None]
        truth = []
        for _ in range(10):
            x = model.f(x)
            truth.append(x)
        truth_t = torch.cat(truth)
        z = model.h(truth_t)[None] + 0.5 * make_data(1, 10, 2, seed=4)
        res = filt(z, m0, TINY * torch.eye(4, dtype=F64))
    sigma = res.cov[0].diagonal(dim1=-2, dim2=-1).sqrt()
    wrong = ((res.mean[0] - truth_t).abs() > 1e-2 * sigma + 64 * torch.finfo(F64).eps * truth_t.abs()).any(-1)
    assert not bool((wrong & ~res.extras["untrusted"][0]).any()), (wrong, res.extras["untrusted"][0])
