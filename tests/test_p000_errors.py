"""p000's mis-specified families: each injected sensor error has the stated statistics; the
literal reuse UKF is the paper's equations; the sigma_a sweep's per-axis metric."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import UKF, KalmanFilter
from difffilter.filters.sigma_points import Julier
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from experiments.papers.p000 import (
    LiteralReuseUKF,
    SensorErrors,
    gauss_markov,
    p000_simulator,
    per_axis_metrics,
    random_windows,
    simulate_p000,
)
from experiments.papers.p000.model import A_MAX_VEHICLE, GPSDR_PAPER

f64 = torch.float64


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_hand_tuned_sigma_a_is_the_current_statistical_rule():
    assert GPSDR_PAPER["sigma_a"] ** 2 == pytest.approx((4.0 - math.pi) / math.pi * A_MAX_VEHICLE**2, rel=1e-12)
    assert GPSDR_PAPER["a_max"] == A_MAX_VEHICLE == 3.4


def test_gauss_markov_has_its_stationary_std_and_correlation():
    x = gauss_markov(_gen(0), (400, 600), 0.1, 2.0, 5.0)
    assert abs(float(x.std()) - 2.0) < 0.05
    lag = 50  # = tau / dt: correlation exp(-1)
    c = float((x[:, lag:] * x[:, :-lag]).mean() / x.var())
    assert c == pytest.approx(math.exp(-1.0), abs=0.03)


def test_random_windows_cover_the_expected_fraction_and_hold_one_value():
    rate, lo, hi, dt, steps = 0.02, 5.0, 15.0, 0.1, 3000
    w = random_windows(_gen(1), (300, steps), dt, rate, (lo, hi), lambda b: torch.randn(b, 2, generator=_gen(9), dtype=f64))
    inside = (w != 0).any(-1)
    # Poisson windows of mean length 10 s: coverage 1 - exp(-rate E[length]) away from the run's start
    frac = float(inside[:, 300:].double().mean())
    assert frac == pytest.approx(1 - math.exp(-rate * 0.5 * (lo + hi)), abs=0.03)
    # inside one window the value does not change between consecutive steps (except at a new window)
    changes = ((w[:, 1:] != w[:, :-1]).any(-1) & inside[:, 1:] & inside[:, :-1]).double().mean()
    assert float(changes) < 0.005
    assert torch.equal(random_windows(_gen(1), (2, 10), dt, 0.0, (lo, hi)), torch.zeros(2, 10, 1, dtype=f64))


def test_gyro_bias_family_turn_on_and_instability():
    err = SensorErrors(gyro_turn_on_std=1e-3, gyro_instability_std=4e-4, gyro_instability_tau=300.0)
    bias = err.gyro_bias(_gen(2), (2000, 100), 0.1)
    # over 10 s the instability hardly moves: the run mean is turn-on + instability, variance summed
    assert float(bias.mean(1).std()) == pytest.approx(math.hypot(1e-3, 4e-4), rel=0.06)
    step = bias[:, 1:] - bias[:, :-1]  # only the instability moves: increments of a GM with tau = 300 s
    assert float(step.std()) == pytest.approx(4e-4 * math.sqrt(1 - math.exp(-0.2 / 300.0)), rel=0.05)
    with pytest.raises(ValueError, match="gyro_instability_tau"):
        SensorErrors(gyro_instability_tau=0.0)


def test_odometer_family_slip_follows_the_acceleration_and_bursts():
    err = SensorErrors(slip_per_accel=0.007)
    accel = torch.linspace(-2.0, 2.0, 50, dtype=f64).expand(3, 50)
    torch.testing.assert_close(err.slip(_gen(0), accel, 0.1), 0.007 * accel)
    bursty = SensorErrors(slip_burst_rate=0.05, slip_burst_size=(0.1, 0.3), slip_burst_duration=(1.0, 1.0))
    lam = bursty.slip(_gen(3), torch.zeros(400, 2000, dtype=f64), 0.1)
    on = lam != 0
    assert float(on.double().mean()) == pytest.approx(1 - math.exp(-0.05 * 1.0), abs=0.01)
    assert float(lam[on].abs().min()) >= 0.1 and float(lam[on].abs().max()) <= 0.3
    assert float((lam[on] > 0).double().mean()) == pytest.approx(0.5, abs=0.05)  # spin and lock-up alike


def test_gps_family_multipath_nlos_and_outages():
    mp = SensorErrors(multipath_std=8.0, multipath_tau=30.0).gps_error(_gen(4), (300, 400), 0.1)
    assert float(mp.std()) == pytest.approx(8.0, rel=0.05)
    nlos = SensorErrors(nlos_rate=0.02, nlos_std=30.0, nlos_duration=(5.0, 5.0)).gps_error(_gen(5), (400, 3000), 0.1)
    on = (nlos != 0).all(-1)
    assert float(nlos[on].std()) == pytest.approx(30.0, rel=0.05)
    ok = SensorErrors(outage_rate=0.01, outage_duration=(10.0, 30.0)).gps_available(_gen(6), (400, 3000), 0.1)
    assert float(1.0 - ok[:, 400:].double().mean()) == pytest.approx(1 - math.exp(-0.01 * 20.0), abs=0.02)


def test_simulator_errors_reach_truth_and_measurements_consistently():
    base = simulate_p000(batch_size=4, seed=7, scenario="random", steps=800, dtype=f64)
    none = simulate_p000(batch_size=4, seed=7, scenario="random", steps=800, dtype=f64, errors=SensorErrors())
    assert torch.equal(base.measurements.nan_to_num(), none.measurements.nan_to_num())  # all off = the nominal data
    gyro = simulate_p000(batch_size=4, seed=7, scenario="random", steps=800, dtype=f64, errors=SensorErrors(gyro_turn_on_std=0.01))
    # the drift state of the truth carries the added bias, and the gyro reads it
    torch.testing.assert_close(gyro.measurements[..., 2] - gyro.truth[..., 6], base.measurements[..., 2] - base.truth[..., 6])
    assert float((gyro.truth[..., 6] - base.truth[..., 6]).std(1).max()) < 1e-12  # a constant per run
    slip = simulate_p000(batch_size=4, seed=7, scenario="random", steps=800, dtype=f64, errors=SensorErrors(slip_per_accel=0.05))
    speed = torch.sqrt(base.truth[..., 1] ** 2 + base.truth[..., 4] ** 2)
    clean = base.truth[..., 7] * 0.1 * speed
    extra = slip.measurements[..., 3] - base.measurements[..., 3]
    accel = (base.truth[..., 1] * base.truth[..., 2] + base.truth[..., 4] * base.truth[..., 5]) / speed  # d|v|/dt
    torch.testing.assert_close(extra, 0.05 * accel * clean, atol=2e-3, rtol=0.05)
    out = p000_simulator(batch_size=4, seed=7, scenario="random", steps=800, errors={"outage_rate": 0.05, "outage_duration": [5.0, 5.0]})
    assert not bool(out.mask[..., :2].all()) and bool(out.measurements[..., :2][~out.mask[..., :2]].isnan().all())


def _cv_model() -> torch.nn.Module:
    return tracking_model(dynamics=ConstantVelocity(axes=1, dt=1.0, q=2.0, dtype=f64), R=[0.5])


def test_literal_reuse_ukf_is_the_paper_update_without_q_in_the_measurement_moments():
    model = _cv_model()
    z = torch.tensor([[[1.0], [2.5], [2.0]]], dtype=f64)
    m0, p0 = torch.tensor([[0.0, 1.0]], dtype=f64), torch.diag(torch.tensor([1.0, 0.5], dtype=f64))[None]
    points = Julier(kappa=1.0)
    lit = LiteralReuseUKF(model, sigma_points=points)(z, m0, p0)
    ext = UKF(model, sigma_points=points, redraw_after_predict=False)(z, m0, p0)
    torch.testing.assert_close(ext.mean, KalmanFilter(model)(z, m0, p0).mean)  # the extension keeps it exact
    # the paper's equations on a linear model: P_zz = H F P F^T H^T + R, P_xz = F P F^T H^T, P- = F P F^T + Q
    f, h = model.dynamics.matrix(), model.measurement.matrix()
    q, r = model.dynamics.Q, model.measurement.R
    x, p = m0[0], p0[0]
    for k in range(3):
        spread = f @ p @ f.T
        pm, xm = spread + q, f @ x
        pzz, pxz = h @ spread @ h.T + r, spread @ h.T
        gain = pxz @ torch.linalg.inv(pzz)
        x = xm + gain @ (z[0, k] - h @ xm)
        p = pm - gain @ pzz @ gain.T
        torch.testing.assert_close(lit.mean[0, k], x)
        torch.testing.assert_close(lit.cov[0, k], p)
    assert not torch.allclose(lit.mean, ext.mean)


def test_per_axis_metric_and_divergence():
    truth = torch.zeros(4, 100, 2, dtype=f64)
    est = truth.clone()
    est[..., 0] = 2.0  # east error 2 m everywhere: RMSE 2, bias +2, variance over time 0
    est[3, :, 1] = 100.0  # one run lost in the north: diverged (tail RMSE 100 > 3 x 10)
    out = per_axis_metrics(est, truth, dt=1.0, sigma_gps=10.0, tail=10.0)
    assert out["rmse_mean_e"] == pytest.approx(2.0) and out["bias_e"] == pytest.approx(2.0) and out["rmse_var_e"] == pytest.approx(0.0)
    assert out["rmse_mean_n"] == pytest.approx(50.0) and out["diverged"] == pytest.approx(0.25)
    assert out["rmse_mean_n_ok"] == pytest.approx(0.0) and out["bias_e_ok"] == pytest.approx(2.0)
