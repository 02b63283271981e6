"""Issue 17, defect 3: constrained values are valid for ANY raw value in [-50, 50].

Measured before: ``PositiveDefinite`` (full) factorised for 37-45 % of raw draws (condition
numbers up to 1e304), float32 diagonal with floor 0 failed 18-29 %, ``Bounded(-1, 1)`` returned
exactly +-1 (``ColoredNoiseUKF`` then ran with psi = 1), float32 ``Interval(0.1, 1e4)`` refused
its own upper bound with a message about "Bounded" and log-space numbers.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from difffilter.filters import ColoredNoiseUKF
from difffilter.models import LinearModel
from difffilter.params import Bounded, Interval, PositiveDefinite, register_constrained, register_covariance

from .filter_contract import cv_matrices, make_data

RAW = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False)
DTYPES = [torch.float32, torch.float64]


@settings(max_examples=150, deadline=None)
@given(st.integers(2, 8), st.lists(RAW, min_size=64, max_size=64), st.sampled_from(DTYPES), st.booleans(), st.sampled_from([0.0, 1e-3]))
def test_positive_definite_factorises_for_any_raw(n, vals, dtype, diagonal, floor):
    raw = torch.tensor(vals[: n if diagonal else n * n], dtype=dtype).reshape((n,) if diagonal else (n, n)).requires_grad_(True)
    value = PositiveDefinite(diagonal=diagonal, floor=floor)(raw)
    assert torch.isfinite(value).all()
    chol, info = torch.linalg.cholesky_ex(value)
    assert int(info) == 0 and torch.isfinite(chol).all()
    # the correlation matrix's condition number is bounded (in any units)
    d = torch.diagonal(value.double()).sqrt()
    corr = value.detach().double() / (d[:, None] * d[None, :]).detach()
    assert float(torch.linalg.cond(corr)) <= 2 * n / (16 * n * torch.finfo(dtype).eps)  # n (1 + delta) / delta, cond computed to ~1 %
    value.sum().backward()
    assert torch.isfinite(raw.grad).all()


def test_positive_definite_extreme_raw_draws_all_factorise():
    """The issue's experiment, rerun: uniform raw draws in [-50, 50]."""
    g = torch.Generator().manual_seed(0)
    for dtype in DTYPES:
        for n in (3, 6, 12):
            raw = (torch.rand(4000, n, n, generator=g, dtype=torch.float64) * 100 - 50).to(dtype)
            for c, r in ((PositiveDefinite(), raw), (PositiveDefinite(floor=1e-3), raw), (PositiveDefinite(diagonal=True), raw[..., 0])):
                info = torch.linalg.cholesky_ex(c(r))[1]
                assert int((info != 0).sum()) == 0, (dtype, n, c.diagonal)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9), st.floats(1e-3, 1e3), st.sampled_from(DTYPES))
def test_positive_definite_set_then_get_returns_the_value(vals, scale, dtype):
    a = torch.tensor(vals, dtype=torch.float64).reshape(3, 3)
    value = (scale * (a @ a.mT + 0.1 * torch.eye(3, dtype=torch.float64))).to(dtype)
    m = nn.Module()
    register_covariance(m, "R", value, "full")
    tol = 1e-12 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(m.R, value, rtol=tol, atol=tol * float(value.abs().max()))


@settings(max_examples=200, deadline=None)
@given(RAW, st.sampled_from(DTYPES))
def test_bounded_is_strictly_inside(r, dtype):
    raw = torch.tensor(r, dtype=dtype, requires_grad=True)
    for lo, hi in ((-1.0, 1.0), (0.0, 1.0)):
        v = Bounded(lo, hi)(raw)
        assert lo < float(v) < hi
        (g,) = torch.autograd.grad(v, raw)
        assert torch.isfinite(g)


@pytest.mark.parametrize("dtype", DTYPES)
def test_colored_noise_ukf_never_sees_psi_one(dtype):
    mats = {k: v.to(dtype) for k, v in cv_matrices().items()}
    flt = ColoredNoiseUKF(LinearModel(**mats), psi=0.5)
    with torch.no_grad():
        flt.parametrizations.psi.original.fill_(50.0)
    assert bool((flt.psi.abs() < 1).all())
    res = flt(make_data(2, 20, 2, dtype=dtype), torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype))
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.log_likelihood).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_interval_accepts_its_documented_bounds_and_names_the_parameter(dtype):
    m = nn.Module()
    register_constrained(m, "tau", torch.tensor(20.0, dtype=dtype), Interval(0.1, 1e4))
    for bound in (0.1, 1e4):
        m.tau = torch.tensor(bound, dtype=dtype)
        assert abs(float(m.tau) - bound) <= 1e-5 * bound
    m.tau = torch.tensor(20.0, dtype=dtype)
    assert abs(float(m.tau) - 20.0) < 1e-4
    with pytest.raises(ValueError, match=r"tau must lie in \[0\.1, 10000\], got \[?20000") as err:
        m.tau = torch.tensor(2e4, dtype=dtype)
    assert "Bounded" not in str(err.value) and "9.21" not in str(err.value)
    lo7 = nn.Module()
    register_constrained(lo7, "tau", torch.tensor(1.0, dtype=dtype), Interval(0.7, 7.7))
    lo7.tau = torch.tensor(0.7, dtype=dtype)  # float32(0.7) < 0.7: still the documented bound
    lo7.tau = torch.tensor(7.7, dtype=dtype)


@settings(max_examples=100, deadline=None)
@given(RAW, st.sampled_from(DTYPES))
def test_interval_is_within_bounds_for_any_raw(r, dtype):
    v = Interval(0.1, 1e4)(torch.tensor(r, dtype=dtype))
    assert 0.1 <= float(v) <= 1e4 and math.isfinite(float(v))


def test_learned_values_keep_their_meaning():
    """Existing parametrisations: setting a constrained value reads back the same value."""
    m = nn.Module()
    register_constrained(m, "psi", torch.tensor(0.3, dtype=torch.float64), Bounded(-1.0, 1.0))
    register_constrained(m, "rho", torch.tensor(1.0, dtype=torch.float64), Bounded(0.0, 1.0))  # p002's (0, 1]
    assert abs(float(m.psi) - 0.3) < 1e-15
    assert 1.0 - 1e-14 < float(m.rho) < 1.0  # the bound maps to the nearest raw value inside (as before)
    register_covariance(m, "R", torch.diag(torch.tensor([225.0, 4.9e-5, 1.0], dtype=torch.float64)), "full")
    torch.testing.assert_close(torch.diagonal(m.R), torch.tensor([225.0, 4.9e-5, 1.0], dtype=torch.float64), rtol=1e-13, atol=0)
