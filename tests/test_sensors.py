"""Multi-rate, multi-sensor measurement: IMU (accelerations) at 100 Hz and GNSS (positions) at
10 Hz on a 100 Hz step grid, built from per-sensor streams without padding by hand; the joint
masked update equals the dense joint Gaussian of the samples that exist, and sequential updates
equal the joint update on linear models."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, UKF, KalmanFilter, SequentialUpdate
from difffilter.models import FunctionalModel, MultiSensorMeasurement, StateSpaceModel, align_streams, event_times, linear_measurement
from difffilter.models.motion import ConstantAcceleration
from difffilter.smoothers import RTSSmoother
from tests.smoother_reference import dense_smoother

F64 = torch.float64


def imu_gnss_model():
    dyn = ConstantAcceleration(axes=2, dt=0.01, q=4.0, dtype=F64)  # state [px, vx, ax, py, vy, ay]
    imu = linear_measurement(R=[0.05, 0.05], state_dim=6, observed=[2, 5])
    gnss = linear_measurement(R=[4.0, 4.0], state_dim=6, observed=[0, 3])
    sensors = MultiSensorMeasurement({"imu": imu, "gnss": gnss}, rates={"imu": 100.0, "gnss": 10.0})
    return StateSpaceModel(dyn, sensors)


def imu_gnss_streams(B=2, seconds=1.0, seed=0, jitter=0.0):
    g = torch.Generator().manual_seed(seed)
    n_imu, n_gnss = round(100 * seconds), round(10 * seconds)
    t_imu = torch.arange(1, n_imu + 1, dtype=F64) / 100
    t_gnss = torch.arange(1, n_gnss + 1, dtype=F64) / 10 + jitter * torch.randn(n_gnss, generator=g, dtype=F64)
    acc = torch.randn(B, n_imu, 2, generator=g, dtype=F64)
    pos = 5 * torch.randn(B, n_gnss, 2, generator=g, dtype=F64)
    return {"imu": (t_imu, acc), "gnss": (t_gnss, pos)}, t_imu


def test_streams_land_on_the_right_steps():
    model = imu_gnss_model()
    streams, grid_t = imu_gnss_streams(jitter=0.002)
    grid = align_streams(streams, grid_t, sensors=model.measurement)
    assert grid.measurements.shape == (2, 100, 4) and grid.mask.shape == (2, 100, 4)
    assert grid.slices == {"imu": slice(0, 2), "gnss": slice(2, 4)}
    assert bool(grid.mask[..., :2].all())
    gnss_steps = grid.mask[0, :, 2].nonzero().flatten()
    assert gnss_steps.tolist() == [10 * k + 9 for k in range(10)]  # 0.1 s, 0.2 s, ... = steps 9, 19, ...
    torch.testing.assert_close(grid.measurements[:, gnss_steps, 2:], streams["gnss"][1])
    assert bool(torch.isnan(grid.measurements[:, 0, 2:]).all())
    torch.testing.assert_close(grid.dt, torch.full((2, 100), 0.01, dtype=F64))
    # the sensors' rates give the same mask on a uniform grid
    assert torch.equal(model.measurement.rate_mask(100, 100.0, batch_size=2), grid.mask)


def test_per_trajectory_streams_out_of_grid_samples_and_conflicts():
    grid_t = torch.arange(1, 11, dtype=F64)
    times = torch.tensor([[1.1, 3.0, math.nan], [2.0, 9.6, 20.0]], dtype=F64)  # NaN pads the shorter stream
    vals = torch.arange(6, dtype=F64).reshape(2, 3, 1)
    grid = align_streams({"a": (times, vals)}, grid_t)
    assert grid.mask[0, :, 0].nonzero().flatten().tolist() == [0, 2]
    assert grid.mask[1, :, 0].nonzero().flatten().tolist() == [1, 9]  # 9.6 is within half a step of 10
    assert grid.measurements[1, 9, 0].item() == 4.0 and grid.measurements[0, 2, 0].item() == 1.0
    assert grid.dropped == {"a": 1}  # 20.0 is beyond every step
    with pytest.raises(ValueError, match="share a step"):
        align_streams({"a": (torch.tensor([1.0, 1.2]), torch.zeros(2, 1))}, grid_t)
    last = align_streams({"a": (torch.tensor([1.2, 0.9]), torch.tensor([[5.0], [7.0]]))}, grid_t, on_conflict="last")
    assert float(last.measurements[0, 0, 0]) == 5.0 and last.superseded == {"a": 1}
    with pytest.raises(ValueError, match="unknown sensors"):
        align_streams({"b": (grid_t, torch.zeros(10, 1))}, grid_t, sensors=["a"])
    torch.testing.assert_close(
        event_times({"x": (torch.tensor([3.0, 1.0]), None), "y": (torch.tensor([1.0, 2.0]), None)}),
        torch.tensor([1.0, 2.0, 3.0], dtype=F64),
    )


def test_joint_and_sequential_updates_equal_the_dense_joint_gaussian():
    model = imu_gnss_model()
    streams, grid_t = imu_gnss_streams(seconds=0.3, seed=1)
    grid = align_streams(streams, grid_t, sensors=model.measurement)
    m0 = torch.zeros(6, dtype=F64)
    p0 = torch.diag(torch.tensor([25.0, 4.0, 1.0, 25.0, 4.0, 1.0], dtype=F64))
    joint = RTSSmoother(KalmanFilter(model))(grid.measurements, m0, p0, mask=grid.mask)
    seq = RTSSmoother(SequentialUpdate(KalmanFilter(model)))(grid.measurements, m0, p0, mask=grid.mask)
    for name in ("mean", "cov"):
        torch.testing.assert_close(getattr(seq, name), getattr(joint, name), rtol=0, atol=1e-10)
        torch.testing.assert_close(getattr(seq.filtered, name), getattr(joint.filtered, name), rtol=0, atol=1e-10)
    torch.testing.assert_close(seq.filtered.log_likelihood, joint.filtered.log_likelihood, rtol=0, atol=1e-10)
    with torch.no_grad():
        f = model.dynamics.matrix(None).numpy()
        q = model.dynamics.process_noise(m0).numpy()
        h = model.measurement.matrix(None).numpy()
        r = model.measurement.measurement_noise(m0).numpy()
    for b in range(2):
        ref = dense_smoother(grid.measurements[b].numpy(), m0.numpy(), p0.numpy(), f, h, q, r, mask=grid.mask[b].numpy())
        np.testing.assert_allclose(joint.mean[b].detach().numpy(), ref["mean"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(joint.cov[b].detach().numpy(), ref["cov"], rtol=0, atol=1e-10)
        assert joint.filtered.log_likelihood[b].sum().item() == pytest.approx(ref["log_likelihood"], abs=1e-9)


def test_sensors_of_different_dimensions_stack_jacobians_noise_and_residuals():
    one = linear_measurement(R=[2.0], state_dim=6, observed=[1])
    two = linear_measurement(R=[4.0, 9.0], state_dim=6, observed=[0, 3])
    both = MultiSensorMeasurement({"speed": one, "gnss": two})
    x = torch.randn(5, 3, 6, dtype=F64)
    h = torch.zeros(3, 6, dtype=F64)
    h[0, 1] = h[1, 0] = h[2, 3] = 1.0
    torch.testing.assert_close(both.jacobian(x), h.expand(5, 3, 3, 6))
    torch.testing.assert_close(both.matrix(), h)
    torch.testing.assert_close(both(x), x @ h.T)
    torch.testing.assert_close(both.measurement_noise(x[0]), torch.diag(torch.tensor([2.0, 4.0, 9.0], dtype=F64)))
    assert both.component_groups() == [[0], [1, 2]]
    mask = both.expand_mask({"gnss": torch.tensor([[True, False]])})
    assert mask.tolist() == [[[False, True, True], [False, False, False]]]


def test_nonlinear_sensors_sequential_and_joint_agree_closely_and_learn():
    dyn = ConstantAcceleration(axes=2, dt=0.1, q=1.0, dtype=F64)
    rng = FunctionalModel(
        f=lambda x: x, h=lambda x: x[..., [0, 3]].norm(dim=-1, keepdim=True), Q=torch.eye(6, dtype=F64), R=torch.tensor([[0.5]], dtype=F64)
    )
    gnss = linear_measurement(R=[9.0, 9.0], state_dim=6, observed=[0, 3])
    sensors = MultiSensorMeasurement({"range": rng.measurement, "gnss": gnss}, rates={"range": 10.0, "gnss": 2.0})
    model = StateSpaceModel(dyn, sensors)
    mask = sensors.rate_mask(40, 10.0, batch_size=3)
    g = torch.Generator().manual_seed(3)
    z = torch.cat([30 + torch.randn(3, 40, 1, generator=g, dtype=F64), 20 + 3 * torch.randn(3, 40, 2, generator=g, dtype=F64)], -1)
    z = torch.where(mask, z, torch.nan)
    m0 = torch.tensor([20.0, 0.0, 0.0, 20.0, 0.0, 0.0], dtype=F64)
    p0 = torch.diag(torch.tensor([9.0, 1.0, 1.0, 9.0, 1.0, 1.0], dtype=F64))
    for make in (EKF, UKF):
        joint = make(model)(z, m0, p0, mask=mask)
        seq = SequentialUpdate(make(model))(z, m0, p0, mask=mask)
        # relinearising after the first sensor changes the nonlinear update only slightly here
        diff = (seq.mean - joint.mean).abs().max().item()
        assert 0.0 < diff < 0.05
    res = SequentialUpdate(EKF(model))(z, m0, p0, mask=mask)
    res.log_likelihood.sum().backward()
    raw = sensors.sensors["gnss"].parametrizations.R.original
    assert raw.grad is not None and torch.isfinite(raw.grad).all()
    with pytest.raises(ValueError, match="partition"):
        SequentialUpdate(EKF(model), groups=[[0], [1]])
