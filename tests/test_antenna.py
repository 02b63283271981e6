"""Lever arm and receiver time offset (difffilter.models.navigation.antenna) in the pseudorange
model (odometry layout) and the GNSS/IMU fix: the measured position moves to p + C l - tau v, the
analytic pseudorange Jacobian equals autodiff, absent options leave the models unchanged, and
both quantities are recovered by back-propagation from noise-free measurements."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacfwd, vmap

from difffilter.filters import EKF
from difffilter.geometry import geodetic_to_ecef
from difffilter.models.navigation.antenna import planar_rotation
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from experiments.papers.p004.model import GnssImuModel, GnssMeasurement

F64 = torch.float64


def _scene(n: int = 6, k: int = 7, seed: int = 0) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origin = geodetic_to_ecef(torch.tensor([math.radians(52.5), math.radians(13.4), 70.0], dtype=F64))
    x = torch.cat(
        [
            torch.randn(n, 3, generator=g, dtype=F64) * 50,
            torch.rand(n, 1, generator=g, dtype=F64) * 6.0,
            torch.randn(n, 3, generator=g, dtype=F64),
        ],
        -1,
    )
    az = torch.rand(n, k, generator=g, dtype=F64) * 2 * math.pi
    el = 0.2 + torch.rand(n, k, generator=g, dtype=F64) * 1.2
    sat = 2.2e7 * torch.stack([torch.cos(el) * torch.sin(az), torch.cos(el) * torch.cos(az), torch.sin(el)], -1)
    u = {
        "sat_pos": sat,
        "glonass": (torch.rand(n, k, generator=g) < 0.5).to(F64),
        "speed": 3.0 + 5 * torch.rand(n, 1, generator=g, dtype=F64),
    }
    return x, u, origin


def _meas(origin: torch.Tensor, **kw) -> PseudorangeMeasurement:  # type: ignore[no-untyped-def]
    return PseudorangeMeasurement(
        num_satellites=7, layout=GnssStateLayout.odometry(), sagnac=True, frame_origin=origin, frame="enu", reduced=True, **kw
    )


def test_pseudorange_antenna_shifts_the_position_and_jacobian_matches_autodiff() -> None:
    x, u, origin = _scene()
    plain = _meas(origin)
    arm, tau = [1.4, -0.3, 0.8], 0.12
    moved = _meas(origin, lever_arm=arm, latency=tau)
    yaw, speed = x[:, 3], u["speed"][:, 0]
    shift = (planar_rotation(yaw) @ torch.tensor(arm, dtype=F64)[:, None])[..., 0]
    shift = shift - tau * torch.stack([speed * torch.cos(yaw), speed * torch.sin(yaw), torch.zeros_like(yaw)], -1)
    x_shifted = x.clone()
    x_shifted[:, :3] += shift
    torch.testing.assert_close(moved(x, u), plain(x_shifted, u), rtol=0, atol=1e-7)
    with torch.no_grad():
        auto = vmap(jacfwd(lambda xi, ui: moved(xi, ui)))(x, u)
    torch.testing.assert_close(moved.jacobian(x, u).detach(), auto, rtol=1e-7, atol=1e-9)
    assert float(auto[..., 3].abs().max()) > 0.5  # the yaw column is not trivially zero
    assert not hasattr(plain, "lever_arm") and "latency" not in dict(plain.named_parameters())
    with pytest.raises(ValueError, match="yaw state"):
        PseudorangeMeasurement(num_satellites=7, layout=GnssStateLayout.constant_velocity(), lever_arm=[1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="inside"):
        _meas(origin, latency=2.0)


def test_lever_arm_and_latency_are_recovered_by_backpropagation() -> None:
    """Noise-free pseudoranges of a known antenna (lever arm [1.2, -0.4, 0.9] m, 0.15 s): fitting
    the model's lever arm and latency by gradient descent from zero recovers them."""
    x, u, origin = _scene(n=60, seed=1)
    truth = _meas(origin, lever_arm=[1.2, -0.4, 0.9], latency=0.15)
    with torch.no_grad():
        z = truth(x, u)
    model = _meas(origin, lever_arm=[0.0, 0.0, 0.0], latency=0.0)
    opt = torch.optim.LBFGS(
        model.parameters(), lr=0.5, max_iter=200, tolerance_grad=1e-14, tolerance_change=1e-16, line_search_fn="strong_wolfe"
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = (model(x, u) - z).pow(2).mean()
        loss.backward()
        return loss

    for _ in range(5):  # the forward arm and latency x speed are nearly collinear: slow but exact
        opt.step(closure)
    torch.testing.assert_close(model.lever_arm.detach(), torch.tensor([1.2, -0.4, 0.9], dtype=F64), rtol=0, atol=1e-4)
    assert float(model.latency.detach()) == pytest.approx(0.15, abs=1e-4)


@pytest.mark.parametrize("planar", [True, False])
def test_gnss_imu_fix_with_lever_arm_and_latency(planar: bool) -> None:
    g = torch.Generator().manual_seed(2)
    n = 8 if planar else 16
    x = torch.randn(5, n, generator=g, dtype=F64)
    if not planar:
        x[:, 6:10] = x[:, 6:10] / x[:, 6:10].norm(dim=-1, keepdim=True)
    arm, tau = [0.8, 0.2, -0.5], 0.05
    plain = GnssMeasurement(planar=planar, velocity=True, dtype=F64)
    fix = GnssMeasurement(planar=planar, velocity=True, lever_arm=arm, latency=tau, dtype=F64)
    assert plain.matrix() is not None and fix.matrix() is None and fix.jacobian(x) is None
    if planar:
        yaw = math.pi / 2 - x[:, 4]
        c, s = torch.cos(yaw), torch.sin(yaw)
        shift = torch.stack([c * arm[0] - s * arm[1], s * arm[0] + c * arm[1]], -1) - tau * x[:, 2:4]
        d = 2
    else:
        w, qx, qy, qz = x[:, 6:10].unbind(-1)
        rot = torch.stack(
            [
                torch.stack([1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)], -1),
                torch.stack([2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)], -1),
                torch.stack([2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)], -1),
            ],
            -2,
        )
        shift = (rot @ torch.tensor(arm, dtype=F64)[:, None])[..., 0] - tau * x[:, 3:6]
        d = 3
    expect = plain(x).clone()
    expect[:, :d] += shift
    torch.testing.assert_close(fix(x).detach(), expect)
    # an EKF runs on the model (autodiff Jacobian) and the antenna terms get gradients
    model = GnssImuModel(planar=planar, velocity=True, lever_arm=arm, latency=tau, dtype=F64)
    steps = 4
    k = 2 if planar else 3
    controls = {"accel": torch.zeros(1, steps, k, dtype=F64), "gyro": torch.zeros(1, steps, 1 if planar else 3, dtype=F64)}
    mean0 = torch.tensor(model.defaults.initial_mean, dtype=F64)[None]
    cov0 = torch.diag(torch.tensor(model.defaults.initial_var, dtype=F64))[None]
    z = torch.randn(1, steps, model.measurement_dim, generator=g, dtype=F64)
    res = EKF(model)(z, mean0, cov0, controls=controls)
    res.log_likelihood.sum().backward()
    raws = dict(model.measurement.named_parameters())
    assert all(float(raws[f"parametrizations.{n}.original"].grad.abs().sum()) > 0 for n in ("lever_arm", "latency"))
