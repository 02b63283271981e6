"""Tests of the p002 PDR model, the p002 track and the GPS+PDR outage simulator."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF, MerweScaled
from experiments.papers.p002 import (
    BLOCKAGE_PROBS,
    gps_only_positions,
    pdr_only_positions,
    position_rmse,
    simulate_p002,
    simulate_p002_random,
)
from experiments.papers.p002.model import PDRMeasurement, PDRModel, PDRStepDynamics, wrap_angle, wrap_measurement
from experiments.papers.p002.track import p002_track

F64 = torch.float64


def _random_state(gen: torch.Generator, *shape: int) -> torch.Tensor:
    x = torch.randn(*shape, 4, generator=gen, dtype=F64)
    x[..., 2] = 0.6 + 0.2 * torch.rand(shape, generator=gen, dtype=F64)
    x[..., 3] = 4.0 * x[..., 3]
    return x


# ---------------------------------------------------------------------------------- model
def test_wrap_angle_range_and_congruence() -> None:
    a = torch.linspace(-20.0, 20.0, 4001, dtype=F64)
    w = wrap_angle(a)
    assert bool(((w > -math.pi) & (w <= math.pi)).all())
    k = (a - w) / (2 * math.pi)
    torch.testing.assert_close(k, k.round(), atol=1e-9, rtol=0)
    edge = torch.tensor([math.pi, -math.pi, 3 * math.pi], dtype=F64)
    torch.testing.assert_close(wrap_angle(edge), torch.full((3,), math.pi, dtype=F64))


def test_wrap_measurement_moves_only_the_heading() -> None:
    z_pred = torch.tensor([[10.0, -5.0, 3.0], [1.0, 2.0, -3.1]], dtype=F64)
    delta = torch.tensor([0.3, -0.2], dtype=F64)
    z = z_pred.clone()
    z[:, 0] += 7.0
    z[:, 2] = z_pred[:, 2] + delta + torch.tensor([4.0, -6.0], dtype=F64) * math.pi
    out = PDRMeasurement(dtype=F64).wrap_measurement(z, z_pred)
    torch.testing.assert_close(out[:, :2], z[:, :2])
    torch.testing.assert_close(out[:, 2] - z_pred[:, 2], delta)
    torch.testing.assert_close(wrap_measurement(z, z_pred, ()), z)


def test_heading_convention_is_clockwise_azimuth() -> None:
    dyn = PDRStepDynamics(dtype=F64)
    x = torch.tensor([[0.0, 0.0, 0.7, 0.0], [0.0, 0.0, 0.7, math.pi / 2]], dtype=F64)
    out = dyn(x, {"dtheta": torch.tensor([[0.1], [-0.2]], dtype=F64)})
    expected = torch.tensor([[0.0, 0.7, 0.7, 0.1], [0.7, 0.0, 0.7, math.pi / 2 - 0.2]], dtype=F64)
    torch.testing.assert_close(out, expected)


@pytest.mark.parametrize("controls", ["dict", "tensor", "none"])
def test_jacobians_match_autograd(controls: str) -> None:
    gen = torch.Generator().manual_seed(3)
    model = PDRModel(dtype=F64)
    x = _random_state(gen, 7)
    d = torch.randn(7, 1, generator=gen, dtype=F64)
    u = {"dtheta": d} if controls == "dict" else (d if controls == "tensor" else None)
    jf = model.dynamics.jacobian(x, u)
    jh = model.measurement.jacobian(x, u)
    for i in range(7):
        ui = None if u is None else ({"dtheta": d[i]} if isinstance(u, dict) else d[i])
        ref_f = torch.autograd.functional.jacobian(lambda xi: model.dynamics(xi, ui), x[i])  # noqa: B023
        ref_h = torch.autograd.functional.jacobian(lambda xi: model.measurement(xi, ui), x[i])  # noqa: B023
        torch.testing.assert_close(jf[i], ref_f, atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(jh[i], ref_h, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(model.measurement.matrix(), jh[0])


def test_model_broadcasting_and_vmap() -> None:
    gen = torch.Generator().manual_seed(4)
    dyn = PDRStepDynamics(dtype=F64)
    x = _random_state(gen, 3, 9)
    d = torch.randn(3, 1, 1, generator=gen, dtype=F64)
    out = dyn(x, {"dtheta": d})
    assert out.shape == (3, 9, 4)
    assert dyn.jacobian(x, {"dtheta": d}).shape == (3, 9, 4, 4)
    loop = torch.stack([dyn(x[:, j], {"dtheta": d[:, 0]}) for j in range(9)], 1)
    torch.testing.assert_close(out, loop)
    vm = torch.func.vmap(lambda xi, di: dyn(xi, {"dtheta": di}))(x[:, 0], d[:, 0])
    torch.testing.assert_close(vm, out[:, 0])
    assert PDRMeasurement(dtype=F64)(x).shape == (3, 9, 3)


def test_model_defaults_learnable_and_dtypes() -> None:
    for dtype in (torch.float32, F64):
        model = PDRModel(dtype=dtype)
        assert model.Q.dtype == dtype and model.R.dtype == dtype
        assert model.Q.shape == (4, 4) and model.R.shape == (3, 3)
        assert model.angular_components == (2,)
    model = PDRModel(dtype=F64)
    model.R = torch.diag(torch.tensor([4.0, 9.0, 0.01], dtype=F64))
    torch.testing.assert_close(torch.diagonal(model.R), torch.tensor([4.0, 9.0, 0.01], dtype=F64))
    assert {n for n, p in model.named_parameters() if p.requires_grad} == {
        "dynamics.parametrizations.Q.original",
        "measurement.parametrizations.R.original",
    }
    with pytest.raises(ValueError):
        PDRModel(Q=torch.eye(3, dtype=F64))


# ---------------------------------------------------------------------------------- track
def test_track_geometry() -> None:
    track = p002_track()
    s = torch.linspace(0.0, track.length, 360_001, dtype=F64)
    e, n, psi = track.sample(s)
    steps = torch.sqrt(e.diff() ** 2 + n.diff() ** 2)
    assert abs(float(steps.sum()) - 360.0) <= 1.0
    assert float(steps.max()) <= 1.0001e-3  # continuous: no position jump
    nodes = {k: torch.tensor(v, dtype=F64) for k, v in track.nodes().items()}
    assert abs(float((nodes["B"] - nodes["A"]).norm()) - 110.0) < 1e-9
    assert abs(float((nodes["C"] - nodes["B"]).norm()) - 70.0) < 1e-9
    # Right-angle turns at A, B, C, D: the heading jumps by pi/2 at each node.
    starts = torch.tensor([0.0, 45.5, 155.5, 225.5, 270.0], dtype=F64)
    _, _, before = track.sample((starts[1:] - 1e-9).clamp_min(0))
    _, _, after = track.sample(starts[1:])
    torch.testing.assert_close(after - before, torch.full((4,), math.pi / 2, dtype=F64), atol=1e-6, rtol=0)
    # The last 90 m is an arc of radius 37 m around D + (-37, 0).
    sa = torch.linspace(270.0, 360.0, 101, dtype=F64)
    ea, na, _ = track.sample(sa)
    center = nodes["D"] + torch.tensor([-37.0, 0.0], dtype=F64)
    radius = torch.sqrt((ea - center[0]) ** 2 + (na - center[1]) ** 2)
    torch.testing.assert_close(radius, torch.full_like(radius, 37.0))
    e_end, n_end, _ = track.end
    assert math.hypot(e_end, n_end) < 1.0  # nearly closes at the start S
    # Beyond the end the track continues straight.
    e2, n2, p2 = track.sample(torch.tensor([361.0, 362.0], dtype=F64))
    assert abs(math.hypot(float(e2[1] - e2[0]), float(n2[1] - n2[0])) - 1.0) < 1e-9 and float(p2[0] - p2[1]) == 0.0


# ---------------------------------------------------------------------------------- simulator
def test_simulator_shapes_and_truth_consistency() -> None:
    sc = simulate_p002(4, blockage_prob=0.4, seed=0)
    B, T = 4, 514
    assert sc.truth.shape == (B, T, 4) and sc.measurements.shape == (B, T, 3) and sc.mask.shape == (B, T, 3)
    assert sc.mask.dtype == torch.bool and bool(sc.mask[..., 2].all())
    assert bool(torch.equal(sc.mask[..., 0], sc.mask[..., 1]))
    assert bool(torch.isnan(sc.measurements[..., 0][~sc.mask[..., 0]]).all())
    assert bool(torch.isfinite(sc.measurements[sc.mask]).all())
    assert all(v.shape == (B, T, 1) for v in sc.controls.values())
    L = sc.truth[..., 2]
    assert bool(((L >= 0.6) & (L <= 0.8)).all())
    # The step from event k to k+1 has length L_k (exactly on straight stretches).
    pos = torch.cat([sc.initial_state[:, None, :2], sc.truth[..., :2]], 1)
    chord = (pos.diff(dim=1)).norm(dim=-1)
    prev_len = torch.cat([sc.initial_state[:, None, 2], L[:, :-1]], 1)
    assert bool((chord <= prev_len + 1e-9).all())
    assert float(((chord - prev_len).abs() < 1e-9).double().mean()) > 0.6
    # Cadence ~1.8 steps/s; the walk covers the 360 m path.
    assert abs(1.0 / float(sc.controls["dt"].mean()) - 1.8) < 0.02
    walked = sc.initial_state[:, 2] + L[:, :-1].sum(1)
    assert bool(((walked - 360.0).abs() < 10.0).all())


def test_determinism_and_dtypes() -> None:
    a = simulate_p002(3, seed=11)
    b = simulate_p002(3, seed=torch.Generator().manual_seed(11))
    c = simulate_p002(3, seed=12)
    for x, y in ((a.truth, b.truth), (a.measurements, b.measurements), (a.controls["dtheta"], b.controls["dtheta"])):
        assert torch.equal(torch.nan_to_num(x), torch.nan_to_num(y))
    assert torch.equal(a.mask, b.mask)
    assert not torch.equal(a.truth, c.truth)
    f32 = simulate_p002(3, seed=11, dtype=torch.float32)
    assert f32.truth.dtype == torch.float32 and f32.measurements.dtype == torch.float32
    assert f32.initial_cov.dtype == torch.float32 and f32.controls["dtheta"].dtype == torch.float32
    torch.testing.assert_close(f32.truth, a.truth.float())
    assert torch.equal(f32.mask, a.mask)
    r1, r2 = simulate_p002_random(5, seed=2), simulate_p002_random(5, seed=2)
    assert torch.equal(r1.truth, r2.truth) and torch.equal(r1.mask, r2.mask)


@pytest.mark.parametrize("p", [0.2, 0.8])
def test_blockage_fraction_matches_probability(p: float) -> None:
    sc = simulate_p002(64, blockage_prob=p, seed=5)
    # Fraction of 5 s windows blocked, estimated per window: one sample per window start.
    t = sc.times
    window = torch.floor(t / 5.0).long()
    first = torch.cat([torch.ones_like(window[:, :1], dtype=torch.bool), window.diff(dim=1) != 0], 1)
    frac = float(sc.blocked[first].double().mean())
    n = int(first.sum())
    assert abs(frac - p) < 4.0 * math.sqrt(p * (1 - p) / n)
    # Fixes are lost only in blocked windows: delivered fixes ~ (1 - P) x fix epochs.
    epochs = torch.floor(t[:, -1] - 5.0) + 1.0
    delivered = sc.mask[..., 0].sum(1).double()
    ratio = float(delivered.sum() / epochs.sum())
    windows_with_fixes = float(epochs.sum()) / 5.0
    assert abs(ratio - (1 - p)) < 4.0 * math.sqrt(p * (1 - p) / windows_with_fixes)


def test_gps_schedule_without_and_with_full_blockage() -> None:
    sc = simulate_p002(8, blockage_prob=0.0, seed=9, cold_start_delay=6.0)
    gps = sc.mask[..., 0]
    expected = torch.floor(sc.times[:, -1] - 6.0) + 1.0
    torch.testing.assert_close(gps.sum(1).double(), expected)
    assert not bool(gps[sc.times < 6.0].any())
    full = simulate_p002(4, blockage_prob=1.0, seed=9)
    assert not bool(full.mask[..., :2].any()) and bool(full.blocked.all())


def test_sensor_noise_statistics() -> None:
    sc = simulate_p002(16, blockage_prob=0.05, seed=21)
    ok = sc.mask[..., 0]
    res = (sc.measurements[..., :2] - sc.truth[..., :2])[ok].flatten()
    n = res.numel()
    assert abs(float(res.mean())) < 4.0 * 2.67 / math.sqrt(n)
    assert abs(float(res.std()) / 2.67 - 1.0) < 4.0 / math.sqrt(2 * n)
    # Compass RMSE 11.4 deg (correlated error: tolerance from the ~10 s correlation time).
    big = simulate_p002(64, blockage_prob=0.2, seed=22)
    err = big.measurements[..., 2] - big.truth[..., 3]
    assert abs(math.degrees(float(err.pow(2).mean().sqrt())) / 11.4 - 1.0) < 0.03
    torch.testing.assert_close(wrap_angle(big.compass_raw - big.truth[..., 3]), err)
    # Gyro: increments = true heading change + bias dt + angle random walk 0.5 deg/sqrt(s).
    psi = torch.cat([big.initial_state[:, None, 3], big.truth[..., 3]], 1)
    dt = big.controls["dt"][..., 0]
    noise = (big.controls["dtheta"][..., 0] - psi.diff(dim=1) - big.gyro_bias[:, None] * dt) / dt.sqrt()
    assert abs(math.degrees(float(noise.std())) / 0.5 - 1.0) < 4.0 / math.sqrt(2 * noise.numel())
    bias = big.gyro_bias.abs() * 3600 * 180 / math.pi
    assert bool(((bias >= 40.0) & (bias <= 80.0)).all())


def test_compass_interference_segment() -> None:
    sc = simulate_p002(32, seed=23, interference=(100.0, 200.0))
    arc = sc.initial_state[:, None, 2] + torch.cat([torch.zeros(32, 1, dtype=F64), sc.truth[:, :-1, 2].cumsum(1)], 1)
    err = sc.measurements[..., 2] - sc.truth[..., 3]
    inside = (arc >= 100.0) & (arc < 200.0)
    rmse_in = math.degrees(float(err[inside].pow(2).mean().sqrt()))
    rmse_out = math.degrees(float(err[~inside].pow(2).mean().sqrt()))
    assert abs(rmse_in / 49.7 - 1.0) < 0.1
    assert abs(rmse_out / 11.4 - 1.0) < 0.05


def test_randomised_variant() -> None:
    sc = simulate_p002_random(32, seed=1)
    assert sc.truth.shape == (32, 514, 4)
    assert set(sc.blockage_prob.tolist()) <= set(BLOCKAGE_PROBS) and len(set(sc.blockage_prob.tolist())) > 1
    assert float(sc.initial_state[:, 3].std()) > 1.0  # random start headings
    L = sc.truth[..., 2]
    assert bool(((L >= 0.55 - 1e-12) & (L <= 0.85 + 1e-12)).all())
    bias = sc.gyro_bias.abs() * 3600 * 180 / math.pi
    assert bool(((bias >= 40.0) & (bias <= 100.0)).all())
    err = sc.measurements[..., 2] - sc.truth[..., 3]
    assert float(err.abs().max()) < math.pi  # compass unwrapped next to the truth


# ---------------------------------------------------------------------------------- baselines
def test_gps_only_holds_last_fix() -> None:
    sc = simulate_p002(3, blockage_prob=0.6, seed=4)
    est = gps_only_positions(sc)
    ok = sc.mask[..., 0]
    for b in range(3):
        last = sc.initial_mean[b, :2]
        for t in range(sc.truth.shape[1]):
            if ok[b, t]:
                last = sc.measurements[b, t, :2]
            torch.testing.assert_close(est[b, t], last)


def test_pdr_only_with_perfect_sensors() -> None:
    sc = simulate_p002(
        4, seed=8, gyro_bias_deg_per_h=(0.0, 0.0), gyro_arw=0.0, compass_std=0.0, compass_correlated_std=0.0,
        step_scale_std=0.0, step_noise_std=0.0, initial_position_std=0.0, initial_heading_std=0.0,
    )  # fmt: skip
    pos, psi = pdr_only_positions(sc)
    torch.testing.assert_close(psi, sc.truth[..., 3], atol=1e-9, rtol=0)
    # Only the corner and arc discretisation (the step uses the heading at its start) remains.
    assert float(position_rmse(pos, sc.truth).max()) < 3.0
    noisy = simulate_p002(4, seed=8)
    assert float(position_rmse(pdr_only_positions(noisy)[0], noisy.truth).mean()) > float(position_rmse(pos, sc.truth).mean())


# ---------------------------------------------------------------------------------- filters
def _ukf(model: PDRModel) -> UKF:
    return UKF(model, sigma_points=MerweScaled(alpha=0.5, beta=2.0, kappa=0.0))


def test_ukf_tracks_p002_at_p02() -> None:
    sc = simulate_p002(8, blockage_prob=0.2, seed=31)
    with torch.no_grad():
        res = _ukf(sc.make_model())(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    ukf_rmse = position_rmse(res.mean, sc.truth)
    gps_rmse = position_rmse(gps_only_positions(sc), sc.truth)
    pdr_rmse = position_rmse(pdr_only_positions(sc)[0], sc.truth)
    assert float(ukf_rmse.max()) < 3.5
    assert float(ukf_rmse.mean()) < min(float(gps_rmse.mean()), float(pdr_rmse.mean()))
    assert float((res.mean[..., :2] - sc.truth[..., :2]).norm(dim=-1).max()) < 12.0
    heading_err = math.degrees(float((res.mean[..., 3] - sc.truth[..., 3]).pow(2).mean().sqrt()))
    assert heading_err < 11.4  # better than the compass alone
    assert bool(torch.isfinite(res.log_likelihood).all())


def test_ukf_batch_equals_loop_and_ekf_agrees() -> None:
    sc = simulate_p002(3, blockage_prob=0.4, seed=32, num_steps=60)
    model = sc.make_model()
    ukf = _ukf(model)
    with torch.no_grad():
        res = ukf(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
        for b in range(3):
            one = ukf(
                sc.measurements[b : b + 1], sc.initial_mean[b], sc.initial_cov, mask=sc.mask[b : b + 1],
                controls={k: v[b : b + 1] for k, v in sc.controls.items()},
            )  # fmt: skip
            torch.testing.assert_close(one.mean[0], res.mean[b], atol=1e-10, rtol=1e-10)
        ekf = EKF(model)(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    assert float((ekf.mean - res.mean).abs()[..., :2].max()) < 0.5


def test_ukf_float32_matches_float64_and_gradients() -> None:
    sc64 = simulate_p002(2, blockage_prob=0.2, seed=33, num_steps=80)
    sc32 = simulate_p002(2, blockage_prob=0.2, seed=33, num_steps=80, dtype=torch.float32)
    r64 = _ukf(sc64.make_model())(sc64.measurements, sc64.initial_mean, sc64.initial_cov, mask=sc64.mask, controls=sc64.controls)
    r32 = _ukf(sc32.make_model())(sc32.measurements, sc32.initial_mean, sc32.initial_cov, mask=sc32.mask, controls=sc32.controls)
    assert r32.mean.dtype == torch.float32
    torch.testing.assert_close(r32.mean.double(), r64.mean, atol=2e-3, rtol=1e-4)
    model = sc64.make_model()
    res = _ukf(model)(sc64.measurements, sc64.initial_mean, sc64.initial_cov, mask=sc64.mask, controls=sc64.controls)
    loss = (res.mean[..., :2] - sc64.truth[..., :2]).pow(2).mean() - res.log_likelihood.mean()
    loss.backward()
    for p in model.parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().sum()) > 0
