"""Heteroscedastic noise models (difffilter.models.heteroscedastic): closed-form values, bounds,
monotonicity, gradients against central differences, maximum-likelihood recovery of a known
variance law, the robust gate, and a filter with side-information noise against a hand-written
Kalman filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from difffilter.filters import EKF, UKF, IteratedEKF, KalmanFilter, SimplifiedUKF, SquareRootUKF
from difffilter.models.base import StateSpaceModel
from difffilter.models.heteroscedastic import (
    CN0Variance,
    ElevationVariance,
    HeteroscedasticMeasurement,
    MonotoneVariance,
    RobustGate,
    ScaledVariance,
    SumVariance,
)
from difffilter.models.motion import ConstantVelocity
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from difffilter.models.tracking import linear_measurement
from difffilter.selection import assign_parameters, named_raw_parameters

F64 = torch.float64


def _side(k: int = 6, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "elevation": 5.0 + 80.0 * torch.rand(3, k, generator=g, dtype=F64),
        "cn0": 20.0 + 30.0 * torch.rand(3, k, generator=g, dtype=F64),
        "constellation": torch.randint(0, 2, (3, k), generator=g).to(F64),
        "pr_var": 25.0 + 100.0 * torch.rand(3, k, generator=g, dtype=F64),
    }


def test_closed_forms_per_constellation() -> None:
    u = _side()
    like = torch.zeros((), dtype=F64)
    el = ElevationVariance(a=[2.0, 5.0], b=[3.0, 7.0], groups=2)
    cn = CN0Variance(a=[1.0, 4.0], b=[2e5, 6e5], groups=2)
    sc = ScaledVariance(scale=[0.5, 2.0], groups=2)
    g = u["constellation"].long().numpy()
    sin2 = np.sin(np.radians(u["elevation"].numpy())) ** 2
    inv_cn0 = 10.0 ** (-u["cn0"].numpy() / 10.0)
    np.testing.assert_allclose(el(u, like).detach().numpy(), np.array([2.0, 5.0])[g] + np.array([3.0, 7.0])[g] / sin2, rtol=1e-12)
    np.testing.assert_allclose(cn(u, like).detach().numpy(), np.array([1.0, 4.0])[g] + np.array([2e5, 6e5])[g] * inv_cn0, rtol=1e-12)
    np.testing.assert_allclose(sc(u, like).detach().numpy(), np.array([0.5, 2.0])[g] * u["pr_var"].numpy(), rtol=1e-12)
    total = SumVariance(el, cn)(u, like)
    torch.testing.assert_close(total, el(u, like) + cn(u, like))
    # one group: no constellation needed; empty slots (elevation 0) stay finite
    one = ElevationVariance(a=2.0, b=3.0)
    assert torch.isfinite(one({"elevation": torch.zeros(4, dtype=F64)}, like)).all()


def test_parameters_are_bounded_around_their_start_and_named() -> None:
    el = ElevationVariance(a=[2.0, 5.0], b=[3.0, 7.0], groups=2, bound=10.0)
    names = set(named_raw_parameters(el))
    assert names == {"a", "b"}
    assign_parameters(el, {"a": [19.0, 0.3]})  # inside [0.2, 50]
    with pytest.raises(ValueError):
        assign_parameters(el, {"a": [60.0, 1.0]})
    with torch.no_grad():  # any raw value stays inside the bounds
        next(iter(named_raw_parameters(el)["b"])).fill_(1e3)
    assert float(el.b.detach().max()) <= 70.0 + 1e-9 and float(el.b.detach().min()) > 0
    with pytest.raises(ValueError, match="a must"):
        ElevationVariance(a=[1.0, 2.0, 3.0], groups=2)
    with pytest.raises(ValueError, match="positive"):
        CN0Variance(b=-1.0)


def test_monotone_variance_interpolates_and_stays_monotone() -> None:
    mv = MonotoneVariance(knots=[10.0, 30.0, 60.0, 90.0], values=[40.0, 20.0, 10.0, 10.0], key="elevation")
    like = torch.zeros((), dtype=F64)
    x = torch.tensor([0.0, 10.0, 20.0, 30.0, 45.0, 60.0, 75.0, 90.0, 95.0], dtype=F64)
    expect = np.interp(x.numpy(), [10.0, 30.0, 60.0, 90.0], [40.0, 20.0, 10.0, 10.0])
    np.testing.assert_allclose(mv({"elevation": x}, like).detach().numpy(), expect, rtol=1e-7)
    with pytest.raises(ValueError, match="non-increasing"):
        MonotoneVariance(knots=[10.0, 30.0], values=[10.0, 20.0], key="elevation")
    with pytest.raises(ValueError, match="increasing numbers"):
        MonotoneVariance(knots=[30.0, 10.0], values=[20.0, 10.0], key="elevation")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3), st.floats(-5.0, 5.0))
def test_monotone_variance_is_monotone_for_any_raw_parameters(raw_ratios, raw_first) -> None:
    mv = MonotoneVariance(knots=[0.0, 1.0, 2.0, 3.0], values=[8.0, 4.0, 2.0, 1.0], key="x", groups=2, group_key="g")
    raws = named_raw_parameters(mv)
    with torch.no_grad():
        raws["ratios"][0].copy_(torch.tensor([raw_ratios, raw_ratios[::-1]], dtype=F64))
        raws["first"][0].fill_(raw_first)
    x = torch.linspace(-1.0, 4.0, 101, dtype=F64)
    for grp in (0.0, 1.0):
        v = mv({"x": x, "g": torch.full_like(x, grp)}, x)
        assert bool((v > 0).all()) and bool((v[1:] <= v[:-1] * (1 + 1e-12)).all())


def test_gradients_match_central_differences() -> None:
    u = _side(seed=1)
    model = SumVariance(ElevationVariance(a=[2.0, 5.0], b=[3.0, 7.0], groups=2), CN0Variance(a=1.0, b=2e5))
    mono = MonotoneVariance(knots=[20.0, 35.0, 50.0], values=[30.0, 12.0, 9.0], key="cn0", groups=2)
    w = torch.linspace(0.5, 1.5, 6, dtype=F64)
    for module in (model, mono):
        raws = named_raw_parameters(module)

        def loss(module=module) -> torch.Tensor:
            return (torch.log(module(u, w)) * w).sum()

        module.zero_grad()
        loss().backward()
        for name, (raw,) in raws.items():
            auto = raw.grad.clone()
            for i in range(raw.numel()):
                h = 1e-6
                with torch.no_grad():
                    raw.view(-1)[i] += h
                    up = float(loss())
                    raw.view(-1)[i] -= 2 * h
                    down = float(loss())
                    raw.view(-1)[i] += h
                assert float(auto.view(-1)[i]) == pytest.approx((up - down) / (2 * h), rel=1e-5, abs=1e-8), name


def test_maximum_likelihood_recovers_a_known_elevation_law() -> None:
    """Residuals drawn with sigma^2 = a_g + b_g / sin^2(el): maximising the Gaussian likelihood
    over the variance module by back-propagation recovers (a_g, b_g) (4,000 draws per group)."""
    g = torch.Generator().manual_seed(7)
    n = 8000
    el = 5.0 + 80.0 * torch.rand(n, generator=g, dtype=F64)
    grp = (torch.arange(n) % 2).to(F64)
    true_a, true_b = torch.tensor([4.0, 9.0], dtype=F64), torch.tensor([1.0, 3.0], dtype=F64)
    var = true_a[grp.long()] + true_b[grp.long()] / torch.sin(torch.deg2rad(el)) ** 2
    res = torch.sqrt(var) * torch.randn(n, generator=g, dtype=F64)
    u = {"elevation": el, "constellation": grp}
    model = ElevationVariance(a=[1.0, 1.0], b=[1.0, 1.0], groups=2)
    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    for _ in range(600):
        opt.zero_grad()
        v = model(u, res)
        nll = 0.5 * (torch.log(v) + res * res / v).mean()
        nll.backward()
        opt.step()
    torch.testing.assert_close(model.a.detach(), true_a, rtol=0.15, atol=0.0)
    torch.testing.assert_close(model.b.detach(), true_b, rtol=0.15, atol=0.0)


def test_robust_gate_hard_soft_and_learnable() -> None:
    res = torch.tensor([0.0, 5.0, 20.0, 30.0, 60.0], dtype=F64)
    var = torch.full_like(res, 25.0)
    hard = RobustGate(threshold=2.5, floor=8.0)
    n = res.abs() / math.sqrt(25.0 + 64.0)
    torch.testing.assert_close(hard.factor(res, var), torch.where(n > 2.5, 1e6, 1.0).to(F64))
    assert list(hard.parameters()) == []
    soft = RobustGate(threshold=2.5, floor=8.0, softness=2e-3)
    far = (n - 2.5).abs() > 0.05
    torch.testing.assert_close(soft.factor(res, var)[far], hard.factor(res, var)[far], rtol=1e-6, atol=0.0)
    learn = RobustGate(threshold=2.5, floor=8.0, softness=0.3, learnable=True)
    assert set(named_raw_parameters(learn)) == {"gate_softness", "gate_threshold", "gate_floor"}
    raws = named_raw_parameters(learn)

    def loss() -> torch.Tensor:
        return torch.log(learn.factor(res, var)).sum()

    learn.zero_grad()
    loss().backward()
    for name, (raw,) in raws.items():
        auto, h = float(raw.grad), 1e-6
        with torch.no_grad():
            raw += h
            up = float(loss())
            raw -= 2 * h
            down = float(loss())
            raw += h
        assert abs(auto) > 1e-6 and auto == pytest.approx((up - down) / (2 * h), rel=1e-5), name
    with torch.no_grad():
        raws["gate_threshold"][0].add_(1.0)
    moved = float(learn.gate_threshold.detach())
    learn.set_softness(None)  # back to the hard gate: keeps the learned threshold as a number
    assert not learn.soft and not learn.learnable and learn.threshold == pytest.approx(moved)
    with pytest.raises(ValueError, match="smooth gate"):
        RobustGate(kind="huber").set_learnable(True)


def test_heteroscedastic_measurement_matches_a_hand_written_kalman_filter() -> None:
    """A constant-velocity target seen through a position sensor whose variance follows a
    reported quality number, with a gate: the EKF on HeteroscedasticMeasurement equals a Kalman
    filter written out with the same per-step R (and gate) by hand."""
    g = torch.Generator().manual_seed(3)
    steps, bsz = 30, 2
    dyn = ConstantVelocity(axes=1, dt=1.0, q=0.5, dtype=F64)
    base = linear_measurement(R=[1.0], H=[[1.0, 0.0]], dtype="float64")
    variance = ScaledVariance(scale=[2.0, 0.5], key="quality", groups=2, group_key="kind")
    meas = HeteroscedasticMeasurement(base, variance=variance, gate=RobustGate(threshold=3.0, floor=1.0), observed_key="z")
    quality = 0.5 + 3.0 * torch.rand(bsz, steps, 1, generator=g, dtype=F64)
    kind = torch.randint(0, 2, (bsz, steps, 1), generator=g).to(F64)
    z = torch.cumsum(torch.randn(bsz, steps, 1, generator=g, dtype=F64), 1)
    z[0, 10] += 40.0  # an outlier the gate rejects
    m0, p0 = torch.zeros(bsz, 2, dtype=F64), torch.eye(2, dtype=F64).expand(bsz, 2, 2) * 10.0
    out = EKF(StateSpaceModel(dyn, meas))(z, m0, p0, controls={"quality": quality, "kind": kind, "z": z})
    f, q, h = dyn.matrix().numpy(), dyn.Q.detach().numpy(), np.array([[1.0, 0.0]])
    for b in range(bsz):
        m, p = m0[b].numpy(), p0[b].numpy()
        for t in range(steps):
            m, p = f @ m, f @ p @ f.T + q
            r = (2.0 if kind[b, t, 0] == 0 else 0.5) * float(quality[b, t, 0])
            resid = float(z[b, t, 0]) - float((h @ m)[0])
            if abs(resid) / math.sqrt(r + 1.0) > 3.0:
                r *= 1e6
            s = float((h @ p @ h.T)[0, 0]) + r
            k = (p @ h.T) / s
            m = m + (k * resid).ravel()
            p = (np.eye(2) - k @ h) @ p
            np.testing.assert_allclose(out.mean[b, t].detach().numpy(), m, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(out.cov[b, t].detach().numpy(), p, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("make", [KalmanFilter, UKF, SquareRootUKF, SimplifiedUKF, lambda m: IteratedEKF(m, iterations=1)])
def test_every_filter_takes_the_heteroscedastic_measurement(make) -> None:
    """On a linear model with a learnable smooth gate, every Gaussian filter gives the EKF's
    means, covariances and log-likelihoods (the EKF matches the hand-written filter above), and
    the gradient of the log-likelihood reaches the scales and the gate's three parameters."""
    g = torch.Generator().manual_seed(5)
    steps, bsz = 25, 2
    variance = ScaledVariance(scale=[2.0, 0.5], key="quality", groups=2, group_key="kind")
    gate = RobustGate(threshold=3.0, floor=1.0, softness=0.1, learnable=True)
    meas = HeteroscedasticMeasurement(
        linear_measurement(R=[1.0], H=[[1.0, 0.0]], dtype="float64"), variance=variance, gate=gate, observed_key="z"
    )
    model = StateSpaceModel(ConstantVelocity(axes=1, dt=1.0, q=0.5, dtype=F64), meas)
    z = torch.cumsum(torch.randn(bsz, steps, 1, generator=g, dtype=F64), 1)
    z[0, 8] += 40.0
    u = {
        "quality": 0.5 + 3.0 * torch.rand(bsz, steps, 1, generator=g, dtype=F64),
        "kind": torch.randint(0, 2, (bsz, steps, 1), generator=g),
        "z": z,
    }
    m0, p0 = torch.zeros(bsz, 2, dtype=F64), torch.eye(2, dtype=F64).expand(bsz, 2, 2) * 10.0
    with torch.no_grad():
        ref = EKF(model)(z, m0, p0, controls=u)
    out = make(model)(z, m0, p0, controls=u)
    for a, b in ((out.mean, ref.mean), (out.cov, ref.cov), (out.log_likelihood, ref.log_likelihood)):
        torch.testing.assert_close(a.detach(), b, rtol=1e-9, atol=1e-9)
    params = {n: raw[0] for n, raw in named_raw_parameters(meas).items() if not n.startswith("base.")}  # base's own R is unused
    assert len(params) == 4
    grads = torch.autograd.grad(out.log_likelihood.sum(), list(params.values()))
    for name, grad in zip(params, grads, strict=True):
        assert torch.isfinite(grad).all() and float(grad.abs().sum()) > 0.0, name


def test_pseudorange_noise_model_reproduces_the_receiver_variances() -> None:
    """noise_model=ScaledVariance(scale 1, "pr_var") gives the same R as noise_from_data, and an
    elevation model gives diag(a + b / sin^2 el) under the same gate."""
    lay = GnssStateLayout.constant_velocity()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(4, 8, generator=g, dtype=F64) * 10.0
    sat = torch.randn(4, 5, 3, generator=g, dtype=F64) * 2e7
    u = {"sat_pos": sat, "pr_var": 10.0 + torch.rand(4, 5, generator=g, dtype=F64), "elevation": 10.0 + 70 * torch.rand(4, 5, dtype=F64)}
    ref = PseudorangeMeasurement(num_satellites=5, layout=lay, noise_from_data=True, robust="reject", gate=2.5, gate_floor=8.0)
    u["pr_obs"] = ref(x, u) + 30.0 * torch.randn(4, 5, generator=g, dtype=F64)
    new = PseudorangeMeasurement(
        num_satellites=5, layout=lay, robust="reject", gate=2.5, gate_floor=8.0, noise_model=ScaledVariance(scale=1.0)
    )
    torch.testing.assert_close(new.measurement_noise(x, u), ref.measurement_noise(x, u), rtol=0, atol=0)
    elev = PseudorangeMeasurement(num_satellites=5, layout=lay, noise_model=ElevationVariance(a=2.0, b=3.0))
    expect = 2.0 + 3.0 / torch.sin(torch.deg2rad(u["elevation"])) ** 2
    torch.testing.assert_close(torch.diagonal(elev.measurement_noise(x, u), dim1=-2, dim2=-1), expect)
    with pytest.raises(ValueError, match="noise_model"):
        PseudorangeMeasurement(num_satellites=5, layout=lay, noise_from_data=True, noise_model=ElevationVariance())
