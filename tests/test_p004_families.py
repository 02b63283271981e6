"""p004's scenario families: the MEMS IMU's walking biases and noise have the stated statistics
and stay in the filter's family (one-step prediction errors match the oracle's Q), the urban
canyon's GNSS error is the stated Gauss-Markov process with the reported accuracy, the
accuracy-scaled R reduces to p004's constant R at gamma = 0, and the oracle's values."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from experiments.papers.p004 import p004_simulator, simulate_p004
from experiments.papers.p004.model import GNSS_IMU_PAPER, GnssImuModel, GnssMeasurement

F64 = torch.float64
# experiments/papers/p004/conf/scenario/p004_mems_*.yaml
MEMS = {
    "sigma_accel": 0.002,
    "sigma_gyro": math.radians(0.05),
    "sigma_accel_bias": 1e-3 * 9.80665,
    "sigma_gyro_bias": math.radians(0.1),
}
WALK = (0.1e-3 * 9.80665 / 20.0, math.radians(20.0 / 3600.0) / 20.0)
CANYON = [(90.0, 215.0), (290.0, 350.0)]  # experiments/papers/p004/conf/scenario/p004_urban_*.yaml


def test_mems_biases_walk_with_the_stated_statistics_and_stay_in_the_family() -> None:
    data = simulate_p004(batch_size=8, seed=4, planar=True, dtype=F64, bias_walk=WALK, **MEMS)
    steps = data.truth[:, 1:, 5:8] - data.truth[:, :-1, 5:8]  # [B, T-1, 3] bias increments
    n = steps.shape[0] * steps.shape[1]
    expected = torch.tensor([WALK[0], WALK[0], WALK[1]], dtype=F64)
    ratio = steps.reshape(-1, 3).std(0) / expected
    assert bool(((ratio - 1).abs() < 5 / math.sqrt(2 * n)).all()), ratio
    # the filter with the true values predicts one step with errors distributed as its Q
    # (velocity, heading and biases; position carries the trapezoid's own error, covered in test_gnss_imu)
    model = GnssImuModel(planar=True, dtype=F64, sigma_accel_bias_walk=WALK[0], sigma_gyro_bias_walk=WALK[1], **MEMS)
    prev = torch.cat([data.initial_state[:, None], data.truth[:, :-1]], 1)
    err = (model.f(prev, data.controls) - data.truth).reshape(-1, 8)[:, 2:]
    q = model.dynamics.Q.detach().diagonal()[2:]
    n = err.shape[0]
    ratio = err.std(0) / q.sqrt()
    assert bool(((ratio - 1).abs() < 5 / math.sqrt(2 * n)).all()), ratio
    # turn-on biases: drawn from the datasheet spread that the initial belief states
    _, cov0 = data.initial_belief()
    torch.testing.assert_close(
        cov0.diagonal()[5:], torch.tensor([MEMS["sigma_accel_bias"] ** 2] * 2 + [MEMS["sigma_gyro_bias"] ** 2], dtype=F64)
    )
    nominal = simulate_p004(batch_size=2, seed=4, planar=True, dtype=F64)
    assert bool((nominal.truth[:, :, 5:] == nominal.initial_state[:, None, 5:]).all())  # p004: constant biases
    with pytest.raises(ValueError, match="bias_walk"):
        simulate_p004(batch_size=1, planar=True, bias_walk=(-1.0, 0.0))


def test_urban_canyon_gnss_error_and_reported_accuracy() -> None:
    data = simulate_p004(batch_size=64, seed=5, planar=True, dtype=F64, canyon_windows=CANYON, canyon_sigma=1.0, canyon_tau=10.0)
    t = torch.arange(1, 401, dtype=F64)
    canyon = ((t >= 90) & (t < 215)) | ((t >= 290) & (t < 350))
    err = data.measurements - data.truth[..., :2]
    acc = data.controls["gnss_accuracy"][..., 0]
    assert bool((acc[:, canyon] == 1.0).all()) and bool((acc[:, ~canyon] == 0.1).all())
    inside = err[:, 100:200]  # one canyon stretch, away from its edges
    n = inside.numel()
    phi = math.exp(-1.0 / 10.0)
    eff = n * (1 - phi) / (1 + phi)
    assert abs(float(inside.pow(2).mean().sqrt()) - 1.0) < 5 * math.sqrt(0.5 / eff)
    lag1 = float((inside[:, 1:] * inside[:, :-1]).mean() / inside.pow(2).mean())
    assert abs(lag1 - phi) < 5 * (1 - phi**2) / math.sqrt(eff)
    open_sky = err[:, :85]
    m = open_sky.numel()
    assert abs(float(open_sky.pow(2).mean().sqrt()) - 0.1) < 0.1 * 5 * math.sqrt(0.5 / m)
    assert abs(float((open_sky[:, 1:] * open_sky[:, :-1]).mean() / open_sky.pow(2).mean())) < 5 / math.sqrt(m)
    nominal = simulate_p004(batch_size=2, seed=5, planar=True, dtype=F64)
    assert bool((nominal.controls["gnss_accuracy"] == GNSS_IMU_PAPER["sigma_gnss"]).all())
    with pytest.raises(ValueError, match="windows"):
        simulate_p004(batch_size=1, planar=True, canyon_windows=[(10.0, 5.0)])


def test_accuracy_scaled_r_reduces_to_p004s_constant_r() -> None:
    acc = torch.tensor([[0.1], [1.0], [0.3]], dtype=F64)
    u = {"gnss_accuracy": acc}
    plain = GnssMeasurement(planar=True, velocity=True, dtype=F64)
    at_zero = GnssMeasurement(planar=True, velocity=True, accuracy_exponent=0.0, dtype=F64)
    torch.testing.assert_close(at_zero.measurement_noise(None, u), plain.R.expand(3, 4, 4), rtol=0, atol=0)
    scaled = GnssMeasurement(planar=True, velocity=True, accuracy_exponent=1.0, dtype=F64)
    r = scaled.measurement_noise(None, u)
    for i, a in enumerate((0.1, 1.0, 0.3)):
        expected = torch.diag(torch.tensor([0.01 * (a / 0.1) ** 2] * 2 + [0.05**2] * 2, dtype=F64))
        torch.testing.assert_close(r[i], expected)
    assert "accuracy_exponent" not in dict(plain.named_parameters()) and "parametrizations.accuracy_exponent.original" in dict(
        scaled.named_parameters()
    )
    with pytest.raises(ValueError, match="accuracy_exponent"):
        GnssMeasurement(planar=True, accuracy_exponent=4.5)
    with pytest.raises(KeyError, match="gnss_accuracy"):
        scaled.measurement_noise(None, {})
    model = GnssImuModel(planar=True, accuracy_exponent=0.5, dtype=F64)
    torch.testing.assert_close(
        model.measurement.measurement_noise(None, {"gnss_accuracy": torch.tensor([0.4], dtype=F64)}), 0.01 * 4 * torch.eye(2, dtype=F64)
    )


def test_oracle_values_of_each_family() -> None:
    nominal = p004_simulator(batch_size=2, seed=1)
    assert set(nominal.true_params) == {"sigma_accel", "sigma_gyro", "R"}
    mems = p004_simulator(batch_size=2, seed=1, bias_walk=list(WALK), **MEMS)
    assert mems.true_params["sigma_accel"] == MEMS["sigma_accel"] and mems.true_params["sigma_gyro"] == MEMS["sigma_gyro"]
    assert mems.true_params["sigma_accel_bias_walk"] == WALK[0] and mems.true_params["sigma_gyro_bias_walk"] == WALK[1]
    urban = p004_simulator(batch_size=2, seed=1, canyon_windows=CANYON)
    assert set(urban.true_params) == {"sigma_accel", "sigma_gyro", "R"}  # the canyon's correlated error has no filter value


def test_cold_start_family_has_the_stated_outage_and_heading_spread() -> None:
    """experiments/papers/p004/conf/scenario/p004_outage_*.yaml: no GNSS before t = 30 s, a fix every second after, and
    the belief's heading error drawn with the stated 30 deg std (its variance says so too)."""
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=p004_outage"])
    assert cfg.data.test_simulator.randomize is False and cfg.scenario.randomize is True
    for sim in (cfg.data.test_simulator, cfg.scenario):
        d = instantiate(sim, _convert_="all")(batch_size=60, seed=3, dtype="float64")
        t = torch.arange(1, d.mask.shape[1] + 1, dtype=F64)
        assert bool((~d.mask[:, t < 30]).all()) and bool(d.mask[:, t >= 30].all())
        assert bool(torch.isnan(d.measurements[:, t < 30]).all())
        assert float(d.initial_cov[4, 4]) == pytest.approx(math.radians(30.0) ** 2)
        err = math.degrees(float((d.initial_mean[:, 4] - d.scenario.initial_state[:, 4]).std()))
        assert abs(err - 30.0) < 5 * 30.0 / math.sqrt(120)  # 5 standard errors of a 60-draw std
    # the family keeps p004's noise: hand-tuned noise = the simulator's truth
    assert cfg.experiment.hand_tuned.sigma_accel == pytest.approx(d.true_params["sigma_accel"])
    assert list(cfg.experiment.hand_tuned.R) == pytest.approx(d.true_params["R"])
