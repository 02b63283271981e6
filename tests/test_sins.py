"""Tests for experiments.papers.p003.sins (p003 20-state GPS/SINS error model)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from torch.func import jacfwd, vmap

from difffilter.filters import EKF, SimplifiedUKF
from difffilter.geometry import normal_gravity
from experiments.papers.constellation import CircularOrbitConstellation
from experiments.papers.p003 import make_p003_model, simulate_p003
from experiments.papers.p003.sins import SinsErrorDynamics, sins_error_matrix
from experiments.papers.p003.sins_measurement import SinsPseudorangeMeasurement

F64 = torch.float64


def _nav_inputs(batch: int = 3, k: int = 6, seed: int = 0, dtype: torch.dtype = F64) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    llh = torch.tensor([0.56, 2.07, 1000.0], dtype=F64) + torch.randn(batch, 3, generator=g, dtype=F64) * torch.tensor(
        [1e-2, 1e-2, 100], dtype=F64
    )
    sp, sv = CircularOrbitConstellation().state(torch.zeros(batch, dtype=F64))
    c = torch.linalg.qr(torch.randn(batch, 3, 3, generator=g, dtype=F64))[0]
    u = {
        "llh": llh,
        "vel": torch.randn(batch, 3, generator=g, dtype=F64) * 100,
        "f_n": torch.randn(batch, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 9.8], dtype=F64),
        "C_bn": c,
        "dt": torch.ones(batch, 1, dtype=F64),
        "sat_pos": sp[:, :k],
        "sat_vel": sv[:, :k],
    }
    return {key: v.to(dtype) for key, v in u.items()}


def _state(batch: int, metres: bool, scale: float = 1.0, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    sd = ([300.0, 300.0] if metres else [5e-5, 5e-5]) + [300.0, 5, 5, 5] + [1e-3] * 12 + [100.0, 1.0]
    return torch.randn(batch, 20, generator=g, dtype=F64) * torch.tensor(sd, dtype=F64) * scale


@pytest.mark.parametrize("metres", [False, True])
@pytest.mark.parametrize("linearized", [False, True])
def test_measurement_jacobian_matches_autograd(metres: bool, linearized: bool) -> None:
    model = SinsPseudorangeMeasurement(num_satellites=6, linearized=linearized, position_in_metres=metres)
    u = _nav_inputs()
    x = _state(3, metres)
    auto = vmap(jacfwd(model), in_dims=(0, 0))(x, u)
    ana = model.jacobian(x, u)
    # radian position columns reach 6e6 m/rad: compare them relatively, all others absolutely
    big = auto.abs() > 1.0
    assert torch.allclose(ana[~big], auto[~big], atol=1e-8, rtol=0)
    assert torch.allclose(ana[big], auto[big], rtol=1e-10, atol=0)


def test_linearized_and_nonlinear_forms() -> None:
    u = _nav_inputs()
    nonlin = SinsPseudorangeMeasurement(num_satellites=6, position_in_metres=True)
    lin = SinsPseudorangeMeasurement(num_satellites=6, position_in_metres=True, linearized=True)
    small, large = _state(3, True, 1e-3), _state(3, True, 10.0)
    # ranges: the paper's form is the first-order expansion (gap second order: |d|^2 / 2r)
    gap1 = (nonlin(small, u) - lin(small, u))[:, :6].abs().max()
    gap2 = (nonlin(2 * small, u) - lin(2 * small, u))[:, :6].abs().max()
    assert gap1 < 1e-6 and 3.9 < gap2 / gap1 < 4.1
    assert (nonlin(large, u) - lin(large, u))[:, :6].abs().max() > 1.0
    # rates: the paper also drops the line-of-sight change (e_I - e_G).(v - s'), a first-order
    # term, so the gap grows linearly with the error: 1e4 x larger error, ~1e4 x larger gap
    gap_small = (nonlin(small, u) - lin(small, u))[:, 6:].abs().max()
    gap_large = (nonlin(large, u) - lin(large, u))[:, 6:].abs().max()
    assert 2e3 < gap_large / gap_small < 5e4
    assert torch.allclose(lin.matrix(u), lin.jacobian(_state(3, True), u))
    assert nonlin.matrix(u) is None


def test_transition_is_matrix_exponential_and_series_converge() -> None:
    u = _nav_inputs()
    dyn = SinsErrorDynamics()
    F = dyn.continuous_matrix(u)
    for b in range(3):
        assert np.allclose(dyn.matrix(u)[b].numpy(), scipy.linalg.expm(F[b].numpy()), rtol=1e-10, atol=1e-14)
    u_small = dict(u, dt=torch.full((3, 1), 0.01, dtype=F64))
    second = SinsErrorDynamics(discretization="second").matrix(u_small)
    first = SinsErrorDynamics(discretization="first").matrix(u_small)
    exact = dyn.matrix(u_small)
    assert (second - exact).abs().max() < (first - exact).abs().max()
    x = _state(3, False)
    assert torch.allclose(dyn(x, u), (dyn.matrix(u) @ x[..., None])[..., 0])
    q = dyn.process_noise(x, u)
    assert torch.allclose(q, q.mT) and bool((torch.linalg.eigvalsh(q / q.diagonal(dim1=-2, dim2=-1).amax()) > -1e-12).all())


def test_batched_matrix_equals_loop_and_metre_units_are_similar() -> None:
    u = _nav_inputs()
    F = sins_error_matrix(u["llh"], u["vel"], u["f_n"], u["C_bn"], gyro_markov_time=3600.0, accel_markov_time=3600.0, clock_time=3600.0)
    for b in range(3):
        one = sins_error_matrix(
            u["llh"][b], u["vel"][b], u["f_n"][b], u["C_bn"][b], gyro_markov_time=3600.0, accel_markov_time=3600.0, clock_time=3600.0
        )
        # to rounding: a batched product may sum in another order than one matrix (1 ulp seen on an AVX-512 machine)
        torch.testing.assert_close(one, F[b], rtol=1e-13, atol=0.0)
    rad, met = SinsErrorDynamics(), SinsErrorDynamics(position_in_metres=True)
    # The same error expressed in metres propagates to the same error.  The metre scale is taken at
    # the INS position, which moves during the step (velocities ~100 m/s here): the error enters in
    # the scale of the previous position and leaves in the scale of the current one.
    a, e2 = 6378137.0, 6.69437999014e-3

    def scale(llh: torch.Tensor) -> torch.Tensor:
        lat, h = llh[:, 0], llh[:, 2]
        w = torch.sqrt(1 - e2 * torch.sin(lat) ** 2)
        out = torch.ones(3, 20, dtype=F64)
        out[:, 0] = a * (1 - e2) / w**3 + h
        out[:, 1] = (a / w + h) * torch.cos(lat)
        return out

    s_now = scale(u["llh"])
    vel = u["vel"]
    prev = u["llh"] - torch.stack([vel[:, 1] / s_now[:, 0], vel[:, 0] / s_now[:, 1], vel[:, 2]], -1)  # dt = 1 s
    x = _state(3, False)
    exact = rad(x, u) * s_now
    got = met(x * scale(prev), u)
    assert torch.allclose(got[:, 3:], exact[:, 3:], rtol=1e-6, atol=1e-12)
    assert (got[:, :3] - exact[:, :3]).abs().max() < 2e-4  # metres, on position errors of ~1 km
    # without the scale-rate term (frozen scale) the position error is off by ~1 cm per step
    frozen = met(x * s_now, u)
    assert (frozen[:, :3] - exact[:, :3]).abs().max() > 5e-3


def test_linear_prediction_builds_F_once_and_matches_the_separate_calls(monkeypatch: pytest.MonkeyPatch) -> None:
    import experiments.papers.p003.sins as sins

    u = _nav_inputs()
    u["feedback"] = _state(3, True, scale=0.01, seed=4)
    dyn = SinsErrorDynamics(position_in_metres=True)
    x = _state(3, True)
    calls = []
    real = sins.sins_error_matrix
    monkeypatch.setattr(sins, "sins_error_matrix", lambda *a, **k: calls.append(1) or real(*a, **k))
    xm, phi, qd = dyn.linear_prediction(x, u)
    assert len(calls) == 1
    torch.testing.assert_close(phi, dyn.matrix(u), rtol=0, atol=0)
    torch.testing.assert_close(qd, dyn.process_noise(x, u), rtol=0, atol=0)
    torch.testing.assert_close(xm, dyn(x, u), rtol=0, atol=0)
    # closed-loop feedback: the error restarts from x - feedback
    torch.testing.assert_close(xm, (phi @ (x - u["feedback"])[..., None])[..., 0])
    assert len(calls) == 4


def test_simplified_ukf_builds_F_once_per_predict_with_unchanged_results(monkeypatch: pytest.MonkeyPatch) -> None:
    import experiments.papers.p003.sins as sins
    from difffilter.filters.ukf import symmetrize
    from difffilter.mixers import IMM

    class ThreeCallSUKF(SimplifiedUKF):
        """The prediction as three separate model calls (matrix, process_noise, f)."""

        def predict(self, belief, u):  # type: ignore[no-untyped-def]
            mean, cov = belief["mean"], belief["cov"]
            f = self.model.dynamics.matrix(u)
            q = self.model.dynamics.process_noise(mean, u)
            return {**belief, "mean": self.model.dynamics(mean, u), "cov": symmetrize(f @ cov @ f.mT + q)}

    sc = simulate_p003(2, seed=3, duration=30, imu_rate=5, position_in_metres=True, feedback="imm")
    calls = []
    real = sins.sins_error_matrix
    monkeypatch.setattr(sins, "sins_error_matrix", lambda *a, **k: calls.append(1) or real(*a, **k))
    args = (sc.measurements, sc.initial_mean, sc.initial_cov)
    kw = {"mask": sc.mask, "controls": sc.controls}
    model = make_p003_model(position_in_metres=True)
    new = SimplifiedUKF(model)(*args, **kw)
    # forward builds F once for the whole [B, T] run (SinsErrorDynamics.precompute_controls) and every
    # predict, and the diffuse-prior check, read it
    assert len(calls) == 1
    calls.clear()
    old = ThreeCallSUKF(model)(*args, **kw)
    assert len(calls) == 1
    calls.clear()
    # without the precomputed entry (the model on one step's inputs) each of the three calls builds F
    one = {k: v[:, 0] for k, v in sc.controls.items()}
    ThreeCallSUKF(model).predict({"mean": sc.initial_mean, "cov": sc.initial_cov}, one)
    assert len(calls) == 3
    calls.clear()
    SimplifiedUKF(model).predict({"mean": sc.initial_mean, "cov": sc.initial_cov}, one)
    assert len(calls) == 1
    torch.testing.assert_close(new.mean, old.mean, rtol=0, atol=0)
    torch.testing.assert_close(new.cov, old.cov, rtol=0, atol=0)
    torch.testing.assert_close(new.log_likelihood, old.log_likelihood, rtol=0, atol=0)
    calls.clear()
    pi = torch.tensor([[0.95, 0.05], [0.05, 0.95]], dtype=F64)
    high = make_p003_model(q_scale=1e4, position_in_metres=True)
    imm = IMM([SimplifiedUKF(model), SimplifiedUKF(high)], pi, torch.tensor([0.9, 0.1], dtype=F64))
    imm(*args, **kw)
    assert len(calls) == 1  # one for both modes (same settings), every step and the diffuse-prior check


def test_schuler_oscillation_of_a_stationary_ins() -> None:
    """A north velocity error on a stationary INS oscillates at the Schuler period 2 pi sqrt(R/g)."""
    lat = math.radians(32.0)
    u = {
        "llh": torch.tensor([lat, 2.0, 0.0], dtype=F64),
        "vel": torch.zeros(3, dtype=F64),
        "f_n": torch.tensor([0.0, 0.0, normal_gravity(torch.tensor(lat), torch.tensor(0.0)).item()], dtype=F64),
        "C_bn": torch.eye(3, dtype=F64),
        "dt": torch.tensor([10.0], dtype=F64),
    }
    phi = SinsErrorDynamics(position_in_metres=True).matrix(u)
    x = torch.zeros(20, dtype=F64)
    x[4] = 1.0
    vn = []
    for _ in range(600):
        x = phi @ x
        vn.append(x[4].item())
    crossings = np.nonzero(np.diff(np.sign(vn)))[0]
    period_expected = 2 * math.pi * math.sqrt(6.371e6 / 9.79)
    first_zero = (crossings[0] + 1) * 10.0
    assert first_zero == pytest.approx(period_expected / 4, rel=0.03)
    assert abs(x[4].item()) < 1.05  # bounded, not growing


def test_measurement_model_reproduces_simulated_measurements_exactly() -> None:
    sc = simulate_p003(2, seed=4, duration=40, imu_rate=5, measurement_noise=False, position_in_metres=True)
    model = make_p003_model(position_in_metres=True)
    pred = model.measurement(sc.truth, sc.controls)
    assert (pred - sc.measurements).abs().max() < 1e-6


def test_error_model_tracks_the_strapdown_simulation() -> None:
    """Propagating the discrete error model from the true initial error reproduces the INS-minus-
    truth errors of the independent mechanisation (deterministic sensor errors, 300 s)."""
    sc = simulate_p003(1, seed=7, duration=300, imu_rate=5, imu_noise=False, measurement_noise=False, position_in_metres=True)
    dyn = make_p003_model(position_in_metres=True).dynamics
    x = sc.initial_truth
    pred = []
    for k in range(sc.truth.shape[1]):
        x = dyn(x, {key: v[:, k] for key, v in sc.controls.items()})
        pred.append(x)
    pred_t = torch.stack(pred, 1)
    scale = sc.truth[..., :9].abs().amax(1)
    rel = ((pred_t[..., :9] - sc.truth[..., :9]).abs().amax(1) / scale).max()
    assert rel < 0.03
    assert sc.truth[0, -1, :3].norm() > 3 * sc.initial_truth[0, :3].norm()  # free-inertial growth


def test_filters_run_and_reduce_error_float32_and_float64() -> None:
    sc = simulate_p003(1, seed=2, duration=25, imu_rate=5, position_in_metres=True)  # noise "nominal": nothing switches
    model = make_p003_model(position_in_metres=True)
    res = SimplifiedUKF(model)(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    err = (res.mean - sc.truth)[0, -5:, :6].abs().mean(0)
    prior_sd = sc.initial_cov.diagonal(dim1=-2, dim2=-1)[0, :6].sqrt()
    assert bool((err < 0.5 * prior_sd).all())
    ekf = EKF(model)(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    assert torch.allclose(ekf.mean[..., :6], res.mean[..., :6], atol=0.05)
    sc32 = simulate_p003(1, seed=2, duration=25, imu_rate=5, dtype=torch.float32, position_in_metres=True)
    model32 = make_p003_model(position_in_metres=True, dtype=torch.float32)
    res32 = EKF(model32)(sc32.measurements, sc32.initial_mean, sc32.initial_cov, mask=sc32.mask, controls=sc32.controls)
    assert res32.mean.dtype == torch.float32 and bool(torch.isfinite(res32.mean).all())


def test_scalar_noise_scales_are_learnable() -> None:
    model = make_p003_model(q_scale=4.0, r_scale=9.0)
    base = make_p003_model()
    assert torch.allclose(model.Q, 4.0 * base.Q) and torch.allclose(model.R, 9.0 * base.R)
    names = {n for n, _ in model.named_parameters()}
    assert any("Q" in n for n in names) and any("R" in n for n in names)
