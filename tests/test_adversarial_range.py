"""Issue 17, defect 1: every filter stays exact over the prior's whole dynamic range.

Reference: :mod:`experiments.benchmarks.exact`, plain textbook recursions in mpmath at 80 digits on
the same (dtype-rounded) inputs.  Model: 2-D constant velocity, ``q = 1``, both positions
measured with ``R = 1e-8 I`` (``sigma_z = 1e-4``), prior ``N(0, s I)``; the issue measured
mean errors of 1e-5 to 1e-1 and log-likelihood errors of ~20 nats at ``s = 1e12 .. 1e24``.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.filters import EKF, RCUKF, UKF, ColoredNoiseUKF, KalmanFilter, SimplifiedUKF, SquareRootUKF
from difffilter.filters.diffuse import split_prior
from difffilter.mixers import IMM, Blend
from difffilter.models import LinearModel
from experiments.benchmarks.exact import (
    cv_scenario,
    exact_colored_posteriors,
    exact_fading_kalman,
    exact_imm,
    exact_kalman,
    relative_errors,
    simulate_linear,
)

pytest.importorskip("mpmath")

STEPS = 10
PI = np.array([[0.95, 0.05], [0.1, 0.9]])


def cv_model(q: float = 1.0, r: float = 1e-8) -> dict[str, np.ndarray]:
    return cv_scenario(q, r)


def simulate(mats: dict[str, np.ndarray], steps: int = STEPS, seed: int = 0) -> np.ndarray:
    return simulate_linear(mats, steps, seed)


def build(name: str, mats: dict[str, torch.Tensor]):  # type: ignore[no-untyped-def]
    model = LinearModel(**mats)
    dtype = mats["F"].dtype
    return {
        "kf": lambda: KalmanFilter(model),
        "kf_nojoseph": lambda: KalmanFilter(model, joseph=False),
        "ekf": lambda: EKF(model),
        "ukf": lambda: UKF(model),
        "ukf_reuse_augmented": lambda: UKF(model, noise="augmented", redraw_after_predict=False),
        "sukf": lambda: SimplifiedUKF(model),
        "srukf": lambda: SquareRootUKF(model),
        "rcukf": lambda: RCUKF(model, rho=0.95),
        "colored": lambda: ColoredNoiseUKF(model, psi=0.5),
        "imm": lambda: IMM(
            [KalmanFilter(model), UKF(LinearModel(**{**mats, "Q": 10.0 * mats["Q"]}))],
            transition=torch.tensor(PI, dtype=dtype),
            initial_probs=torch.tensor([0.5, 0.5], dtype=dtype),
        ),
        "blend": lambda: Blend(EKF(model), UKF(LinearModel(**mats)), delta=0.85),
    }[name]()


@functools.cache
def case(scale: float, dtype_name: str, q: float = 1.0, r: float = 1e-8) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    dtype = getattr(torch, dtype_name)
    mats64 = cv_model(q, r)
    mats = {k: torch.tensor(v, dtype=dtype) for k, v in mats64.items()}
    z = torch.tensor(simulate(mats64), dtype=dtype)[None]
    return mats, z, torch.tensor(scale * np.eye(4), dtype=dtype)


@functools.cache
def reference(name: str, scale: float, dtype_name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mats, z, p0 = case(scale, dtype_name)
    m = {k: v.double().numpy() for k, v in mats.items()}
    args = (m["F"], m["H"], m["Q"], m["R"])
    zz, pp = z[0].double().numpy(), p0.double().numpy()
    if name == "rcukf":
        return exact_fading_kalman(*args, np.zeros(4), pp, zz, rho=0.95)
    if name == "colored":
        return exact_colored_posteriors(*args, np.full(2, 0.5), np.zeros(4), pp, zz)
    if name == "imm":
        return exact_imm([args, (m["F"], m["H"], 10.0 * m["Q"], m["R"])], PI, np.array([0.5, 0.5]), np.zeros(4), pp, zz)[:3]
    return exact_kalman(*args, np.zeros(4), pp, zz)


def errors(name: str, scale: float, dtype_name: str, flt=None):  # type: ignore[no-untyped-def]
    mats, z, p0 = case(scale, dtype_name)
    flt = build(name, mats) if flt is None else flt
    res = flt(z, torch.zeros(4, dtype=z.dtype), p0)
    ref = reference(name, scale, dtype_name)
    out = relative_errors(*(t[0].detach().double().numpy() for t in (res.mean, res.cov, res.log_likelihood)), *ref)
    return out, res


ALL = ["kf", "kf_nojoseph", "ekf", "ukf", "ukf_reuse_augmented", "sukf", "srukf", "rcukf", "colored", "imm", "blend"]


@pytest.mark.parametrize("name", ALL)
def test_float64_within_1e6_of_80_digit_reference_at_1e24(name):
    out, res = errors(name, 1e24, "float64")
    assert out["mean"] < 1e-6, out
    assert out["cov"] < 1e-6, out
    assert out["loglik"] < 1e-6, out
    assert not bool(res.untrusted.any())


@pytest.mark.parametrize("name", ["kf", "ukf", "srukf", "imm"])
@pytest.mark.parametrize("scale", [1e8, 1e12, 1e16])
def test_float64_exact_over_the_range(name, scale):
    out, _ = errors(name, scale, "float64")
    assert max(out["mean"], out["cov"], out["loglik"]) < 1e-6, out


@pytest.mark.parametrize("name", ALL)
def test_float32_finite_and_within_1e2_at_1e24(name):
    out, res = errors(name, 1e24, "float32")
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.cov).all() and torch.isfinite(res.log_likelihood).all()
    assert max(out["mean"], out["cov"], out["loglik"]) < 1e-2, out


def test_without_the_split_the_failure_is_reproduced_and_flagged():
    """The reference can fail: the plain covariance form (diffuse_prior=False) is off by the
    issue's orders of magnitude, and in float32 it says so in ``untrusted``."""
    mats, _, _ = case(1e24, "float64")
    flt = UKF(LinearModel(**mats))
    flt.diffuse_prior = False
    out, _ = errors("ukf", 1e24, "float64", flt)
    assert out["loglik_abs"] > 1.0 and out["mean_abs"] > 1e-3
    mats32, _, _ = case(1e24, "float32")
    for cls in (KalmanFilter, UKF):
        flt = cls(LinearModel(**mats32))
        flt.diffuse_prior = False
        _, res = errors("kf", 1e24, "float32", flt)
        assert bool(res.untrusted.any())


def test_no_silent_nan_float32_imm_outlier():
    """A 1e10 outlier in float32 (the issue's IMM NaN): wherever an output is not finite, the
    step or an earlier one is flagged."""
    mats64 = cv_model(q=100.0, r=100.0)
    mats = {k: torch.tensor(v, dtype=torch.float32) for k, v in mats64.items()}
    z = torch.tensor(simulate(mats64, 12), dtype=torch.float32)[None]
    z[0, 5] += 1e10
    imm = build("imm", mats)
    res = imm(z, torch.zeros(4), torch.eye(4))
    bad = ~(torch.isfinite(res.mean).all(-1) & torch.isfinite(res.cov).flatten(-2).all(-1) & torch.isfinite(res.log_likelihood))
    flagged = res.untrusted.cumsum(1) > 0
    assert bool((~bad | flagged).all())
    assert bool(res.untrusted[0, 5:].any())


def test_mixed_batch_equals_separate_runs():
    """One diffuse trajectory next to ordinary ones changes nothing for the others (they pass
    through the exact update's ordinary branch, which equals the Joseph form)."""
    mats, z, _ = case(1e24, "float64")
    flt = KalmanFilter(LinearModel(**mats))
    z3 = torch.cat([z, z + 1.0, z - 2.0])
    p0 = torch.stack([1e24 * torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64), 4.0 * torch.eye(4, dtype=torch.float64)])
    full = flt(z3, torch.zeros(4, dtype=torch.float64), p0)
    for b in range(3):
        one = flt(z3[b : b + 1], torch.zeros(4, dtype=torch.float64), p0[b : b + 1])
        torch.testing.assert_close(full.mean[b], one.mean[0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(full.log_likelihood[b], one.log_likelihood[0], rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(full.cov[b], one.cov[0], rtol=1e-10, atol=1e-18)


def test_ordinary_prior_is_not_split_and_diffuse_part_resolves():
    mats, z, p0 = case(1e24, "float64")
    flt = KalmanFilter(LinearModel(**mats))
    rows = flt.sensitivity(torch.zeros(1, 4, dtype=torch.float64), None)
    assert split_prior(1e-2 * torch.eye(4, dtype=torch.float64)[None], rows) is None  # 1e-2 * 9 / 1e-8 < 6.7e7
    assert split_prior(torch.eye(4, dtype=torch.float64)[None], rows) is not None
    belief = flt.initial_belief(torch.zeros(4, dtype=torch.float64), p0)
    assert "diffuse_cov" in belief and float(belief["diffuse_scale"]) == 1e24
    res = flt(z, torch.zeros(4, dtype=torch.float64), p0)
    assert "diffuse_cov" not in res.final_belief  # position and velocity resolved after two fixes


def test_gradients_through_the_diffuse_phase_match_finite_differences():
    mats, z, p0 = case(1e24, "float64")
    flt = UKF(LinearModel(**mats))
    raw = flt.model.measurement.parametrizations.R.original
    names = ["model.measurement.parametrizations.R.original"]

    def fn(r):
        return torch.func.functional_call(flt, {names[0]: r}, (z[:, :4], torch.zeros(4, dtype=torch.float64), p0)).log_likelihood.sum()

    assert torch.autograd.gradcheck(fn, (raw.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-4, rtol=1e-5)


def test_fused_filter_runs_the_diffuse_phase_exactly():
    mats, z, p0 = case(1e24, "float64")
    fused = FusedFilter(KalmanFilter(LinearModel(**mats)), compile=False)
    out, res = errors("kf", 1e24, "float64", fused)
    assert max(out["mean"], out["cov"], out["loglik"]) < 1e-6, out
    assert res.mean.shape == (1, STEPS, 4)
