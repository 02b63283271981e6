"""Extreme scales the battery of issue 27 found silent: each case is within tolerance of an
independent reference or flagged in ``extras["untrusted"]``.

* ``ColoredNoiseUKF`` at ``P0 = Q = 1e-30``: the state is deterministic to 1e-15, so the exact
  answer is the noise-free trajectory ``F^t m0`` and the AR(1) density of ``z_t - H x_t`` (closed
  form).  The eager filter was 0.8-1.5 off in the mean (sigma 1e-14) and 0.6-0.9 nats off: its
  cross-covariance came from sigma-point deviations that had lost their digits to the mean, the
  joint of the update turned indefinite and its factor fell back to the identity, unflagged.
* A nearly singular innovation covariance (two sensors of one position, ``R`` tiny against
  ``P``): forming ``S`` perturbs its small eigenvalue by ``eps max S_jj``, so the covariance-form
  filters' log-likelihood was up to 0.19 nats (float32) / 0.03 nats (float64) off the 80-digit
  reference, unflagged.  Each step is now within 1e-2 nats (and the mean within 1e-2 sigma) or
  flagged; the square-root UKF's likelihood stays accurate (its ``S`` comes from a QR of the
  square roots) but its gain does not, and is flagged.
* float32 pseudoranges of an ECEF position (~6e6 m, ranges ~2e7 m): the innovation keeps only
  ``eps |z_hat|`` ~ 2 m, and the clock states were 0.3-0.9 m off a float64 run, unflagged.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.engines.build import compiler_available
from difffilter.filters import EKF, UKF, KalmanFilter, SquareRootUKF
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.models import FunctionalModel, LinearModel
from experiments.benchmarks.exact import exact_kalman, mpmath_available

from .filter_contract import cv_matrices, make_data
from .test_colored import beacon_model

F64, F32 = torch.float64, torch.float32
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


# -- nearly singular innovation covariance ---------------------------------------------------


def twin_sensor_case(dtype: torch.dtype, r: float, seed: int = 0, steps: int = 6) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """1-D constant velocity ``[p, v]``, two sensors of ``p`` with variance ``r`` and one of
    ``v`` with variance 1: ``S`` has eigenvalues ~``2 P_pp`` and ``r``."""
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(steps, 3))
    z[:, 1] = z[:, 0] + math.sqrt(r) * rng.normal(size=steps)
    mats = {
        "F": np.array([[1.0, 1.0], [0.0, 1.0]]),
        "Q": np.array([[1 / 3, 0.5], [0.5, 1.0]]),
        "H": np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        "R": np.diag([r, r, 1.0]),
    }
    return {k: torch.tensor(v, dtype=dtype) for k, v in mats.items()}, torch.tensor(z, dtype=dtype)[None]


TWINS = {"KalmanFilter": KalmanFilter, "EKF": EKF, "UKF": UKF, "SquareRootUKF": SquareRootUKF}
RATIOS = {F64: [1e-10, 1e-13, 1e-14, 1e-15], F32: [1e-4, 1e-5, 1e-6, 1e-7]}


def _twin_errors(filt, mats: dict[str, torch.Tensor], z: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Per step: ``|log-likelihood - 80-digit reference|``, whether the mean is beyond
    ``64 eps max(|x*|, |x-*|) + 1e-2 sigma*`` of the reference's (``x-*`` its prediction), and
    the flags."""
    m0, p0 = torch.zeros(2, dtype=z.dtype), torch.eye(2, dtype=z.dtype)
    with torch.no_grad():
        res = filt(z, m0, p0)
    f64 = {k: v.double().numpy() for k, v in mats.items()}
    mean, cov, ll = exact_kalman(f64["F"], f64["H"], f64["Q"], f64["R"], np.zeros(2), np.eye(2), z[0].double().numpy())
    prior = np.concatenate([np.zeros((1, 2)), mean[:-1]]) @ f64["F"].T
    size = np.maximum(np.abs(mean), np.abs(prior))
    tol = 64 * torch.finfo(z.dtype).eps * size + 1e-2 * np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
    bad_mean = (np.abs(res.mean[0].double().numpy() - mean) > tol).any(-1)
    return np.abs(res.log_likelihood[0].double().numpy() - ll), bad_mean, res.extras["untrusted"][0].numpy()


@pytest.mark.skipif(mpmath_available() is not None, reason="mpmath is not installed")
@pytest.mark.parametrize("dtype", [F64, F32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", list(TWINS))
def test_a_nearly_singular_innovation_covariance_gives_accurate_or_flagged_results(name: str, dtype: torch.dtype) -> None:
    needed = False
    for r in RATIOS[dtype]:
        mats, z = twin_sensor_case(dtype, r)
        err, bad_mean, flagged = _twin_errors(TWINS[name](LinearModel(**mats)), mats, z)
        assert not (((err > 1e-2) | bad_mean) & ~flagged).any(), f"r = {r}: silent errors, log-likelihood {err[~flagged]}"
        if r == RATIOS[dtype][0]:
            assert not flagged.any()  # a well-resolved case stays unflagged
        needed = needed or bool((err > 1e-2).any() or bad_mean.any())
    if dtype == F32:
        assert needed  # the flags are needed: some of these cases are beyond tolerance


def test_the_square_root_ukf_keeps_the_likelihood_where_its_gain_is_flagged() -> None:
    """The square-root form's ``S`` comes from a QR of the square roots, so its log-likelihood
    stays within 1e-2 nats at ``cond(S) ~ 1e7`` in float32; its gain (``P_xz`` and ``S``
    rounded apart) does not, and is flagged."""
    mats, z = twin_sensor_case(F32, 1e-7)
    err, bad_mean, flagged = _twin_errors(SquareRootUKF(LinearModel(**mats)), mats, z)
    assert err.max() < 1e-2 and not (bad_mean & ~flagged).any()
    assert _twin_errors(KalmanFilter(LinearModel(**mats)), mats, z)[0].max() > 1e-2


@pytest.mark.slow
@pytest.mark.skipif(compiler_available() is not None, reason="no C++ compiler")
def test_the_compiled_engine_flags_a_nearly_singular_innovation_covariance_alike() -> None:
    mats, z = twin_sensor_case(F32, 1e-6)
    filt = KalmanFilter(LinearModel(**mats))
    m0, p0 = torch.zeros(2, dtype=F32), torch.eye(2, dtype=F32)
    fused = FusedFilter(filt, engine="generated")
    with torch.no_grad():
        got, ref = fused(z, m0, p0), filt(z, m0, p0)
    assert fused.last_engine == "generated"
    assert torch.equal(got.extras["untrusted"], ref.extras["untrusted"]) and bool(ref.extras["untrusted"].any())


# -- float32 at ECEF scale -------------------------------------------------------------------


def ecef_pseudorange_case(dtype: torch.dtype, steps: int = 8, seed: int = 0):  # type: ignore[no-untyped-def]
    """A receiver at ~6.3e6 m from the earth's centre, 8 satellites 2e7 m away, state
    ``[x, y, z, clock bias, clock drift]`` (m, m/s), pseudoranges with sigma 5 m."""
    rng = np.random.default_rng(seed)
    pos = np.array([4.0e6, 3.0e5, 4.9e6])
    dirs = rng.normal(size=(8, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[:, 2] = np.abs(dirs[:, 2])
    sats_np = pos + 2.0e7 * dirs
    sats = torch.tensor(sats_np, dtype=dtype)

    def f(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x[..., :3], (x[..., 3] + x[..., 4])[..., None], x[..., 4:5]], -1)

    def h(x: torch.Tensor) -> torch.Tensor:
        return (sats - x[..., None, :3]).norm(dim=-1) + x[..., 3:4]

    q = torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.1, 0.01], dtype=F64)).to(dtype)
    model = FunctionalModel(f=f, h=h, Q=q, R=25.0 * torch.eye(8, dtype=dtype))
    bias = 100.0 + 0.5 * np.arange(1, steps + 1)
    z = np.stack([np.linalg.norm(sats_np - pos, axis=1) + bias[t] + 5 * rng.normal(size=8) for t in range(steps)])
    m0 = np.concatenate([pos + 10 * rng.normal(size=3), [100.0, 0.5]])
    p0 = torch.diag(torch.tensor([100.0, 100.0, 100.0, 100.0, 1.0], dtype=dtype))
    return model, torch.tensor(z, dtype=dtype)[None], torch.tensor(m0, dtype=dtype), p0


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_float32_at_ecef_scale_is_flagged_where_it_is_off(cls) -> None:  # type: ignore[no-untyped-def]
    model32, z, m0, p0 = ecef_pseudorange_case(F32)
    model64 = ecef_pseudorange_case(F64)[0]
    with torch.no_grad():
        r32 = cls(model32)(z, m0, p0)
        r64 = cls(model64)(z.double(), m0.double(), p0.double())  # the same rounded inputs
    sigma = r64.cov[0].diagonal(dim1=-2, dim2=-1).sqrt()
    err = (r32.mean[0].double() - r64.mean[0]).abs()
    wrong = (err > 64 * torch.finfo(F32).eps * r64.mean[0].abs() + 1e-2 * sigma).any(-1)
    assert bool(wrong.any()) and float(err[:, 3].max()) > 0.2  # the clock states are off
    assert not bool((wrong & ~r32.extras["untrusted"][0]).any())
    assert not bool(r64.extras["untrusted"].any())  # float64 resolves the same case
