"""Tests for difffilter.models.navigation.pseudorange (pseudorange measurement, CV-clock and odometry dynamics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from torch.func import jacfwd, vmap

from difffilter.filters import EKF, UKF
from difffilter.geometry import EARTH_RATE, SPEED_OF_LIGHT, enu_rotation, geodetic_to_ecef
from difffilter.models.base import StateSpaceModel
from difffilter.models.navigation.clock import ConstantVelocityClock, OdometryClockDynamics, clock_process_noise
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from difffilter.selection import named_raw_parameters
from experiments.papers.p001 import make_p001_model, simulate_p001

F64 = torch.float64
ORIGIN = geodetic_to_ecef(torch.tensor([math.radians(52.5), math.radians(13.37), 76.0], dtype=F64))


def _inputs(batch: int = 4, k: int = 5, seed: int = 0, dtype: torch.dtype = F64) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, 9, generator=g, dtype=F64) * torch.tensor([50, 50, 20, 5, 5, 1, 1e5, 40, 10], dtype=F64)
    direction = torch.randn(batch, k, 3, generator=g, dtype=F64)
    direction[..., 2] = direction[..., 2].abs() + 0.3
    sat = 2.2e7 * direction / direction.norm(dim=-1, keepdim=True)
    u = {
        "sat_pos": sat.to(dtype),
        "sat_vel": (torch.randn(batch, k, 3, generator=g, dtype=F64) * 3e3).to(dtype),
        "glonass": (torch.rand(batch, k, generator=g) > 0.5).to(dtype),
        "pr_var": (25 + 100 * torch.rand(batch, k, generator=g, dtype=F64)).to(dtype),
        "prr_var": (0.01 + torch.rand(batch, k, generator=g, dtype=F64)).to(dtype),
    }
    return x.to(dtype), u


@pytest.mark.parametrize("frame", ["ecef", "enu"])
@pytest.mark.parametrize("reduced", [False, True])
@pytest.mark.parametrize("rates", [False, True])
def test_jacobian_matches_autograd(frame: str, reduced: bool, rates: bool) -> None:
    model = PseudorangeMeasurement(
        num_satellites=5,
        layout=GnssStateLayout.constant_velocity(isb=True),
        rates=rates,
        sagnac=True,
        frame_origin=ORIGIN,
        frame=frame,
        reduced=reduced,
    )
    x, u = _inputs()
    auto = vmap(jacfwd(model), in_dims=(0, 0))(x, u)
    assert torch.allclose(model.jacobian(x, u), auto, atol=1e-8, rtol=0)


def test_reduced_equals_absolute_minus_reference_and_float32_precision() -> None:
    lay = GnssStateLayout.constant_velocity(isb=True)
    x, u = _inputs()
    absolute = PseudorangeMeasurement(num_satellites=5, layout=lay)(x, u)
    red = PseudorangeMeasurement(num_satellites=5, layout=lay, reduced=True)
    expected = absolute - u["sat_pos"].norm(dim=-1)
    assert torch.allclose(red(x, u), expected, atol=1e-6)
    x32, u32 = _inputs(dtype=torch.float32)
    red32 = PseudorangeMeasurement(num_satellites=5, layout=lay, reduced=True, dtype=torch.float32)
    # float32 spacing near 2e7 m is 2 m; the reduced form keeps centimetres (clock ~1e5 m: 8 mm)
    assert (red32(x32, u32).double() - red(x32.double(), {k: v.double() for k, v in u32.items()})).abs().max() < 0.05


def test_sagnac_term_and_enu_frame_against_direct_ecef_formula() -> None:
    lay = GnssStateLayout.constant_velocity(isb=True)
    x, u = _inputs()
    model = PseudorangeMeasurement(num_satellites=5, layout=lay, sagnac=True, frame_origin=ORIGIN, frame="enu")
    rot = enu_rotation(torch.tensor(math.radians(52.5), dtype=F64), torch.tensor(math.radians(13.37), dtype=F64))
    p = (ORIGIN + x[:, :3] @ rot).numpy()
    s = (ORIGIN + u["sat_pos"] @ rot).numpy()
    rng = np.linalg.norm(s - p[:, None], axis=-1)
    sagnac = EARTH_RATE / SPEED_OF_LIGHT * (s[..., 0] * p[:, None, 1] - s[..., 1] * p[:, None, 0])
    expected = rng + sagnac + x[:, 6, None].numpy() + u["glonass"].numpy() * x[:, 8, None].numpy()
    assert np.abs(model(x, u).numpy() - expected).max() < 1e-6
    assert np.abs(sagnac).max() > 1.0  # the term matters (tens of metres)


def test_isb_only_on_flagged_satellites() -> None:
    lay = GnssStateLayout.constant_velocity(isb=True)
    model = PseudorangeMeasurement(num_satellites=5, layout=lay)
    x, u = _inputs()
    x2 = x.clone()
    x2[:, 8] += 7.0
    diff = model(x2, u) - model(x, u)
    assert torch.allclose(diff, 7.0 * u["glonass"], atol=1e-6)


def test_rate_is_time_derivative_of_range() -> None:
    lay = GnssStateLayout.constant_velocity()
    model = PseudorangeMeasurement(num_satellites=5, layout=lay, rates=True)
    x, u = _inputs()
    x = x[:, :8]
    h = 1e-3
    x_next = x.clone()
    x_next[:, :3] += h * x[:, 3:6]
    x_next[:, 6] += h * x[:, 7]
    u_next = dict(u, sat_pos=u["sat_pos"] + h * u["sat_vel"])
    fd = (model(x_next, u_next)[:, :5] - model(x, u)[:, :5]) / h
    assert torch.allclose(model(x, u)[:, 5:], fd, atol=1e-4)


def test_noise_from_data_and_robust_inflation() -> None:
    lay = GnssStateLayout.constant_velocity(isb=True)
    x, u = _inputs()
    model = PseudorangeMeasurement(num_satellites=5, layout=lay, rates=True, noise_from_data=True)
    model.noise_scale = torch.tensor(2.0, dtype=F64)
    r = model.measurement_noise(x, u)
    assert r.shape == (4, 10, 10)
    assert torch.allclose(torch.diagonal(r, dim1=-2, dim2=-1), 2.0 * torch.cat([u["pr_var"], u["prr_var"]], -1))
    gated = PseudorangeMeasurement(num_satellites=5, layout=lay, noise_from_data=True, robust="reject", gate=3.0)
    z = gated(x, u).detach().clone()
    z[:, 1] += 200.0  # a gross outlier on satellite 1 only
    var = torch.diagonal(gated.measurement_noise(x, dict(u, pr_obs=z)), dim1=-2, dim2=-1)
    assert torch.allclose(var[:, [0, 2, 3, 4]], u["pr_var"][:, [0, 2, 3, 4]])
    assert bool((var[:, 1] > 1e5 * u["pr_var"][:, 1]).all())
    huber = PseudorangeMeasurement(num_satellites=5, layout=lay, noise_from_data=True, robust="huber", gate=1.0)
    var_h = torch.diagonal(huber.measurement_noise(x, dict(u, pr_obs=z)), dim1=-2, dim2=-1)
    expected = u["pr_var"][:, 1] * 200.0 / u["pr_var"][:, 1].sqrt()
    assert torch.allclose(var_h[:, 1], expected, rtol=1e-9)


def test_constant_velocity_clock_matches_van_loan() -> None:
    dyn = ConstantVelocityClock(
        dt=3.0, accel_psd=torch.tensor([0.5, 1.0, 2.0]), clock_bias_psd=0.3, clock_drift_psd=0.7, isb=True, isb_psd=0.2
    )
    n = 9
    F = np.zeros((n, n))
    F[0, 3] = F[1, 4] = F[2, 5] = F[6, 7] = 1.0
    qc = np.diag([0, 0, 0, 0.5, 1.0, 2.0, 0.3, 0.7, 0.2])
    big = np.zeros((2 * n, 2 * n))
    big[:n, :n], big[:n, n:], big[n:, n:] = -F, qc, F.T
    e = scipy.linalg.expm(big * 3.0)
    phi = e[n:, n:].T
    q = phi @ e[:n, n:]
    assert np.allclose(dyn.matrix(None).numpy(), phi, atol=1e-12)
    assert np.allclose(dyn.Q.detach().numpy(), q, atol=1e-10)
    x = torch.randn(2, n, dtype=F64)
    assert torch.allclose(dyn(x), x @ dyn.matrix(None).mT)
    u = {"dt": torch.tensor([[1.0], [3.0]], dtype=F64)}
    assert torch.allclose(dyn.process_noise(x, u)[1], dyn.Q)
    assert torch.allclose(
        clock_process_noise(torch.tensor(3.0, dtype=F64), torch.tensor(0.3), torch.tensor(0.7)).double(),
        torch.from_numpy(q[6:8, 6:8]),
        atol=1e-6,
    )


def test_dynamics_jacobians_match_autograd() -> None:
    g = torch.Generator().manual_seed(3)
    x = torch.randn(5, 7, generator=g, dtype=F64)
    u = {
        "speed": torch.rand(5, 1, generator=g, dtype=F64) * 10,
        "yaw_rate": torch.randn(5, 1, generator=g, dtype=F64) * 0.3,
        "dt": torch.full((5, 1), 0.3, dtype=F64),
    }
    odo = OdometryClockDynamics()
    assert torch.allclose(odo.jacobian(x, u), vmap(jacfwd(odo), in_dims=(0, 0))(x, u), atol=1e-10)
    q = odo.process_noise(x, u)
    assert torch.allclose(q, q.mT) and bool((torch.linalg.eigvalsh(q) > -1e-12).all())
    cv = ConstantVelocityClock(isb=True)
    x9 = torch.randn(5, 9, generator=g, dtype=F64)
    assert torch.allclose(cv.jacobian(x9, u), vmap(jacfwd(cv), in_dims=(0, 0))(x9, u), atol=1e-12)


def test_odometry_follows_a_circular_arc() -> None:
    odo = OdometryClockDynamics(isb=False)
    speed, rate, dt = 8.0, 0.4, 0.2
    x = torch.zeros(1, 6, dtype=F64)
    x[0, 3] = 0.3
    u = {"speed": torch.tensor([[speed]], dtype=F64), "yaw_rate": torch.tensor([[rate]], dtype=F64), "dt": torch.tensor([[dt]], dtype=F64)}
    for _ in range(50):
        x = odo(x, u)
    t = 50 * dt
    radius = speed / rate
    exact_e = radius * (math.sin(0.3 + rate * t) - math.sin(0.3))
    exact_n = -radius * (math.cos(0.3 + rate * t) - math.cos(0.3))
    # midpoint heading: chord length error (rate dt)^2 / 24 per step, relative
    tol = 50 * speed * dt * (rate * dt) ** 2 / 24 + 1e-9
    assert abs(x[0, 0].item() - exact_e) < tol and abs(x[0, 1].item() - exact_n) < tol
    assert x[0, 3].item() == pytest.approx(0.3 + rate * t)


def _p001_model_and_data(dtype: torch.dtype) -> tuple[StateSpaceModel, object]:
    return make_p001_model(dtype=dtype), simulate_p001(3, seed=5, dtype=dtype, num_epochs=30)


def test_filters_on_p001_batch_equals_loop_and_dtypes() -> None:
    model, sc = _p001_model_and_data(F64)
    ekf = EKF(model)
    full = ekf(sc.measurements, sc.initial_mean, sc.initial_cov, controls=sc.controls)
    for b in range(3):
        one = ekf(
            sc.measurements[b : b + 1],
            sc.initial_mean[b : b + 1],
            sc.initial_cov,
            controls={k: v[b : b + 1] for k, v in sc.controls.items()},
        )
        assert torch.allclose(one.mean[0], full.mean[b], atol=1e-9)
    err = (full.mean[:, 10:, :3] - sc.truth[:, 10:, :3]).norm(dim=-1)
    assert err.mean() < 10.0  # converged from the 10 m start
    ukf = UKF(model)
    res = ukf(sc.measurements, sc.initial_mean, sc.initial_cov, controls=sc.controls)
    assert torch.allclose(res.mean, full.mean, atol=1e-3)  # nearly linear measurement
    model32, sc32 = _p001_model_and_data(torch.float32)
    res32 = EKF(model32)(sc32.measurements, sc32.initial_mean, sc32.initial_cov, controls=sc32.controls)
    assert res32.mean.dtype == torch.float32
    assert (res32.mean.double() - full.mean).abs().max() < 0.05


def test_gradients_reach_learnable_noise() -> None:
    model, sc = _p001_model_and_data(F64)
    res = UKF(model)(sc.measurements, sc.initial_mean, sc.initial_cov, controls=sc.controls)
    res.log_likelihood.sum().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert model.measurement.parametrizations.R.original.grad.abs() > 0


def _gated(softness: float | None, **kwargs: object) -> PseudorangeMeasurement:
    lay = GnssStateLayout.constant_velocity(isb=True)
    return PseudorangeMeasurement(
        num_satellites=6, layout=lay, noise_from_data=True, robust="reject", gate=2.5, gate_floor=8.0, gate_softness=softness, **kwargs
    )


def test_soft_gate_tends_to_the_hard_gate_and_default_is_unchanged() -> None:
    x, u = _inputs(batch=2, k=6)
    hard = _gated(None)
    var = u["pr_var"]
    n = torch.tensor([0.0, 1.0, 2.3, 2.7, 4.0, 50.0], dtype=F64)  # normalised residuals, either side of 2.5
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0], dtype=F64)
    z = hard(x, u).detach() + sign * n * torch.sqrt(var + 8.0**2)
    uz = dict(u, pr_obs=z)
    r_hard = torch.diagonal(hard.measurement_noise(x, uz), dim1=-2, dim2=-1)
    assert torch.equal(r_hard[:, :3], var[:, :3])
    torch.testing.assert_close(r_hard[:, 3:], 1e6 * var[:, 3:], rtol=1e-14, atol=0)
    # the hard gate has no temperature parameter; None and 0 are the same hard gate
    assert not hard.soft_gate and "gate_softness" not in dict(hard.named_parameters())
    assert torch.equal(torch.diagonal(_gated(0.0).measurement_noise(x, uz), dim1=-2, dim2=-1), r_hard)
    errors = []
    for t in (0.5, 0.1, 0.02, 0.005):
        soft = _gated(t)
        assert soft.soft_gate and float(soft.gate_softness.detach()) == pytest.approx(t)
        r_soft = torch.diagonal(soft.measurement_noise(x, uz), dim1=-2, dim2=-1)
        assert bool((r_soft >= var).all()) and bool((r_soft <= 1e6 * var * (1 + 1e-12)).all())
        errors.append(float((torch.log(r_soft) - torch.log(r_hard)).abs().max()))
    assert errors == sorted(errors, reverse=True) and errors[-1] < 1e-9, errors
    # at the gate itself the smooth factor is sqrt(1e6) = 1e3 for every temperature
    at = dict(u, pr_obs=hard(x, u).detach() + 2.5 * torch.sqrt(var + 8.0**2))
    r_at = torch.diagonal(_gated(0.2).measurement_noise(x, at), dim1=-2, dim2=-1)
    torch.testing.assert_close(r_at, 1e3 * var)
    # switching back to the hard gate removes the parameter again
    soft.set_gate_softness(None)
    assert not soft.soft_gate and "gate_softness" not in dict(soft.named_parameters())
    assert torch.equal(torch.diagonal(soft.measurement_noise(x, uz), dim1=-2, dim2=-1), r_hard)
    with pytest.raises(ValueError, match="gate_softness"):
        PseudorangeMeasurement(num_satellites=6, layout=GnssStateLayout.constant_velocity(isb=True), robust="huber", gate_softness=0.2)
    with pytest.raises(ValueError, match="gate_softness"):
        _gated(-0.1)


def test_soft_gate_position_gradient_matches_finite_differences() -> None:
    """With the smooth gate a position loss is differentiable through the gate: autograd agrees
    with central differences w.r.t. the noise scale and the temperature (the hard gate's step is
    invisible to autograd, see results/smartloc_real.md)."""
    base = make_p001_model(dtype=F64)
    sc = simulate_p001(2, seed=5, dtype=F64, num_epochs=25)
    meas = PseudorangeMeasurement(
        num_satellites=7,
        layout=GnssStateLayout.constant_velocity(),
        reduced=True,
        noise_from_data=True,
        robust="reject",
        gate=2.5,
        gate_floor=2.0,
        gate_softness=0.3,
    )
    model = StateSpaceModel(base.dynamics, meas)
    z = sc.measurements.clone()
    g = torch.Generator().manual_seed(3)
    z = z + 15.0 * (torch.rand(z.shape, generator=g, dtype=F64) < 0.15) * torch.randn(z.shape, generator=g, dtype=F64)
    controls = dict(sc.controls, pr_obs=z, pr_var=torch.full_like(z, 9.0))

    def loss() -> torch.Tensor:
        res = UKF(model)(z, sc.initial_mean, sc.initial_cov, controls=controls)
        return (res.mean[..., :2] - sc.truth[..., :2]).norm(dim=-1).mean()

    raws = {k.rsplit(".", 1)[-1]: v[0] for k, v in named_raw_parameters(meas).items()}  # the gate lives in meas.robust_gate
    for name in ("noise_scale", "gate_softness"):
        raw = raws[name]
        meas.zero_grad()
        loss().backward()
        auto = float(raw.grad)
        h = 1e-5
        with torch.no_grad():
            raw += h
            up = float(loss())
            raw -= 2 * h
            down = float(loss())
            raw += h
        numeric = (up - down) / (2 * h)
        assert abs(numeric) > 1e-4, (name, numeric)  # the gate is active in this case
        assert auto == pytest.approx(numeric, rel=1e-4, abs=1e-7), (name, auto, numeric)
