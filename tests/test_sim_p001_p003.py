"""Tests for the p001 (static, coloured noise) and p003 (flight, SINS errors) simulators and geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter import geometry as geo
from experiments.papers import constellation as sky
from experiments.papers.p001 import P001_CONFIG, make_p001_model, simulate_p001
from experiments.papers.p003 import PAPER_PHASES, flight_profile, make_p003_model, manoeuvre_flags, simulate_p003

F64 = torch.float64


# --- geometry -----------------------------------------------------------------------------------
def test_geodetic_round_trip_enu_and_stable_displacement() -> None:
    g = torch.Generator().manual_seed(0)
    llh = torch.stack(
        [
            (torch.rand(50, generator=g, dtype=F64) - 0.5) * 3.0,
            (torch.rand(50, generator=g, dtype=F64) - 0.5) * 6.0,
            torch.rand(50, generator=g, dtype=F64) * 1e4,
        ],
        -1,
    )
    xyz = geo.geodetic_to_ecef(llh)
    assert torch.allclose(geo.ecef_to_geodetic(xyz), llh, atol=1e-9)
    origin = xyz[0]
    assert torch.allclose(geo.enu_to_ecef(geo.ecef_to_enu(xyz, origin), origin), xyz, atol=1e-6)
    rot = geo.enu_rotation(llh[..., 0], llh[..., 1])
    assert torch.allclose(rot @ rot.mT, torch.eye(3, dtype=F64).expand(50, 3, 3), atol=1e-12)
    d = torch.randn(50, 3, generator=g, dtype=F64) * torch.tensor([1e-3, 1e-3, 500.0], dtype=F64)
    assert torch.allclose(geo.ecef_displacement(llh, d), xyz - geo.geodetic_to_ecef(llh - d), atol=1e-7)
    # float32 keeps relative precision for a 1 mm displacement (the direct difference cannot)
    tiny = torch.tensor([[1.6e-10, 0.0, 1e-3]], dtype=F64)
    ref = geo.ecef_displacement(llh[:1], tiny)
    got = geo.ecef_displacement(llh[:1].float(), tiny.float()).double()
    assert (got - ref).norm() < 1e-3 * ref.norm()
    jac = torch.autograd.functional.jacobian(geo.geodetic_to_ecef, llh[3])
    assert torch.allclose(geo.geodetic_jacobian(llh[3]), jac, rtol=1e-10, atol=1e-8)


def test_constellation_orbits_and_azimuth_elevation() -> None:
    con = sky.CircularOrbitConstellation()
    t = torch.tensor([0.0, 600.0], dtype=F64)
    pos, vel = con.state(t)
    assert pos.shape == (2, 24, 3)
    assert torch.allclose(pos.norm(dim=-1), torch.full((2, 24), sky.GPS_ORBIT_RADIUS, dtype=F64))
    h = 1e-2
    pos2, _ = con.state(t + h)
    assert torch.allclose((pos2 - pos) / h, vel, atol=1e-2)  # ECEF velocity = d/dt of ECEF position
    period = 2 * math.pi / con.mean_motion
    assert period / 3600 == pytest.approx(11.97, abs=0.02)
    rx = geo.geodetic_to_ecef(torch.tensor([0.5, 1.0, 0.0], dtype=F64))
    az, el = torch.tensor([0.2, 2.0, 4.0], dtype=F64), torch.tensor([0.3, 0.9, 1.4], dtype=F64)
    sats = sky.satellites_from_azimuth_elevation(rx, az, el)
    assert torch.allclose(sats.norm(dim=-1), torch.full((3,), sky.GPS_ORBIT_RADIUS, dtype=F64))
    az2, el2 = geo.azimuth_elevation(rx, sats)
    assert torch.allclose(torch.remainder(az2 - az + math.pi, 2 * math.pi), torch.full_like(az, math.pi), atol=1e-10)
    assert torch.allclose(el2, el, atol=1e-10)


# --- p001 -----------------------------------------------------------------------------------------
def test_p001_shapes_config_and_determinism() -> None:
    sc = simulate_p001(3, seed=11)
    k = len(P001_CONFIG["azimuth_deg"])
    assert sc.truth.shape == (3, 100, 8) and sc.measurements.shape == (3, 100, k) and sc.mask.all()
    assert sc.controls["sat_pos"].shape == (3, 100, k, 3) and sc.dt == 10.0
    assert torch.allclose(sc.initial_cov.diagonal(), torch.tensor([100.0] * 3 + [1.0] * 3 + [100.0, 1.0], dtype=F64))
    assert torch.allclose((sc.initial_mean - sc.initial_truth)[:, :3].norm(dim=-1), torch.full((3,), 10.0, dtype=F64))
    assert torch.equal(sc.truth[..., :6], torch.zeros(3, 100, 6, dtype=F64))  # static receiver
    again = simulate_p001(3, seed=11)
    assert torch.equal(again.measurements, sc.measurements)
    assert not torch.equal(simulate_p001(3, seed=12).measurements, sc.measurements)
    sc32 = simulate_p001(3, seed=11, dtype=torch.float32)
    assert sc32.measurements.dtype == torch.float32 and torch.allclose(sc32.measurements.double(), sc.measurements, atol=1e-4)
    # satellites at GPS radius, fixed geometry at the configured elevations
    sats = sc.controls["sat_pos"][0, 0] + sc.frame_origin[0]
    assert torch.allclose(sats.norm(dim=-1), torch.full((k,), sky.GPS_ORBIT_RADIUS, dtype=F64), rtol=1e-9)
    el = geo.azimuth_elevation(sc.frame_origin[0], sats)[1]
    assert torch.allclose(torch.rad2deg(el), torch.tensor(P001_CONFIG["elevation_deg"], dtype=F64), atol=1e-8)


def test_p001_measurements_are_model_plus_coloured_noise() -> None:
    sc = simulate_p001(2, seed=3)
    model = make_p001_model()
    pred = model.measurement(sc.truth, sc.controls)
    assert torch.allclose(sc.measurements - pred, sc.noise, atol=1e-6)
    absolute = simulate_p001(2, seed=3, reduced=False)
    pred_abs = make_p001_model(reduced=False).measurement(absolute.truth, absolute.controls)
    assert torch.allclose(absolute.measurements - pred_abs, absolute.noise, atol=1e-5)


def test_p001_noise_is_ar1_with_psi_0p7() -> None:
    sc = simulate_p001(400, seed=1)
    v = sc.noise
    n = v[:, :-1].numel()
    psi_hat = ((v[:, 1:] * v[:, :-1]).sum() / (v[:, :-1] ** 2).sum()).item()
    se = math.sqrt((1 - 0.49) / n)
    assert abs(psi_hat - 0.7) < 4 * se
    eta = v[:, 1:] - 0.7 * v[:, :-1]
    assert eta.var().item() == pytest.approx(9.0, rel=4 * math.sqrt(2 / eta.numel()))
    stationary = 9.0 / (1 - 0.49)  # v_1 drawn from the stationary law
    assert v[:, 0].var().item() == pytest.approx(stationary, rel=4 * math.sqrt(2 / v[:, 0].numel()))
    # lag-1 correlation across satellites is zero (independent channels)
    cross = (v[:, 1:, 0] * v[:, :-1, 1]).mean() / stationary
    assert abs(cross.item()) < 4 / math.sqrt(v[:, 1:, 0].numel())


def test_p001_randomised_variant() -> None:
    sc = simulate_p001(6, seed=2, randomize=True, random_psi=(0.3, 0.9), num_satellites=8)
    assert sc.measurements.shape == (6, 100, 8)
    assert bool(((sc.psi >= 0.3) & (sc.psi <= 0.9)).all()) and sc.psi.unique().numel() == 6
    sats = sc.controls["sat_pos"][:, 0] + sc.frame_origin[:, None]
    el = torch.rad2deg(geo.azimuth_elevation(sc.frame_origin, sats)[1])
    assert bool((el > 9.99).all() and (el < 85.01).all()) and bool((el.amax(-1) > 59.99).all())
    for b in range(6):
        v = sc.noise[b]
        psi_hat = (v[1:] * v[:-1]).sum() / (v[:-1] ** 2).sum()
        assert abs(psi_hat - sc.psi[b]) < 0.25  # 800 samples per element


# --- p003 -----------------------------------------------------------------------------------------
def test_p003_paper_phase_times() -> None:
    times = [(p[0], p[1]) for p in PAPER_PHASES]
    expected = [
        (0, 10),
        (10, 20),
        (20, 60),
        (60, 90),
        (90, 150),
        (150, 160),
        (160, 500),
        (500, 520),
        (520, 1000),
        (1000, 1020),
        (1020, 1200),
        (1200, 1220),
        (1220, 1500),
        (1500, 1515),
        (1515, 1800),
    ]
    assert times == expected
    t = np.arange(0, 1800.01, 0.5)
    prof = flight_profile(list(PAPER_PHASES), t, math.radians(135.0))
    at = lambda s: int(round(s * 2))  # noqa: E731
    assert prof["speed"][at(10)] == 0 and prof["speed"][at(20)] == pytest.approx(60.0)
    assert prof["speed"][at(160)] == pytest.approx(100.0) and prof["speed"][-1] == pytest.approx(100.0)
    assert math.degrees(prof["psi"][at(500)]) == pytest.approx(135.0) and math.degrees(prof["psi"][at(520)]) == pytest.approx(75.0)
    assert math.degrees(prof["psi"][-1]) == pytest.approx(135.0)
    climbing = prof["gamma"] != 0
    assert np.array_equal(climbing, manoeuvre_flags([p for p in PAPER_PHASES if p[2] == "climb"], t))
    assert prof["gamma"][at(75)] > 0 and prof["gamma"][at(1507.5)] < 0
    level = ~manoeuvre_flags(list(PAPER_PHASES), t)
    assert np.all(np.diff(prof["speed"])[level[1:] & level[:-1]] == 0)
    steps = manoeuvre_flags(list(PAPER_PHASES), np.arange(1, 1801) - 0.5)
    expected_steps = np.zeros(1800, dtype=bool)
    for a, b in [(10, 20), (60, 90), (150, 160), (500, 520), (1000, 1020), (1200, 1220), (1500, 1515)]:
        expected_steps[a:b] = True  # step k covers (k-1, k]
    assert np.array_equal(steps, expected_steps)


@pytest.fixture(scope="module")
def flight() -> object:
    return simulate_p003(2, seed=5, duration=120, imu_rate=5, position_in_metres=True)


def test_p003_outputs_and_truth_kinematics(flight) -> None:  # type: ignore[no-untyped-def]
    sc = flight
    assert sc.truth.shape == (2, 120, 20) and sc.measurements.shape == (2, 120, 16) and sc.mask.shape == (2, 120, 16)
    assert sc.manoeuvre[0, 10:20].all() and not sc.manoeuvre[0, 20:60].any() and sc.manoeuvre[0, 60:90].all()
    assert sc.nav_truth["vel"][0, 30].norm().item() == pytest.approx(60.0, rel=1e-6)
    assert sc.nav_truth["llh"][0, 99, 2] > 100.0 and sc.nav_truth["llh"][0, 55, 2].abs() < 1e-6
    heading = torch.rad2deg(torch.atan2(sc.nav_truth["vel"][0, 40, 0], sc.nav_truth["vel"][0, 40, 1]))
    assert heading.item() == pytest.approx(135.0, abs=1e-6)
    assert torch.allclose(sc.controls["sat_pos"].norm(dim=-1), torch.full((2, 120, 8), sky.GPS_ORBIT_RADIUS, dtype=F64))
    # the specific force the filter sees reflects the 0-10 s rest and 10-20 s acceleration
    f = sc.controls["f_n"][0]
    assert f[:9, 2].mean().item() == pytest.approx(9.79, abs=0.02)
    assert f[14].norm() > 10.0


def test_p003_error_free_ins_reproduces_truth_and_determinism() -> None:
    sc = simulate_p003(
        1, seed=3, duration=60, imu_rate=5, sensor_errors=False, initial_errors=False, measurement_noise=False, position_in_metres=True
    )
    assert sc.truth[..., :18].abs().max() < 1e-6
    a = simulate_p003(1, seed=9, duration=30, imu_rate=5)
    b = simulate_p003(1, seed=9, duration=30, imu_rate=5)
    assert torch.equal(a.truth, b.truth) and torch.equal(a.measurements, b.measurements)
    c = simulate_p003(1, seed=10, duration=30, imu_rate=5)
    assert not torch.equal(a.truth, c.truth)
    a32 = simulate_p003(1, seed=9, duration=30, imu_rate=5, dtype=torch.float32)
    assert a32.truth.dtype == torch.float32 and torch.allclose(a32.measurements.double(), a.measurements, rtol=1e-5, atol=1e-4)


def test_p003_initial_errors_and_noise_levels(flight) -> None:  # type: ignore[no-untyped-def]
    sc = simulate_p003(200, seed=1, duration=2, imu_rate=2, position_in_metres=True)
    sd = sc.initial_truth.std(0)
    expected = sc.initial_cov[0].diagonal().sqrt()
    tol = 4 * expected / math.sqrt(2 * 200)
    assert bool(((sd - expected).abs() < tol).all())
    # noise = measurement - model(truth): 10x larger in manoeuvres with the two-level "modes" family
    # at p003's sigma_R ratio (the paper-faithful default switches nothing: tests/test_p003_families.py)
    model = make_p003_model(position_in_metres=True)
    flight = simulate_p003(2, seed=5, duration=120, imu_rate=5, position_in_metres=True, noise="modes", config={"mode_gnss_scale": 10.0})
    res = flight.measurements - model.measurement(flight.truth, flight.controls)
    rate_res = res[..., 8:][flight.mask[..., 8:]].reshape(-1)
    man = flight.manoeuvre[..., None].expand(2, 120, 8)[flight.mask[..., 8:]].reshape(-1)
    level_sd, man_sd = rate_res[~man].std().item(), rate_res[man].std().item()
    assert level_sd == pytest.approx(0.05, rel=0.15) and man_sd == pytest.approx(0.5, rel=0.15)


def test_p003_ins_error_growth_is_plausible(flight) -> None:  # type: ignore[no-untyped-def]
    sc = simulate_p003(4, seed=2, duration=300, imu_rate=5, position_in_metres=True, profile="random")
    pos = sc.truth[..., :3].norm(dim=-1)
    # free inertial: 0.1 deg tilt gives g * 1.7e-3 = 0.017 m/s^2, i.e. ~g phi t^2 / 2 = 770 m at 300 s
    assert bool((pos[:, -1] > pos[:, 0]).all()) and bool((pos[:, -1] < 5000.0).all())
    tilt = sc.truth[:, :, 6:8].abs().amax(1)
    assert bool((tilt < math.radians(1.0)).all())
    for phases in sc.phases:
        assert phases[0][:3] == (0.0, 10.0, "static") and phases[-1][1] == pytest.approx(300.0)
        assert all(p[1] == pytest.approx(q[0]) for p, q in zip(phases[:-1], phases[1:], strict=True))
    speed = sc.nav_truth["vel"].norm(dim=-1)
    assert bool((speed[:, 30:] > 30.0).all()) and bool((speed < 210.0).all())


def test_p003_closed_loop_feedback_bounds_the_errors_and_stays_in_the_model_family() -> None:
    kw = {"duration": 300, "imu_rate": 5, "position_in_metres": True, "profile": "random"}
    closed = simulate_p003(2, seed=6, feedback="imm", **kw)
    open_loop = simulate_p003(2, seed=6, **kw)
    assert "feedback" in closed.controls and "feedback" not in open_loop.controls
    assert closed.controls["feedback"].shape == (2, 300, 20) and bool((closed.controls["feedback"][:, 0] == 0).all())
    assert bool((closed.controls["feedback"][..., 9:] == 0).all())  # sensor errors are not fed back
    # same initial errors and sensors; the open loop drifts hundreds of metres, the closed loop stays at the GNSS level
    torch.testing.assert_close(closed.initial_truth, open_loop.initial_truth)
    assert open_loop.truth[:, -1, :2].abs().max() > 200.0 and closed.truth[:, -60:, :3].abs().max() < 20.0
    # noise-free: the measurement model reproduces the closed-loop measurements and the linear model with
    # the feedback input x_k = Phi (x_{k-1} - c_{k-1}) the truth, one step at a time
    quiet = {"imu_noise": False, "measurement_noise": False}
    for metres in (True, False):
        sc = simulate_p003(1, seed=7, duration=100, imu_rate=5, position_in_metres=metres, feedback="imm", **quiet)
        model = make_p003_model(position_in_metres=metres)
        assert (model.measurement(sc.truth, sc.controls) - sc.measurements).abs().max() < 1e-6
        x = torch.cat([sc.initial_truth[:, None], sc.truth], 1)
        step = x[:, 1:] - model.dynamics(x[:, :-1], sc.controls)
        to_m = 1.0 if metres else 6.37e6
        assert (step[..., :2] * to_m).abs().max() < 2e-3 and step[..., 2].abs().max() < 2e-3  # metres per step
        assert sc.controls["feedback"][..., :2].abs().max() * to_m > 1.0  # the corrections are not trivial
    with pytest.raises(ValueError, match="feedback"):
        simulate_p003(1, duration=5, feedback="truth")
