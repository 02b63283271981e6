"""p003's scenario families (experiments.papers.p003.noise): the schedules, the injected noise has
the stated statistics, the oracles, the learned layout with log-scaled R groups, the switching
statistics."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from difffilter import geometry as geo
from difffilter.evaluate.metrics import mode_switch_delay
from difffilter.filters import SageHusa, SimplifiedUKF
from difffilter.mixers import IMM
from experiments.papers.p003 import (
    LOAD_LIMITS,
    PAPER_PHASES,
    antenna_gain_db,
    body_elevation,
    cn0_sigma_scale,
    empirical_transition,
    flight_profile,
    learned_from_state,
    make_p003_model,
    manoeuvre_flags,
    markov_phases,
    p003_imm,
    p003_learner,
    p003_oracle,
    p003_single,
    random_phases,
    reference_imm,
    simulate_p003,
    sojourn_transition,
    switch_delays,
    switching_rows,
    true_transition,
    vibration_scale,
)
from experiments.papers.p003.flight import attitude_matrix

f64 = torch.float64
G = 9.80665


def _peak_loads(phases, speed0=0.0):
    t = np.arange(0.0, max(p[1] for p in phases), 0.05)
    prof = flight_profile(phases, t, 0.0, speed0)
    along = np.abs(np.gradient(prof["speed"], t))
    lateral = np.abs(prof["speed"] * prof["psid"])
    normal = np.abs(prof["speed"] * np.gradient(prof["gamma"], t))
    return along.max(), lateral.max(), normal.max()


def test_random_schedules_stay_inside_the_load_limits():
    rng = np.random.default_rng(0)
    for _ in range(20):
        phases = random_phases(rng, 900.0)
        assert phases[-1][1] == pytest.approx(900.0)
        along, lateral, normal = _peak_loads(phases)
        assert along <= 1.01 * LOAD_LIMITS["accelerate"] and lateral <= 1.01 * LOAD_LIMITS["turn"]
        assert normal <= 1.01 * LOAD_LIMITS["climb"]


def test_markov_schedule_flags_are_the_stated_markov_chain():
    rng = np.random.default_rng(1)
    p_enter, p_leave = 1 / 20, 1 / 5
    counts = np.zeros((2, 2))
    for _ in range(60):
        phases = markov_phases(rng, 600.0, p_enter=p_enter, p_leave=p_leave, speed=100.0)
        assert all(float(p[0]).is_integer() and float(p[1]).is_integer() for p in phases)
        assert phases[0][2] == "level" and phases[0][0] == 0.0
        flags = manoeuvre_flags(phases, np.arange(1, 601) - 0.5).astype(int)
        np.add.at(counts, (flags[:-1], flags[1:]), 1.0)
        along, lateral, normal = _peak_loads(phases, 100.0)
        assert along <= 1.01 * LOAD_LIMITS["accelerate"] and lateral <= 1.01 * LOAD_LIMITS["turn"]
        assert normal <= 1.01 * LOAD_LIMITS["climb"]
    est = counts / counts.sum(1, keepdims=True)
    for i, p in ((0, p_enter), (1, 1 - p_leave)):  # binomial: 4 standard errors
        assert abs(est[i, 1] - p) < 4 * math.sqrt(p * (1 - p) / counts[i].sum())
    np.testing.assert_allclose(true_transition(p_enter, p_leave), [[0.95, 0.05], [0.2, 0.8]])
    with pytest.raises(ValueError, match="p_enter"):
        markov_phases(rng, 10.0, p_enter=0.0, p_leave=0.5, speed=100.0)


def test_noise_helpers():
    np.testing.assert_allclose(vibration_scale(np.array([[0.0, 0.0, 0.0], [0.0, G, 0.0]]), 10.0), [1.0, 11.0])
    np.testing.assert_allclose(antenna_gain_db(np.radians([30.0, 10.0, 4.0, -5.0]), 10.0, 1.0), [0.0, 0.0, -6.0, -15.0])
    np.testing.assert_allclose(cn0_sigma_scale(np.array([0.0, -20.0])), [1.0, 10.0])
    # level attitude: body elevation = elevation; heading north and rolled right by 30 deg (right wing
    # down, the antenna tilted east, into the turn), a satellite due east at 20 deg elevation rises to
    # 50 deg and one due west (the high-wing side) falls 10 deg below the antenna horizon
    los = np.array(
        [[math.cos(math.radians(20)), 0.0, math.sin(math.radians(20))], [-math.cos(math.radians(20)), 0.0, math.sin(math.radians(20))]]
    )
    np.testing.assert_allclose(np.degrees(body_elevation(los, np.eye(3))), [20.0, 20.0], atol=1e-9)
    r = math.radians(30.0)
    roll_right = np.array([[math.cos(r), 0.0, math.sin(r)], [0.0, 1.0, 0.0], [-math.sin(r), 0.0, math.cos(r)]])  # columns: body axes in ENU
    np.testing.assert_allclose(np.degrees(body_elevation(los, roll_right)), [50.0, -10.0], atol=1e-9)


def _residuals(sc):
    model = make_p003_model(position_in_metres=True)
    return sc.measurements - model.measurement(sc.truth, sc.controls)


def test_modes_family_scales_gnss_and_imu_noise_in_manoeuvres():
    cfg = {"mode_imu_scale": 10.0, "mode_gnss_scale": 4.0}
    sc = simulate_p003(6, seed=3, duration=300, imu_rate=5, profile="markov", noise="modes", config=cfg, position_in_metres=True)
    res = _residuals(sc)[..., 8:] / 0.05  # rate noise in units of the nominal sigma
    man = sc.manoeuvre[..., None].expand_as(res)
    ok = sc.mask[..., 8:]
    assert res[ok & ~man].std().item() == pytest.approx(1.0, rel=0.1) and res[ok & man].std().item() == pytest.approx(4.0, rel=0.1)
    torch.testing.assert_close(sc.gnss_noise_scale, torch.where(man, 4.0, 1.0).to(f64))
    torch.testing.assert_close(sc.imu_noise_scale, torch.where(sc.manoeuvre, 10.0, 1.0).to(f64))
    # IMU white noise: open loop, no biases and no initial errors, the velocity error's 1 s increments
    # are the accelerometer white noise (0.1 mg per 1 Hz sample, x 10 in manoeuvres)
    quiet = {"gyro_constant_dph": 0.0, "gyro_markov_dph": 0.0, "accel_bias_mg": 0.0, **cfg}
    sc = simulate_p003(8, seed=4, duration=300, imu_rate=5, profile="markov", noise="modes", config=quiet, initial_errors=False)
    dv = torch.diff(sc.truth[..., 3:5], dim=1) / (0.1 * 9.80665e-3)  # horizontal: no vertical-channel drift
    man = (sc.manoeuvre[:, 1:] & sc.manoeuvre[:, :-1])[..., None].expand_as(dv)
    level = (~sc.manoeuvre[:, 1:] & ~sc.manoeuvre[:, :-1])[..., None].expand_as(dv)
    assert dv[level].std().item() == pytest.approx(1.0, rel=0.15) and dv[man].std().item() == pytest.approx(10.0, rel=0.15)


def test_nominal_family_has_no_bursts():
    sc = simulate_p003(4, seed=5, duration=200, imu_rate=5, profile="random", position_in_metres=True)
    res = _residuals(sc)[..., 8:] / 0.05
    man = sc.manoeuvre[..., None].expand_as(res)
    ok = sc.mask[..., 8:]
    assert bool(sc.manoeuvre.any()) and bool((sc.gnss_noise_scale == 1).all()) and bool((sc.imu_noise_scale == 1).all())
    assert res[ok & ~man].std().item() == pytest.approx(1.0, rel=0.1) and res[ok & man].std().item() == pytest.approx(1.0, rel=0.15)


def test_physical_family_follows_vibration_and_antenna_shading():
    quiet = {"gyro_constant_dph": 0.0, "gyro_markov_dph": 0.0, "accel_bias_mg": 0.0}
    sc = simulate_p003(4, seed=6, duration=600, imu_rate=5, profile="paper", noise="physical", config=quiet, position_in_metres=True)
    # GNSS: residuals in units of sigma x the recorded multiplier are standard normal; lost channels masked
    res = _residuals(sc)
    scale = torch.cat([sc.gnss_noise_scale * 3.0, sc.gnss_noise_scale * 0.05], -1)
    ok = sc.mask
    z = (res / scale)[ok]
    assert z.std().item() == pytest.approx(1.0, rel=0.05) and abs(z.mean().item()) < 0.05
    lost = torch.cat([sc.cn0 < 30.0, sc.cn0 < 30.0], -1)
    assert not bool((ok & lost).any())
    torch.testing.assert_close(sc.gnss_noise_scale, torch.pow(10.0, (45.0 - sc.cn0) / 20.0))
    # C/N0 is the antenna model at the true attitude and satellite directions (recomputed here)
    llh, euler = sc.nav_truth["llh"], sc.nav_truth["euler"]
    p = geo.geodetic_to_ecef(llh)
    los = ((sc.controls["sat_pos"] - p[..., None, :])[..., None, :] @ geo.enu_rotation(llh[..., 0], llh[..., 1]).mT[..., None, :, :])[
        ..., 0, :
    ]
    up = torch.from_numpy(attitude_matrix(*(v.numpy() for v in euler.unbind(-1))))[..., :, 2]
    elev = torch.asin((los / los.norm(dim=-1, keepdim=True) * up[..., None, :]).sum(-1))
    cn0 = 45.0 - torch.clamp(10.0 - torch.rad2deg(elev), min=0.0)
    torch.testing.assert_close(sc.cn0, cn0, rtol=0, atol=1e-6)
    turn = torch.zeros(600, dtype=torch.bool)
    turn[500:520] = True
    drop = (sc.cn0 < 44.0).any(-1)[0]
    assert bool(drop[turn].any()) and bool(((sc.cn0 < 30.0).any(-1)[0] <= turn).all())
    # IMU: level flight at the nominal noise, x (1 + 10 |a| / g) in the 10-20 s take-off acceleration
    # (straight ahead: |a| = the speed's rate of change; per 1 s step the rms over its 5 IMU samples)
    assert bool((sc.imu_noise_scale[:, 30:55] == 1).all())
    tg = np.arange(0, 20.0 + 1e-9, 0.2)
    accel = np.diff(flight_profile(list(PAPER_PHASES), tg, math.radians(135.0))["speed"]) / 0.2
    expected = np.sqrt(((1.0 + 10.0 * accel / G) ** 2).reshape(20, 5).mean(-1))
    np.testing.assert_allclose(sc.imu_noise_scale[0, :20].numpy(), expected, rtol=1e-6)
    assert expected.max() > 12.0


def test_oracles_of_the_families():
    nominal = p003_oracle(noise="nominal", profile="random")
    assert isinstance(nominal, SimplifiedUKF)
    modes = p003_oracle(noise="modes", profile="markov", config={"mode_imu_scale": 10.0, "mode_gnss_scale": 2.0})
    hand = p003_imm()
    q0, q1, qh = (torch.diagonal(m.model.dynamics.Q) for m in (modes.filters[0], modes.filters[1], hand.filters[0]))
    torch.testing.assert_close(q0, qh)
    torch.testing.assert_close(q1[3:9], 100.0 * qh[3:9])
    torch.testing.assert_close(q1[9:], qh[9:])
    torch.testing.assert_close(modes.filters[1].model.measurement.R, 4.0 * hand.filters[0].model.measurement.R)
    torch.testing.assert_close(modes.transition, torch.tensor([[59 / 60, 1 / 60], [1 / 15, 14 / 15]], dtype=f64), rtol=0, atol=2e-6)
    paper = p003_oracle(noise="modes", profile="paper", duration=600.0)
    torch.testing.assert_close(paper.transition, torch.tensor(empirical_transition(PAPER_PHASES, 600.0), dtype=f64), rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="physical"):
        p003_oracle(noise="physical", profile="random")


def test_hand_tuned_transition_rule():
    pi = np.array(sojourn_transition())
    np.testing.assert_allclose(pi, [[1 - 8 / 1675, 8 / 1675], [7 / 125, 1 - 7 / 125]], rtol=1e-12)
    torch.testing.assert_close(reference_imm().transition, torch.tensor(pi, dtype=f64), rtol=0, atol=2e-6)


def test_learned_layout_with_log_scaled_r_groups():
    hand = p003_imm(model={"num_satellites": 4})
    r_hand = [f.model.measurement.R.detach().clone() for f in hand.filters]
    learner = p003_learner(copy.deepcopy(hand), "nll", q_groups="imu_white", r_groups="range_rate", learn=["Q", "R", "transition"])
    meas = learner.filter.filters[1].model.measurement
    assert meas.parametrizations.R.original.shape == (2,)
    torch.testing.assert_close(meas.R, r_hand[1])
    with torch.no_grad():
        meas.parametrizations.R.original.copy_(torch.tensor([math.log(0.1), math.log(4.0)], dtype=f64))
    r = torch.diagonal(meas.R)
    torch.testing.assert_close(r[:4], 0.1 * torch.diagonal(r_hand[1])[:4])  # pseudoranges
    torch.testing.assert_close(r[4:], 4.0 * torch.diagonal(r_hand[1])[4:])  # pseudorange rates
    torch.testing.assert_close(hand.filters[1].model.measurement.R, r_hand[1])  # the hand-tuned filter is untouched
    state = {f"filter.{k}": v for k, v in learner.filter.state_dict().items()}
    rebuilt = learned_from_state(hand, state, "imu_white", "range_rate")
    torch.testing.assert_close(rebuilt.filters[1].model.measurement.R, meas.R)
    one = p003_learner(copy.deepcopy(hand), "nll", r_groups="one", learn=["R"])
    assert one.filter.filters[0].model.measurement.parametrizations.R.original.shape == (1,)
    with pytest.raises(ValueError, match="r_groups"):
        p003_learner(copy.deepcopy(hand), "nll", r_groups="per_satellite")


def test_learned_layout_of_an_adaptive_filter_around_one_mode():
    # the learned adaptive job: Sage-Husa around p003_single, its inner model in the family's layout
    filt = SageHusa(p003_single(model={"num_satellites": 4}), b=0.98)
    q0, r0 = filt.model.dynamics.Q.detach().clone(), filt.model.measurement.R.detach().clone()
    learner = p003_learner(filt, "nll", q_groups="imu_white", r_groups="range_rate", learn=["b", "Q", "R"])
    dyn, meas = learner.filter.inner.model.dynamics, learner.filter.inner.model.measurement
    assert dyn.parametrizations.Q.original.shape == (2,) and meas.parametrizations.R.original.shape == (2,)
    torch.testing.assert_close(dyn.Q, q0)
    with torch.no_grad():
        meas.parametrizations.R.original.copy_(torch.tensor([math.log(0.1), math.log(4.0)], dtype=f64))
    r = torch.diagonal(learner.filter.model.measurement.R)  # the wrapper's model is the inner's
    torch.testing.assert_close(r, torch.cat([0.1 * torch.diagonal(r0)[:4], 4.0 * torch.diagonal(r0)[4:]]))
    assert {n.split(".")[-2] for n, _ in learner.filter.named_parameters()} == {"b", "Q", "R"}


def test_switch_delays_per_run_against_enumeration():
    gen = torch.Generator().manual_seed(0)
    probs_high = torch.rand(3, 40, generator=gen, dtype=f64)
    mode_probs = torch.stack([1 - probs_high, probs_high], -1)
    modes = torch.zeros(3, 40, dtype=torch.long)
    modes[:, 10:20] = 1
    modes[:, 30:35] = 1
    out = switch_delays(mode_probs, modes, 0.5)
    ref = mode_switch_delay(mode_probs, modes, 0.5)
    for b in range(3):
        delays = {}
        for t0, end, m in ((10, 20, 1), (20, 30, 0), (30, 35, 1), (35, 40, 0)):  # brute force over each segment
            hit = [k for k in range(t0, end) if mode_probs[b, k, m] > 0.5]
            delays[(t0, m)] = float(hit[0] - t0) if hit else math.nan
        first_up, first_down = delays[(10, 1)], delays[(20, 0)]
        assert out["first_up"][b].item() == pytest.approx(first_up, nan_ok=True)
        assert out["first_down"][b].item() == pytest.approx(first_down, nan_ok=True)
        ups = [v for (t0, m), v in delays.items() if m == 1]
        found = [v for v in ups if not math.isnan(v)]
        assert out["detected_up"][b].item() == pytest.approx(len(found) / 2)
        assert out["all_up"][b].item() == pytest.approx(sum(found) / len(found) if found else math.nan, nan_ok=True)
    assert int(ref.delay.numel()) == 12
    rows = switching_rows({"a": out, "b": {k: torch.stack([v, v]) for k, v in out.items()}})
    assert (
        [r["filter"] for r in rows] == ["a", "b"] and rows[0]["first_up_found"].endswith("/3") and rows[1]["first_up_found"].endswith("/6")
    )
    with pytest.raises(ValueError, match="mode_probs"):
        switch_delays(mode_probs[..., :1], modes)


def test_paper_imm_stays_in_the_low_mode_when_nothing_switches():
    # the paper-faithful family: a short closed-loop flight; the hand-tuned IMM's estimate equals the
    # single low-noise filter's (the oracle) because the high mode never gains weight
    sc = simulate_p003(2, seed=8, duration=80, imu_rate=5, profile="paper", feedback="imm", position_in_metres=True)
    imm: IMM = p003_imm(transition=sojourn_transition())
    res = imm(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    single = p003_oracle(noise="nominal", profile="paper")(
        sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls
    )
    assert res.mode_probs[:, 5:, 0].min().item() > 0.99
    torch.testing.assert_close(res.mean[:, 5:, :6], single.mean[:, 5:, :6], rtol=0, atol=1e-3)
