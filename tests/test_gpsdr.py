"""Tests of the p000 GPS/DR model and simulator, and of filters tracking it."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from difffilter.filters import EKF, UKF, Julier
from difffilter.models.motion import ConstantAcceleration, constant_acceleration_noise
from experiments.papers.p000 import SCRIPTED_DRIVE, simulate_p000
from experiments.papers.p000.model import GPSDR_PAPER, GpsDrDynamics, GpsDrMeasurement, GpsDrModel, gpsdr_paper_initial_belief

F64 = torch.float64
MOTIONS = ("paper", "singer", "current_statistical")


def _states(gen: torch.Generator, n: int) -> torch.Tensor:
    x = torch.randn(n, 8, generator=gen, dtype=F64) * torch.tensor([50, 8, 1, 50, 8, 1, 1e-3, 0.01], dtype=F64)
    x[:, 7] += 1.0
    x[0, [1, 2, 4, 5]] = 0.0  # standstill
    x[1, [1, 4]] = torch.tensor([1e-3, -2e-3], dtype=F64)  # almost standstill
    return x


# ---------------------------------------------------------------------------------- model
@pytest.mark.parametrize("motion", MOTIONS)
@pytest.mark.parametrize("g", [1.0, 1.5])
def test_jacobians_match_autograd(motion: str, g: float) -> None:
    model = GpsDrModel.paper(motion=motion, g=g, dtype=F64)
    x = _states(torch.Generator().manual_seed(0), 16)
    for fn in (model.dynamics, model.measurement):
        auto = vmap(jacrev(lambda xi, fn=fn: fn(xi)))(x)
        analytic = fn.jacobian(x)
        assert bool(torch.isfinite(analytic).all())
        torch.testing.assert_close(analytic, auto, rtol=0, atol=1e-8)
    u = {"dt": torch.linspace(0.05, 1.0, 16, dtype=F64)[:, None]}
    for fn in (model.dynamics, model.measurement):
        auto = vmap(jacrev(lambda xi, ui, fn=fn: fn(xi, ui)), in_dims=(0, 0))(x, u)
        torch.testing.assert_close(fn.jacobian(x, u), auto, rtol=0, atol=1e-8)


def test_measurement_values_and_standstill() -> None:
    meas = GpsDrMeasurement(dt=0.1, g=1.5, speed_floor=0.1, dtype=F64)
    x = torch.tensor([5.0, 3.0, 1.0, -2.0, 4.0, 0.5, 0.01, 1.02], dtype=F64)
    den = 1.5 * 9 + 16 + 0.01
    expect = torch.tensor([5.0, -2.0, (4 * 1.0 - 3 * 0.5) / den + 0.01, 1.02 * 0.1 * math.sqrt(den)], dtype=F64)
    torch.testing.assert_close(meas(x), expect)
    still = torch.tensor([0.0, 0.0, 0.3, 0.0, 0.0, -0.2, 0.02, 1.0], dtype=F64, requires_grad=True)
    z = meas(still)
    torch.testing.assert_close(z[2].detach(), torch.tensor(0.02, dtype=F64))  # yaw rate -> drift
    torch.testing.assert_close(z[3].detach(), torch.tensor(0.1 * 0.1, dtype=F64))  # psi T v_0
    z.sum().backward()
    assert bool(torch.isfinite(still.grad).all())


def test_paper_model_settings() -> None:
    model = GpsDrModel.paper(dtype=F64)
    r = torch.diag(torch.tensor([15.0**2, 15.0**2, math.radians(0.4) ** 2, 1.0], dtype=F64))
    torch.testing.assert_close(model.R, r)
    q = model.Q
    s2 = GPSDR_PAPER["sigma_a"] ** 2
    qa = constant_acceleration_noise(torch.tensor(0.1, dtype=F64))
    torch.testing.assert_close(q[:3, :3], 2 * s2 * qa)
    torch.testing.assert_close(q[3:6, 3:6], 2 * s2 * qa)
    phi = math.exp(-0.1 / 100.0)
    torch.testing.assert_close(q[6, 6], torch.tensor(math.radians(0.015) ** 2 * (1 - phi**2), dtype=F64))
    torch.testing.assert_close(q[7, 7], torch.tensor(0.005**2 * 0.1 / 100.0, dtype=F64))
    f = model.dynamics.matrix()
    torch.testing.assert_close(f[6, 6], torch.tensor(phi, dtype=F64))
    mean, cov = gpsdr_paper_initial_belief(F64)
    torch.testing.assert_close(mean, torch.tensor([0, 10, 0, 0, 10, 0, 0, 1], dtype=F64))
    torch.testing.assert_close(cov, torch.eye(8, dtype=F64))
    with pytest.raises(ValueError):
        GpsDrModel(motion="bogus")
    with pytest.raises(ValueError):
        GpsDrDynamics(motion=ConstantAcceleration(axes=3))


def test_batch_equals_loop_and_dtypes() -> None:
    gen = torch.Generator().manual_seed(1)
    x = _states(gen, 6)
    for motion in MOTIONS:
        m64 = GpsDrModel.paper(motion=motion, dtype=F64)
        m32 = GpsDrModel.paper(motion=motion, dtype=torch.float32)
        fb, hb, qb = m64.f(x), m64.h(x), m64.dynamics.process_noise(x)
        for i in range(6):
            torch.testing.assert_close(fb[i], m64.f(x[i]))
            torch.testing.assert_close(hb[i], m64.h(x[i]))
            torch.testing.assert_close(qb.expand(6, 8, 8)[i], m64.dynamics.process_noise(x[i]))
        assert m32.f(x.float()).dtype == torch.float32
        torch.testing.assert_close(m32.h(x.float()).double(), hb, rtol=1e-5, atol=1e-5)


def test_learnable_parameters_receive_gradients() -> None:
    data = simulate_p000(batch_size=2, seed=3, steps=30, dtype=F64)
    model = data.make_model(motion="singer")
    mean, cov = data.initial_belief()
    res = UKF(model, sigma_points=Julier(kappa=-5.0), redraw_after_predict=False)(data.measurements, mean, cov, mask=data.mask)
    res.log_likelihood.sum().backward()
    named = dict(model.named_parameters())
    for key in ("dynamics.motion.parametrizations.tau.original", "dynamics.motion.parametrizations.sigma_a.original"):
        assert named[key].grad is not None and bool(torch.isfinite(named[key].grad).all())
    assert float(named["measurement.parametrizations.R.original"].grad.abs().sum()) > 0


# ---------------------------------------------------------------------------------- simulator
def test_straight_scenario_truth_is_the_papers_uniform_motion() -> None:
    data = simulate_p000(batch_size=2, seed=0, scenario="straight", steps=500, dtype=F64)
    assert data.truth.shape == (2, 500, 8) and data.measurements.shape == (2, 500, 4) and data.mask.shape == (2, 500, 4)
    torch.testing.assert_close(data.initial_state[0], torch.tensor([0, 10, 0, 0, 10, 0, 0, 1], dtype=F64))
    t = 0.1 * torch.arange(1, 501, dtype=F64)
    torch.testing.assert_close(data.truth[0, :, 0], 10 * t)
    torch.testing.assert_close(data.truth[0, :, 3], 10 * t)
    assert float(data.truth[..., [2, 5]].abs().max()) < 1e-9
    assert float((data.truth[..., 7] - 1).abs().max()) == 0.0
    mean, cov = data.initial_belief()
    torch.testing.assert_close(mean, data.initial_state)
    torch.testing.assert_close(cov, torch.eye(8, dtype=F64))


def test_determinism_and_dtypes() -> None:
    a = simulate_p000(batch_size=2, seed=5, scenario="random", steps=300, dtype=F64)
    b = simulate_p000(batch_size=2, seed=5, scenario="random", steps=300, dtype=F64)
    c = simulate_p000(batch_size=2, seed=6, scenario="random", steps=300, dtype=F64)
    torch.testing.assert_close(a.truth, b.truth)
    torch.testing.assert_close(a.measurements, b.measurements)
    assert float((a.truth - c.truth).abs().max()) > 1.0
    f = simulate_p000(batch_size=2, seed=torch.Generator().manual_seed(5), scenario="random", steps=300, dtype=torch.float32)
    assert f.truth.dtype == torch.float32 and f.measurements.dtype == torch.float32
    torch.testing.assert_close(f.truth.double(), a.truth, rtol=1e-6, atol=1e-4)
    with pytest.raises(ValueError):
        simulate_p000(scenario="circle")


@pytest.mark.parametrize("scenario", ["scripted", "random"])
def test_truth_is_kinematically_consistent(scenario: str) -> None:
    data = simulate_p000(batch_size=3, seed=2, scenario=scenario, steps=5000, dtype=F64)
    x = torch.cat([data.initial_state[:, None], data.truth], 1)
    dt = data.dt
    # increments are the trapezoid of the derivative (error bounded by the 1 s-smoothed jerk)
    for i in (0, 3):
        dp = x[:, 1:, i] - x[:, :-1, i]
        dv = x[:, 1:, i + 1] - x[:, :-1, i + 1]
        torch.testing.assert_close(dp, 0.5 * dt * (x[:, 1:, i + 1] + x[:, :-1, i + 1]), atol=2e-3, rtol=0)
        torch.testing.assert_close(dv, 0.5 * dt * (x[:, 1:, i + 2] + x[:, :-1, i + 2]), atol=1e-2, rtol=0)
    speed = torch.sqrt(x[..., 1] ** 2 + x[..., 4] ** 2)
    assert float(speed.min()) > 2.0 and float(speed.max()) < 27.0
    lateral = (x[..., 4] * x[..., 2] - x[..., 1] * x[..., 5]) / speed
    assert float(lateral.abs().max()) < 4.5
    if scenario == "scripted":
        assert sum(s[0] for s in SCRIPTED_DRIVE) == 500.0
        torch.testing.assert_close(speed[:, 0], torch.full((3,), 12.0, dtype=F64))


@pytest.mark.parametrize("g", [1.0, 1.5])
def test_measurement_noise_statistics(g: float) -> None:
    data = simulate_p000(batch_size=4, seed=7, scenario="random", steps=5000, g=g, dtype=F64)
    model = data.make_model()
    resid = data.measurements - model.h(data.truth)  # the model's h is the simulator's sensor law
    n = resid.shape[0] * resid.shape[1]
    sig = torch.tensor([15.0, 15.0, math.radians(0.4), 1.0], dtype=F64)
    z = resid / sig
    mean, std = z.mean((0, 1)), z.std((0, 1))
    assert bool((mean.abs() < 4.0 / math.sqrt(n)).all()), mean
    assert bool(((std - 1).abs() < 4.0 / math.sqrt(2 * n)).all()), std


def test_gyro_drift_is_gauss_markov() -> None:
    data = simulate_p000(batch_size=64, seed=11, scenario="scripted", steps=5000, dtype=F64)
    eps = torch.cat([data.initial_state[:, None, 6], data.truth[..., 6]], 1)
    sigma, phi = math.radians(0.015), math.exp(-0.1 / 100.0)
    innov = eps[:, 1:] - phi * eps[:, :-1]
    n = innov.numel()
    ratio = innov.std() / (sigma * math.sqrt(1 - phi**2))
    assert abs(float(ratio) - 1) < 4.0 / math.sqrt(2 * n)
    # stationary start: the initial drift has std sigma (64 samples: loose bound)
    assert 0.6 < float(data.initial_state[:, 6].std() / sigma) < 1.4
    psi = data.truth[:, :, 7]
    assert float((psi - psi[:, :1]).abs().max()) == 0.0 and 0.98 < float(psi.mean()) < 1.02


def test_gps_outages_mask_and_filtering_through_them() -> None:
    data = simulate_p000(batch_size=2, seed=1, scenario="scripted", steps=600, gps_outages=[(20.0, 40.0)], random_outages=1, dtype=F64)
    t = 0.1 * torch.arange(1, 601, dtype=F64)
    inside = (t >= 20.0) & (t < 40.0)
    assert not bool(data.mask[:, inside, :2].any())
    assert bool(data.mask[..., 2:].all())
    assert bool(torch.isnan(data.measurements[~data.mask]).all())
    assert bool(torch.isfinite(data.measurements[data.mask]).all())
    lost = (~data.mask[..., 0]).sum(1)
    assert bool((lost >= 200).all()) and bool((lost <= 200 + 300).all())
    model = data.make_model()
    res = EKF(model)(data.measurements, *data.initial_belief(), mask=data.mask)
    assert bool(torch.isfinite(res.mean).all())


# ---------------------------------------------------------------------------------- filters
def _position_error(res_mean: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    return (res_mean[..., [0, 3]] - truth[..., [0, 3]]).norm(dim=-1)


def _filters(model: GpsDrModel) -> dict[str, torch.nn.Module]:
    # the paper's UKF: Julier weights with n + kappa = 3, measurement on the propagated points
    return {"ukf": UKF(model, sigma_points=Julier(kappa=3.0 - 8), redraw_after_predict=False), "ekf": EKF(model)}


@pytest.mark.parametrize("scenario", ["straight", "scripted"])
def test_filters_track_a_short_run(scenario: str) -> None:
    data = simulate_p000(batch_size=2, seed=4, scenario=scenario, steps=600, dtype=F64)
    model = data.make_model()
    for name, filt in _filters(model).items():
        with torch.no_grad():
            res = filt(data.measurements, *data.initial_belief(), mask=data.mask)
        err = _position_error(res.mean, data.truth)
        gps = (data.measurements[..., :2] - data.truth[..., [0, 3]]).norm(dim=-1)
        assert bool(torch.isfinite(res.cov).all()), name
        # the filter beats raw GPS by a wide margin after the first 10 s
        assert float(err[:, 100:].pow(2).mean().sqrt()) < 0.5 * float(gps.pow(2).mean().sqrt()), name


def test_float32_filtering_matches_float64() -> None:
    data = simulate_p000(batch_size=2, seed=9, scenario="scripted", steps=300, dtype=F64)
    mean, cov = data.initial_belief()
    out = {}
    for dtype in (torch.float32, F64):
        model = data.make_model(dtype=dtype)
        filt = UKF(model, sigma_points=Julier(kappa=-5.0), redraw_after_predict=False)
        with torch.no_grad():
            out[dtype] = filt(data.measurements.to(dtype), mean.to(dtype), cov.to(dtype), mask=data.mask).mean
    assert out[torch.float32].dtype == torch.float32
    diff = (out[torch.float32].double() - out[F64])[..., [0, 3]].abs().max()
    assert float(diff) < 0.05  # metres, against a 15 m GPS


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["straight", "scripted", "random"])
@pytest.mark.parametrize("g", [1.0, 1.5])
def test_filters_track_the_full_500_s_with_paper_settings(scenario: str, g: float) -> None:
    data = simulate_p000(batch_size=4, seed=8, scenario=scenario, steps=5000, g=g, dtype=F64)
    model = data.make_model()
    for name, filt in _filters(model).items():
        with torch.no_grad():
            res = filt(data.measurements, *data.initial_belief(), mask=data.mask)
        err = _position_error(res.mean, data.truth)
        assert bool(torch.isfinite(res.mean).all()) and bool(torch.isfinite(res.cov).all()), name
        assert float(err[:, 100:].pow(2).mean().sqrt()) < 8.0, name  # GPS alone: 21 m
        assert float(err[:, -1000:].pow(2).mean().sqrt()) < 8.0, name  # no divergence at the end
        assert float(err.max()) < 40.0, name
