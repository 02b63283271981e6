"""Tests of the p004 GNSS/IMU models, switching statistics and vehicle simulator."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

from difffilter.filters import EKF, UKF, MerweScaled
from experiments.papers.p004 import P004_SPEED_KNOTS, simulate_p004
from experiments.papers.p004 import imu_switching_statistics as p004_switching_statistics
from experiments.papers.p004.model import (
    GRAVITY,
    GnssImuDynamics,
    GnssImuModel,
    GnssMeasurement,
    PlanarGnssImuDynamics,
    quaternion_multiply,
    quaternion_to_rotation,
)

F64 = torch.float64
NOISE_FREE = {"sigma_accel": 0.0, "sigma_gyro": 0.0, "sigma_accel_bias": 0.0, "sigma_gyro_bias": 0.0}


def _unit(q: torch.Tensor) -> torch.Tensor:
    return q / q.norm(dim=-1, keepdim=True)


# ---------------------------------------------------------------------------------- quaternions
def test_quaternion_helpers() -> None:
    gen = torch.Generator().manual_seed(0)
    p, q = _unit(torch.randn(10, 4, generator=gen, dtype=F64)), _unit(torch.randn(10, 4, generator=gen, dtype=F64))
    rp, rq = quaternion_to_rotation(p), quaternion_to_rotation(q)
    torch.testing.assert_close(rp @ rp.mT, torch.eye(3, dtype=F64).expand(10, 3, 3))
    torch.testing.assert_close(torch.linalg.det(rp), torch.ones(10, dtype=F64))
    torch.testing.assert_close(quaternion_to_rotation(quaternion_multiply(p, q)), rp @ rq)
    yaw = torch.tensor(0.3, dtype=F64)  # rotation about up by yaw
    rz = quaternion_to_rotation(torch.stack([torch.cos(yaw / 2), yaw * 0, yaw * 0, torch.sin(yaw / 2)]))
    torch.testing.assert_close(rz[:2, 0], torch.stack([torch.cos(yaw), torch.sin(yaw)]))


# ---------------------------------------------------------------------------------- dynamics
def _controls(gen: torch.Generator, b: int, planar: bool) -> dict[str, torch.Tensor]:
    if planar:
        return {"accel": torch.randn(b, 2, generator=gen, dtype=F64), "gyro": 0.2 * torch.randn(b, 1, generator=gen, dtype=F64)}
    accel = torch.randn(b, 3, generator=gen, dtype=F64) + torch.tensor([0, 0, GRAVITY], dtype=F64)
    return {"accel": accel, "gyro": 0.2 * torch.randn(b, 3, generator=gen, dtype=F64)}


def test_planar_jacobian_matches_autograd() -> None:
    gen = torch.Generator().manual_seed(1)
    dyn = PlanarGnssImuDynamics(dt=0.7, dtype=F64)
    x = torch.randn(9, 8, generator=gen, dtype=F64) * 3
    u = _controls(gen, 9, planar=True)
    auto = vmap(jacrev(lambda xi, ui: dyn(xi, ui)), in_dims=(0, 0))(x, u)
    torch.testing.assert_close(dyn.jacobian(x, u), auto, rtol=0, atol=1e-8)
    u["dt"] = torch.linspace(0.1, 2.0, 9, dtype=F64)[:, None]
    auto = vmap(jacrev(lambda xi, ui: dyn(xi, ui)), in_dims=(0, 0))(x, u)
    torch.testing.assert_close(dyn.jacobian(x, u), auto, rtol=0, atol=1e-8)


def test_strapdown_keeps_the_quaternion_normalised_and_agrees_with_the_planar_model() -> None:
    gen = torch.Generator().manual_seed(2)
    dyn = GnssImuDynamics(dtype=F64)
    x = torch.randn(6, 16, generator=gen, dtype=F64)
    out = dyn(x, _controls(gen, 6, planar=False))
    torch.testing.assert_close(out[:, 6:10].norm(dim=-1), torch.ones(6, dtype=F64))
    torch.testing.assert_close(out[:, 10:], x[:, 10:])
    # sigma-point layout [B, S, n] with controls [B, 1, k]
    xs = torch.randn(6, 5, 16, generator=gen, dtype=F64)
    u = _controls(gen, 6, planar=False)
    batched = dyn(xs, {k: v[:, None] for k, v in u.items()})
    loop = torch.stack([dyn(xs[:, j], u) for j in range(5)], 1)
    torch.testing.assert_close(batched, loop)
    # a level vehicle: the 3-D and planar models give the same horizontal motion
    psi = torch.tensor([0.3, -2.0], dtype=F64)
    yaw = 0.5 * (math.pi / 2 - psi)
    x3 = torch.zeros(2, 16, dtype=F64)
    x3[:, 0:2] = torch.tensor([[1.0, 2.0], [-3.0, 4.0]], dtype=F64)
    x3[:, 3:5] = torch.tensor([[5.0, 1.0], [0.0, -7.0]], dtype=F64)
    x3[:, 6], x3[:, 9] = torch.cos(yaw), torch.sin(yaw)
    x3[:, 10:12] = 0.01
    x3[:, 15] = 0.002
    x2 = torch.cat([x3[:, 0:2], x3[:, 3:5], psi[:, None], x3[:, 10:12], x3[:, 15:16]], -1)
    f2, w = torch.tensor([[0.5, -1.0], [2.0, 0.3]], dtype=F64), torch.tensor([[0.1], [-0.05]], dtype=F64)
    u3 = {"accel": torch.cat([f2, torch.full((2, 1), GRAVITY, dtype=F64)], -1), "gyro": torch.cat([torch.zeros(2, 2, dtype=F64), w], -1)}
    o3, o2 = dyn(x3, u3), PlanarGnssImuDynamics(dtype=F64)(x2, {"accel": f2, "gyro": w})
    torch.testing.assert_close(o3[:, 0:2], o2[:, 0:2])
    torch.testing.assert_close(o3[:, 3:5], o2[:, 2:4])
    torch.testing.assert_close(o3[:, [2, 5]], torch.zeros(2, 2, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(GnssMeasurement(heading=True, dtype=F64)(o3)[:, 3], o2[:, 4])
    # the rotation increment is smooth at zero angular rate
    x0 = x3[:1].clone().requires_grad_(True)
    still = {"accel": u3["accel"][:1], "gyro": torch.zeros(1, 3, dtype=F64)}
    still["gyro"][0, 2] = 0.002  # = b_g: zero net rotation
    dyn(x0, still).sum().backward()
    assert bool(torch.isfinite(x0.grad).all())


@pytest.mark.parametrize("planar", [True, False])
def test_noise_free_imu_reproduces_the_truth(planar: bool) -> None:
    data = simulate_p004(batch_size=2, seed=3, planar=planar, randomize=True, dtype=F64, **NOISE_FREE)
    model = data.make_model()
    prev = torch.cat([data.initial_state[:, None], data.truth[:, :-1]], 1)
    pred = model.f(prev, data.controls)
    err = pred - data.truth
    d = 2 if planar else 3
    assert float(err[..., d : 2 * d].abs().max()) < 1e-9  # velocity: exact
    # position: the 1 s trapezoid misses T^3/12 d^2v/dt^2 (turn onsets, speed changes)
    pos = err[..., :d].norm(dim=-1)
    assert float(pos.pow(2).mean().sqrt()) < 0.025 and float(pos.max()) < 0.15
    att = slice(4, 5) if planar else slice(6, 10)
    assert float(err[..., att].abs().max()) < 1e-9


def test_process_noise_matches_one_step_prediction_errors() -> None:
    data = simulate_p004(batch_size=8, seed=4, planar=True, dtype=F64)
    model = data.make_model()
    prev = torch.cat([data.initial_state[:, None], data.truth[:, :-1]], 1)
    err = (model.f(prev, data.controls) - data.truth).reshape(-1, 8)[:, :5]
    q = model.dynamics.Q.detach()[:5, :5]
    n = err.shape[0]
    ratio = err.std(0) / q.diagonal().sqrt()
    # velocity and heading: exactly the simulated IMU noise (3200 samples); position: the
    # sample-mean noise var T^4/4 plus the trapezoid step's own 1 cm (sigma_position_step)
    assert bool(((ratio - 1).abs() < 5 / math.sqrt(2 * n)).all()), ratio
    torch.testing.assert_close(q[0, 0], torch.tensor(0.1**2 / 4 + 0.01**2, dtype=F64))
    torch.testing.assert_close(q[0, 2], torch.tensor(0.1**2 / 2, dtype=F64))
    corr = (err[:, 0] * err[:, 2]).mean() / q[0, 2]
    assert abs(float(corr) - 1) < 6 / math.sqrt(n)
    qq = model.dynamics.Q
    assert bool(torch.linalg.cholesky_ex(qq)[1] == 0)
    q3 = GnssImuModel(dtype=F64).dynamics.Q
    assert q3.shape == (16, 16) and bool(torch.linalg.cholesky_ex(q3)[1] == 0)
    with pytest.raises(ValueError, match="sigma_position_step"):
        GnssImuModel(planar=True, sigma_position_step=0.0)


# ---------------------------------------------------------------------------------- measurements
def test_gnss_measurement_layout_and_heading_residual() -> None:
    m = GnssMeasurement(planar=True, velocity=True, heading=True, dtype=F64)
    assert m.measurement_dim == 5
    x = torch.arange(8, dtype=F64)
    torch.testing.assert_close(m(x), x[[0, 1, 2, 3, 4]])
    torch.testing.assert_close(m.matrix() @ x, m(x))
    r = m.residual(torch.tensor([0, 0, 0, 0, 3.1], dtype=F64), torch.tensor([0, 0, 0, 0, -3.1], dtype=F64))
    torch.testing.assert_close(r[-1], torch.tensor(6.2 - 2 * math.pi, dtype=F64))
    m3 = GnssMeasurement(heading=True, dtype=F64)
    assert m3.matrix() is None and m3.measurement_dim == 4
    q = _unit(torch.randn(4, 4, generator=torch.Generator().manual_seed(5), dtype=F64))
    x3 = torch.zeros(4, 16, dtype=F64)
    x3[:, 6:10] = q
    fwd = quaternion_to_rotation(q)[:, :, 0]
    torch.testing.assert_close(m3(x3)[:, 3], torch.atan2(fwd[:, 0], fwd[:, 1]))
    torch.testing.assert_close(m3(x3 * torch.cat([torch.ones(6), 2 * torch.ones(4), torch.ones(6)]).to(F64))[:, 3], m3(x3)[:, 3])
    r = torch.diag(torch.tensor([0.01, 0.01, 0.01, math.radians(1) ** 2], dtype=F64))
    torch.testing.assert_close(m3.R, r)


def test_switching_statistics() -> None:
    accel = torch.tensor([[3.0, 4.0, GRAVITY], [0.0, 0.0, GRAVITY]], dtype=F64)
    gyro = torch.tensor([[0.0, 0.0, math.pi / 2], [0.0, 0.0, 0.0]], dtype=F64)
    gamma, mu = p004_switching_statistics(accel, gyro, 0.1, 0.2, 0.3, 0.05, gravity=GRAVITY)
    torch.testing.assert_close(mu, torch.tensor([math.sqrt(25 / 9.8**2 + 0.25), 0.0], dtype=F64))
    torch.testing.assert_close(gamma, torch.tensor(0.2 / 0.3, dtype=F64))
    _, mu_raw = p004_switching_statistics(accel, gyro, 0.1, 0.2, 0.3, 0.05)
    assert float(mu_raw[1]) == pytest.approx(GRAVITY / 9.8)
    g, _ = p004_switching_statistics(accel, gyro, torch.tensor([0.1, 0.5], dtype=F64), 0.2, 0.3, torch.tensor([0.05, 1.0], dtype=F64))
    torch.testing.assert_close(g, torch.tensor([0.2 / 0.3, 0.5], dtype=F64))
    data = simulate_p004(batch_size=2, seed=0, planar=True, dtype=F64)
    gamma, mu = data.switching_statistics()
    assert mu.shape == (2, 400) and float(mu.max()) < 1.0
    assert float(mu[:, 130:170].mean()) > 3 * float(mu[:, 5:25].mean())  # the 120-180 s loop vs the straight


# ---------------------------------------------------------------------------------- simulator
@pytest.mark.parametrize("randomize", [False, True])
def test_drive_meets_the_papers_boundary_conditions(randomize: bool) -> None:
    data = simulate_p004(batch_size=3, seed=9, randomize=randomize, planar=True, dtype=F64, **NOISE_FREE)
    assert data.truth.shape == (3, 400, 8) and data.controls["accel"].shape == (3, 400, 2)
    torch.testing.assert_close(data.truth[:, -1, :2], torch.tensor([[900.0, 0.0]] * 3, dtype=F64), atol=1e-6, rtol=0)
    torch.testing.assert_close(data.initial_state[:, :5], torch.tensor([[0.0, 0.0, 0.0, 10.0, 0.0]] * 3, dtype=F64))
    torch.testing.assert_close(data.controls["accel"][:, 0], torch.tensor([[2.0, 0.0]] * 3, dtype=F64), atol=1e-9, rtol=0)
    assert float(data.controls["gyro"][:, :20].abs().max()) < 1e-12  # initial turn rate 0
    speed = data.truth[..., 2:4].norm(dim=-1)
    assert float(speed.min()) > 2.9 and float(speed.max()) < 25.1
    if not randomize:
        assert float((data.truth[0] - data.truth[1]).abs().max()) == 0.0
        assert P004_SPEED_KNOTS[-1][0] == 400.0
    else:
        assert float((data.truth[0] - data.truth[1]).abs().max()) > 10.0


def test_simulator_determinism_dtype_and_3d_layout() -> None:
    a = simulate_p004(batch_size=2, seed=1, randomize=True, dtype=F64)
    b = simulate_p004(batch_size=2, seed=1, randomize=True, dtype=F64)
    torch.testing.assert_close(a.measurements, b.measurements)
    torch.testing.assert_close(a.controls["gyro"], b.controls["gyro"])
    f = simulate_p004(batch_size=2, seed=1, randomize=True, dtype=torch.float32)
    assert f.truth.dtype == torch.float32 and f.controls["accel"].dtype == torch.float32
    assert a.truth.shape == (2, 400, 16) and a.measurements.shape == (2, 400, 3)
    torch.testing.assert_close(a.truth[..., 6:10].norm(dim=-1), torch.ones(2, 400, dtype=F64))
    torch.testing.assert_close(
        GnssMeasurement(heading=True, dtype=F64)(a.truth)[..., 3], torch.remainder(a.heading + math.pi, 2 * math.pi) - math.pi
    )


def test_sensor_noise_statistics() -> None:
    kw = {"batch_size": 8, "seed": 12, "randomize": True, "velocity": True, "heading": True, "dtype": F64}
    noisy, clean = simulate_p004(**kw), simulate_p004(**kw, **NOISE_FREE)
    p = noisy.params
    n = 8 * 400
    resid = noisy.measurements - GnssMeasurement(velocity=True, heading=True, dtype=F64)(noisy.truth)
    resid[..., 6] = torch.remainder(resid[..., 6] + math.pi, 2 * math.pi) - math.pi
    std = resid.reshape(n, 7).std(0) / torch.tensor(
        [p["sigma_gnss"]] * 3 + [p["sigma_gnss_velocity"]] * 3 + [p["sigma_heading"]], dtype=F64
    )
    assert bool(((std - 1).abs() < 4 / math.sqrt(2 * n)).all()), std
    # IMU: noisy - clean = constant bias + white noise
    for key, sig in (("accel", p["sigma_accel"]), ("gyro", p["sigma_gyro"])):
        e = noisy.controls[key] - clean.controls[key]
        e = e - e.mean(1, keepdim=True)  # remove the per-trajectory bias
        ratio = e.reshape(-1, 3).std(0) / (sig * math.sqrt(1 - 1 / 400))
        assert bool(((ratio - 1).abs() < 4 / math.sqrt(2 * n)).all()), (key, ratio)
    assert float(clean.truth[..., 10:].abs().max()) == 0.0
    bias_a = noisy.truth[:, 0, 10:13] / p["sigma_accel_bias"]
    assert 0.0 < float(bias_a.abs().max()) < 5.0  # 24 draws of N(0, 1)
    outage = simulate_p004(batch_size=1, seed=0, planar=True, gnss_outages=[(100.0, 130.0)], dtype=F64)
    assert int((~outage.mask[0, :, 0]).sum()) == 30 and not bool(outage.mask[0, 99:129].any())


# ---------------------------------------------------------------------------------- filters
def _track(filt: torch.nn.Module, data: object) -> tuple[torch.Tensor, torch.Tensor]:
    """Horizontal position error ``[B, T]`` and its NEES under the filter's own covariance."""
    with torch.no_grad():
        res = filt(data.measurements, *data.initial_belief(), mask=data.mask, controls=data.controls)
    assert bool(torch.isfinite(res.mean).all()) and bool(torch.isfinite(res.cov).all())
    e = res.mean[..., :2] - data.position
    nees = (e[..., None, :] @ torch.linalg.solve(res.cov[..., :2, :2], e[..., None]))[..., 0, 0]
    return e.norm(dim=-1), nees


@pytest.mark.parametrize("randomize", [False, True])
def test_planar_filters_track_the_full_400_s(randomize: bool) -> None:
    data = simulate_p004(batch_size=3, seed=21, randomize=randomize, planar=True, gnss_outages=[(200.0, 215.0)], dtype=F64)
    model = data.make_model()
    ok = data.mask[..., 0]
    gnss = (data.measurements[..., :2] - data.position).norm(dim=-1)[ok]
    for filt in (UKF(model, sigma_points=MerweScaled(alpha=0.1)), EKF(model)):
        err, nees = _track(filt, data)
        assert float(err[ok].pow(2).mean().sqrt()) < float(gnss.pow(2).mean().sqrt())  # better than raw GNSS
        # consistent (2 degrees of freedom, 1200 samples), also through the 15 s outage where the
        # error grows to metres, and back to GNSS level after it
        assert 1.0 < float(nees.mean()) < 3.0 and float(nees.max()) < 30.0
        assert float(err[:, 250:].max()) < 0.6


def test_full_state_ukf_tracks_the_full_400_s() -> None:
    data = simulate_p004(batch_size=2, seed=22, planar=False, dtype=F64)
    err, nees = _track(UKF(data.make_model(), sigma_points=MerweScaled(alpha=0.1)), data)
    gnss = (data.measurements[..., :2] - data.position).norm(dim=-1)
    assert float(err.pow(2).mean().sqrt()) < float(gnss.pow(2).mean().sqrt())
    assert float(err.max()) < 0.6 and 1.0 < float(nees.mean()) < 3.0


@pytest.mark.parametrize("planar", [True, False])
def test_float32_filtering_matches_float64(planar: bool) -> None:
    data = simulate_p004(batch_size=2, seed=23, planar=planar, dtype=F64)
    mean, cov = data.initial_belief()
    out = {}
    for dtype in (torch.float32, F64):
        filt = UKF(data.make_model(dtype=dtype), sigma_points=MerweScaled(alpha=0.1))
        controls = {k: v[:, :100].to(dtype) for k, v in data.controls.items()}
        with torch.no_grad():
            res = filt(data.measurements[:, :100].to(dtype), mean.to(dtype), cov.to(dtype), controls=controls)
        out[dtype] = res.mean
    assert out[torch.float32].dtype == torch.float32
    assert float((out[torch.float32].double() - out[F64])[..., :2].abs().max()) < 0.01  # against 0.1 m GNSS


@pytest.mark.slow
def test_full_state_ekf_tracks_the_full_400_s() -> None:
    data = simulate_p004(batch_size=2, seed=22, planar=False, velocity=True, heading=True, dtype=F64)
    err, nees = _track(EKF(data.make_model()), data)
    assert float(err.pow(2).mean().sqrt()) < 0.15 and float(err.max()) < 0.6 and 1.0 < float(nees.mean()) < 3.0
