"""Constrained parameters: round trips, validity for any raw value, finite gradients."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from difffilter.params import (
    Bounded,
    Interval,
    Positive,
    PositiveDefinite,
    RowStochastic,
    ScaledMatrix,
    check_covariance,
    constrained_values,
    register_constrained,
    register_covariance,
)

RAW = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False)
DTYPES = [torch.float32, torch.float64]


def _raw_tensor(draw_list, shape, dtype):
    return torch.tensor(draw_list, dtype=dtype).reshape(shape)


@settings(max_examples=60, deadline=None)
@given(st.lists(RAW, min_size=9, max_size=9), st.sampled_from(DTYPES), st.booleans())
def test_positive_definite_any_raw_is_valid_with_finite_gradients(vals, dtype, diagonal):
    raw = _raw_tensor(vals[:3] if diagonal else vals, (3,) if diagonal else (3, 3), dtype).requires_grad_(True)
    value = PositiveDefinite(diagonal=diagonal)(raw)
    assert torch.isfinite(value).all()
    assert torch.allclose(value, value.mT)
    # L L^T is PSD exactly; the product itself carries rounding of order eps * |value|
    eps = torch.finfo(dtype).eps
    assert bool((torch.linalg.eigvalsh(value.double()) >= -10 * eps * float(value.abs().max())).all())
    value.sum().backward()
    assert torch.isfinite(raw.grad).all()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9), st.floats(0.01, 100.0))
def test_positive_definite_round_trip_float64(vals, scale):
    a = torch.tensor(vals, dtype=torch.float64).reshape(3, 3)
    value = scale * (a @ a.mT + 0.1 * torch.eye(3, dtype=torch.float64))
    c = PositiveDefinite()
    back = c(c.right_inverse(value))
    assert torch.allclose(back, value, rtol=1e-12, atol=1e-12 * scale)
    d = torch.diag(torch.diagonal(value))
    cd = PositiveDefinite(diagonal=True)
    assert torch.allclose(cd(cd.right_inverse(d)), d, rtol=1e-12, atol=0)


@settings(max_examples=60, deadline=None)
@given(st.lists(RAW, min_size=4, max_size=4), st.sampled_from(DTYPES), st.floats(0.0, 0.05))
def test_row_stochastic_rows_sum_to_one_and_respect_floor(vals, dtype, floor):
    raw = torch.tensor(vals, dtype=dtype).reshape(2, 2).requires_grad_(True)
    c = RowStochastic(floor)
    value = c(raw)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(value.sum(-1), torch.ones(2, dtype=dtype), atol=tol)
    assert bool((value >= floor - tol).all())
    logv = c.log_value(raw)
    assert torch.isfinite(logv).all()
    assert torch.allclose(logv.exp(), value, rtol=1e-5, atol=0)
    (value[0, 0] + logv[1, 1]).backward()
    assert torch.isfinite(raw.grad).all()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.02, 1.0), min_size=3, max_size=3))
def test_row_stochastic_round_trip_float64(vals):
    p = torch.tensor(vals, dtype=torch.float64)
    p = p / p.sum()
    c = RowStochastic(1e-3)
    p = c(c.right_inverse(p.clamp_min(1e-3) / p.clamp_min(1e-3).sum()))  # a valid point
    assert torch.allclose(c(c.right_inverse(p)), p, rtol=0, atol=1e-12)


@settings(max_examples=80, deadline=None)
@given(RAW, st.sampled_from(DTYPES))
def test_scalar_constraints_valid_for_any_raw(r, dtype):
    raw = torch.tensor(r, dtype=dtype, requires_grad=True)
    for c, lo, hi in [
        (Positive(1e-3), 1e-3, math.inf),
        (Bounded(-1.0, 1.0), -1.0, 1.0),
        (Interval(0.1, 1e4), 0.1, 1e4),
        (Interval(0.0, 2.0, log_scale=False), 0.0, 2.0),
    ]:
        v = c(raw)
        assert torch.isfinite(v) and lo <= float(v) <= hi
        (g,) = torch.autograd.grad(v, raw)
        assert torch.isfinite(g)


@settings(max_examples=80, deadline=None)
@given(st.floats(0.0, 1.0))
def test_scalar_round_trips_float64(u):
    for c, value in [
        (Positive(0.5), 0.5 + 10 * u + 1e-3),
        (Bounded(-1.0, 1.0), -0.999 + 1.998 * u),
        (Interval(0.1, 1e4), 0.1 * (1e5 ** (0.001 + 0.998 * u))),
    ]:
        x = torch.tensor(value, dtype=torch.float64)
        assert abs(float(c(c.right_inverse(x))) - value) <= 1e-12 * max(1.0, abs(value))


def test_register_and_set_constrained_value():
    m = nn.Module()
    register_constrained(m, "tau", torch.tensor(100.0, dtype=torch.float64), Interval(0.1, 1e4))
    assert abs(float(m.tau) - 100.0) < 1e-9
    m.tau = torch.tensor(20.0, dtype=torch.float64)
    assert abs(float(m.tau) - 20.0) < 1e-9
    assert "tau" in constrained_values(m)
    with pytest.raises(ValueError):
        m.tau = torch.tensor(1e5, dtype=torch.float64)


def test_covariance_structures_and_validation():
    m = nn.Module()
    base = torch.diag(torch.tensor([1.0, 4.0], dtype=torch.float64))
    register_covariance(m, "R", base, "scalar")
    assert torch.allclose(m.R, base)
    m.R = 3 * base
    assert torch.allclose(m.R, 3 * base)
    assert isinstance(m.parametrizations.R[0], ScaledMatrix)
    register_covariance(m, "Q", base, "diagonal")
    assert m.parametrizations.Q.original.shape == (2,)
    register_covariance(m, "P", base, "fixed")
    assert not any(n.endswith("P") for n, _ in m.named_parameters())
    with pytest.raises(ValueError, match="Q"):
        register_covariance(m, "Q", torch.tensor([[1.0, 2.0], [0.0, 1.0]]), "diagonal")
    for bad, msg in [
        (torch.ones(2, 3), "square"),
        (torch.tensor([[1.0, 2.0], [2.0, 1.0]]), "positive definite"),
        (torch.tensor([[1.0, 0.5], [0.0, 1.0]]), "symmetric"),
        (torch.tensor([[float("nan"), 0.0], [0.0, 1.0]]), "non-finite"),
    ]:
        with pytest.raises(ValueError, match=msg):
            check_covariance("R", bad)
    with pytest.raises(ValueError, match=r"R must have shape \[3, 3\]"):
        check_covariance("R", torch.eye(2), 3)


def test_reregistering_on_a_deep_copy_leaves_the_original_working() -> None:
    """copy.deepcopy shares a parametrized module's generated class; re-registering the copy's
    only parametrization must not delete the property the original reads through."""
    import copy

    from torch import nn

    from difffilter.params import Positive, ScaledMatrix, register_constrained

    m = nn.Module()
    register_constrained(m, "q", 2.0 * torch.eye(3, dtype=torch.float64), ScaledMatrix(torch.eye(3, dtype=torch.float64)))
    c = copy.deepcopy(m)
    assert type(c) is type(m)
    register_constrained(c, "q", torch.tensor(5.0, dtype=torch.float64), Positive())
    assert torch.allclose(m.q, 2.0 * torch.eye(3, dtype=torch.float64))
    assert float(c.q) == pytest.approx(5.0) and c.parametrizations.q.original.requires_grad
    assert [n for n, _ in c.named_parameters()] == ["parametrizations.q.original"]
    # a fixed buffer replaces the parametrization (the copy's own class is restored)
    register_constrained(c, "q", torch.tensor(1.0, dtype=torch.float64), None)
    assert float(c.q) == 1.0 and torch.allclose(m.q, 2.0 * torch.eye(3, dtype=torch.float64))


def test_switching_the_soft_gate_off_on_a_copy_keeps_the_original_soft_gate() -> None:
    import copy

    from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement

    layout = GnssStateLayout.odometry(isb=True)
    meas = PseudorangeMeasurement(num_satellites=4, layout=layout, noise_from_data=True, robust="reject", gate_softness=0.2)
    twin = copy.deepcopy(meas)
    twin.set_gate_softness(None)
    assert twin.soft_gate is False and not hasattr(twin, "gate_softness")
    assert float(meas.gate_softness) == pytest.approx(0.2)


def test_registering_on_a_deep_copy_adds_nothing_to_the_original() -> None:
    import copy

    from torch import nn

    from difffilter.params import Positive, register_constrained

    m = nn.Module()
    register_constrained(m, "a", torch.tensor(1.0, dtype=torch.float64), Positive())
    c = copy.deepcopy(m)
    register_constrained(c, "b", torch.tensor(2.0, dtype=torch.float64), Positive())
    assert float(c.b) == pytest.approx(2.0) and float(c.a) == pytest.approx(1.0)
    assert not hasattr(m, "b") and float(m.a) == pytest.approx(1.0)


def test_remove_constrained_leaves_no_attribute() -> None:
    from torch import nn

    from difffilter.params import Positive, register_constrained, remove_constrained

    m = nn.Module()
    register_constrained(m, "a", torch.tensor(1.0, dtype=torch.float64), Positive())
    remove_constrained(m, "a")
    assert not hasattr(m, "a") and list(m.parameters()) == []
    remove_constrained(m, "a")  # nothing to remove: no error
