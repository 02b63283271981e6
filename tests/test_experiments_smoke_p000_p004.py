"""p000 (GPS/DR, Singer UKF) and p004 (EKF/UKF blend) experiments: the support modules (fast) and
`experiments/train.py experiment=... debug=smoke` end to end (slow)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from difffilter.filters import EKF, UKF
from difffilter.selection import parameter_owners
from experiments.papers.p000 import p000_simulator
from experiments.papers.p004 import ImuSwitchingStatistics, blend_filter, p004_simulator
from experiments.papers.p004.model import GNSS_IMU_PAPER, GnssImuModel
from tests.smoke_helpers import run_train_smoke

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64


def test_p000_simulator_gives_the_paper_belief_and_a_deterministic_set():
    a = p000_simulator(batch_size=2, seed=3, num_steps=40, scenario="random", dtype="float64")
    b = p000_simulator(batch_size=2, seed=3, num_steps=40, scenario="random", dtype=f64)
    assert a.measurements.shape == (2, 40, 4) and a.truth.shape == (2, 40, 8)
    assert torch.equal(a.measurements, b.measurements)
    torch.testing.assert_close(a.initial_cov, torch.eye(8, dtype=f64))  # p000: P(0|0) = I_8
    # the belief starts at the truth at t = 0: one step of motion before the first sample
    step = a.truth[:, 0, [0, 3]] - a.initial_mean[:, [0, 3]]
    speed = a.initial_mean[:, [1, 4]].norm(dim=-1)
    torch.testing.assert_close(step.norm(dim=-1), 0.1 * speed, rtol=0.05, atol=0.0)
    assert a.make_model().state_dim == 8
    c = p000_simulator(batch_size=1, seed=0, steps=30, scenario="straight", initial_std=[2.0] * 8, dtype=f64)
    torch.testing.assert_close(c.initial_cov, 4.0 * torch.eye(8, dtype=f64))


def test_p004_simulator_oracle_values_and_heading_error():
    d = p004_simulator(batch_size=3, seed=1, dtype=f64)
    assert d.truth.shape == (3, 400, 8) and d.controls["accel"].shape == (3, 400, 2)
    assert d.true_params["sigma_accel"] == GNSS_IMU_PAPER["sigma_accel"] and d.true_params["sigma_gyro"] == GNSS_IMU_PAPER["sigma_gyro"]
    assert d.true_params["R"] == pytest.approx([0.1**2, 0.1**2], rel=1e-12)
    exact = p004_simulator(batch_size=3, seed=1, dtype=f64, initial_error=False)
    torch.testing.assert_close(exact.initial_mean[:, :5], exact.scenario.initial_state[:, :5])
    torch.testing.assert_close(exact.truth, d.truth)  # the belief's draw comes after the drive's
    # default: the belief's mean is drawn from N(truth, P0) (consistent with its covariance)
    w = p004_simulator(batch_size=400, seed=2, dtype=f64)
    z = (w.initial_mean[:, :5] - w.scenario.initial_state[:, :5]) / w.initial_cov.diagonal()[:5].sqrt()
    assert bool(((z.std(0) - 1).abs() < 5 / math.sqrt(800)).all()), z.std(0)
    torch.testing.assert_close(w.initial_mean[:, 5:], torch.zeros(400, 3, dtype=f64))
    with pytest.raises(TypeError, match="initial_error"):
        p004_simulator(batch_size=1, initial_error="yes")
    e = p004_simulator(batch_size=60, seed=1, initial_heading_std_deg=30.0, dtype=f64)
    err = e.initial_mean[:, 4] - e.scenario.initial_state[:, 4]
    assert float(e.initial_cov[4, 4]) == pytest.approx(math.radians(30.0) ** 2)
    # sample std of 60 draws: within 4 standard errors (std / sqrt(2 n)) of 30 deg
    assert abs(math.degrees(float(err.std())) - 30.0) < 4 * 30.0 / math.sqrt(120)
    with pytest.raises(ValueError, match="planar"):
        p004_simulator(batch_size=1, planar=False, initial_heading_std_deg=5.0)


def test_switching_statistics_from_controls():
    stats = ImuSwitchingStatistics()
    u = {"accel": torch.tensor([[3.0, 4.0], [0.0, 0.0]], dtype=f64), "gyro": torch.tensor([[0.0], [math.pi]], dtype=f64)}
    gamma, mu = stats(u)
    torch.testing.assert_close(mu, torch.tensor([5.0 / 9.8, 1.0], dtype=f64))
    torch.testing.assert_close(gamma, torch.ones(2, dtype=f64))  # max(0.1, 0.0017) / max(0.1, 0.1)
    # a 3-axis reading includes gravity on the up axis; it is removed
    u3 = {"accel": torch.tensor([[3.0, 4.0, 9.80665]], dtype=f64), "gyro": torch.zeros(1, 3, dtype=f64)}
    torch.testing.assert_close(stats(u3)[1], torch.tensor([5.0 / 9.8], dtype=f64))
    with pytest.raises(ValueError, match="controls"):
        stats(torch.zeros(2, 3))


def test_blend_filter_shares_one_model_and_matches_its_branches():
    model = GnssImuModel(planar=True, dtype=f64)
    blend = blend_filter(model=model, delta=1.0)
    assert blend.ekf.model is blend.ukf.model is model
    names = set(parameter_owners(blend))
    assert sum(n.endswith("sigma_accel") for n in names) == 1 and sum(n.endswith(".R") for n in names) == 1
    d = p004_simulator(batch_size=2, seed=0, dtype=f64)
    z, m0, p0 = d.measurements[:, :30], d.initial_mean, d.initial_cov
    u = {k: v[:, :30] for k, v in d.controls.items()}
    # delta = 1 is the EKF prediction with the (linear, hence exact) UKF update = the EKF
    ref = EKF(model)(z, m0, p0, controls=u)
    out = blend(z, m0, p0, controls=u)
    torch.testing.assert_close(out.mean, ref.mean)
    blend0 = blend_filter(model=model, delta=0.0)
    torch.testing.assert_close(blend0(z, m0, p0, controls=u).mean, UKF(model)(z, m0, p0, controls=u).mean)
    gate = blend_filter(model=model, mode="gate", statistics=ImuSwitchingStatistics(), thresholds=[3.0, 0.1], temperature=[0.1, 0.02])
    with torch.no_grad():
        w = gate(z, m0, p0, controls=u).blend_weight
    # p004 eqs. (1), (2) written out: gamma = 0.1 / 0.1, mu from the planar IMU readings
    mu = torch.sqrt((u["accel"] ** 2).sum(-1) / 9.8**2 + u["gyro"][..., 0] ** 2 / math.pi**2)
    torch.testing.assert_close(w, torch.sigmoid(torch.tensor(2.0 / 0.1, dtype=f64)) * torch.sigmoid((0.1 - mu) / 0.02))
    assert float(w[:, :2].max()) < 0.05  # the paper's 2 m/s^2 start is "nonlinear" (mu ~ 0.2): UKF


@pytest.mark.slow
@pytest.mark.parametrize(
    ("experiment", "expected"),
    [
        # p000: the paper's CA filter hand-tuned vs learned; its EKF-vs-UKF comparison is the sigma_a sweep
        # (experiments.papers.p000.sigma_sweep), the random-drive test set lands in extra_tests/random
        ("p000_gpsdr", ["hand-tuned", "learned"]),
        ("p004_blend", ["hand-tuned", "learned", "oracle", "ekf", "ukf", "switch", "gate"]),
    ],
)
def test_experiment_smoke(tmp_path, experiment, expected):
    rows, md = run_train_smoke(tmp_path, experiment)
    assert [r["filter"] for r in rows] == expected
    for col in (
        "rmse_pos",
        "rmse_state",
        "anees",
        "anees_run_ci_lo",
        "anees_run_ci_hi",
        "anees_step_band_frac",
        "nis",
        "nll",
        "time_per_step_ms",
    ):
        assert col in rows[0], col
    assert "anees_lo" not in rows[0] and "nis_lo" not in rows[0]  # the runs x steps chi-square band is gone
    for r in rows:
        assert float(r["rmse_pos"]) > 0 and math.isfinite(float(r["rmse_pos"])), r
        assert math.isfinite(float(r["anees"])) and math.isfinite(float(r["nll"])) and float(r["time_per_step_ms"]) > 0, r
    assert "| hand-tuned |" in md and "| learned |" in md
    if experiment == "p000_gpsdr":
        extra = tmp_path.rglob("extra_tests/random/results.csv")
        assert next(extra, None) is not None  # the in-distribution test set was evaluated too
