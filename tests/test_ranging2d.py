"""The 2-D ranging model (difffilter.models.navigation.ranging2d): analytic Jacobians against
finite differences in float64, the process noise against its closed form, the gate and bias, the
snapshot multilateration against noise-free geometry, and gradients through the EKF against
finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF
from difffilter.models.navigation import OdometryDynamics2D, RangeMeasurement2D, make_ranging_model
from difffilter.models.navigation.ranging2d import multilateration

D = torch.float64
ANCHORS = torch.tensor([[0.0, 0.0], [20.0, 0.0], [20.0, 15.0], [-5.0, 12.0]], dtype=D)


def _fd(fn, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    cols = []
    for i in range(x.shape[-1]):
        dx = torch.zeros_like(x)
        dx[..., i] = eps
        cols.append((fn(x + dx) - fn(x - dx)) / (2 * eps))
    return torch.stack(cols, -1)


def _controls(b: int = 3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(b, 3, 3, generator=g, dtype=D) * 0.1
    return {
        "odom": torch.randn(b, 3, generator=g, dtype=D),
        "odom_cov": a @ a.transpose(-1, -2) + 0.01 * torch.eye(3, dtype=D),
        "dt": torch.rand(b, 1, generator=g, dtype=D) + 0.1,
        "anchors": ANCHORS.expand(b, 4, 2),
        "range_var": torch.full((b, 4), 0.25, dtype=D),
        "z_obs": torch.full((b, 4), 10.0, dtype=D),
    }


def test_jacobians_match_finite_differences() -> None:
    u = _controls()
    x = torch.tensor([[3.0, 4.0, 0.3], [10.0, -2.0, 2.9], [-1.0, 7.0, -1.2]], dtype=D)
    dyn = OdometryDynamics2D()
    assert torch.allclose(dyn.jacobian(x, u), _fd(lambda v: dyn(v, u), x), atol=1e-8)
    meas = RangeMeasurement2D(num_anchors=4)
    with torch.no_grad():
        meas.range_bias = torch.tensor([0.5, -1.0, 2.0, 0.0], dtype=D)
    assert torch.allclose(meas.jacobian(x, u), _fd(lambda v: meas(v, u), x), atol=1e-8)
    expect = (x[:, None, :2] - ANCHORS).norm(dim=-1) + torch.tensor([0.5, -1.0, 2.0, 0.0], dtype=D)
    assert torch.allclose(meas(x, u), expect)


def test_process_noise_is_the_odometry_covariance_mapped_plus_the_psd() -> None:
    u = _controls()
    dyn = OdometryDynamics2D(odom_scale=2.0, process_psd=(1e-3, 2e-3, 1e-5))
    x = torch.tensor([[0.0, 0.0, 0.7]] * 3, dtype=D)
    q = dyn.process_noise(x, u)
    # G = d f / d odom, by finite differences of f in the odometry
    g = _fd(lambda o: dyn(x, {**u, "odom": o}), u["odom"])
    expect = 2.0 * g @ u["odom_cov"] @ g.transpose(-1, -2) + torch.diag_embed(torch.tensor([1e-3, 2e-3, 1e-5], dtype=D) * u["dt"])
    assert torch.allclose(q, expect, atol=1e-12) and torch.allclose(q, q.transpose(-1, -2))
    assert bool((torch.linalg.eigvalsh(q) > 0).all())
    with pytest.raises(ValueError, match="odom_scale must be > 0"):
        OdometryDynamics2D(odom_scale=0.0)


def test_gate_inflates_only_outlying_ranges_and_modes_are_checked() -> None:
    u = _controls(1)
    model = make_ranging_model(num_anchors=4, gate="soft", gate_threshold=3.0, gate_floor=0.5, gate_softness=0.05)
    x = torch.tensor([[5.0, 5.0, 0.0]], dtype=D)
    h = model.measurement(x, u)
    u["z_obs"] = h + torch.tensor([[0.1, 0.0, 10.0, -0.2]], dtype=D)
    r = torch.diagonal(model.measurement.measurement_noise(x, u), dim1=-2, dim2=-1)[0]
    assert torch.allclose(r[[0, 1, 3]], torch.full((3,), 0.25, dtype=D), rtol=1e-3) and r[2] > 1e4
    assert not hasattr(RangeMeasurement2D(num_anchors=4, bias=None, noise=None), "range_bias")
    assert RangeMeasurement2D(num_anchors=4, bias="shared").range_bias.shape == (1,)
    with pytest.raises(ValueError, match="bias must be 'anchor', 'shared' or None"):
        RangeMeasurement2D(num_anchors=4, bias="per")
    with pytest.raises(ValueError, match="gate must be"):
        make_ranging_model(num_anchors=4, gate="wide")


def test_multilateration_recovers_noise_free_positions_and_needs_three_ranges() -> None:
    p = torch.tensor([[3.0, 4.0], [15.0, 9.0], [1.0, 1.0]], dtype=D)
    z = (p[:, None] - ANCHORS).norm(dim=-1)
    mask = torch.ones(3, 4, dtype=torch.bool)
    mask[2, :2] = False
    fix = multilateration(z, torch.full_like(z, 0.25), mask, ANCHORS.expand(3, 4, 2))
    assert torch.allclose(fix[:2], p[:2], atol=1e-8) and bool(fix[2].isnan().all())


def test_gradients_through_the_ekf_match_finite_differences() -> None:
    torch.manual_seed(0)
    b, t = 2, 12
    u = {k: v[:1].expand(b, *v.shape[1:])[:, None].expand(b, t, *v.shape[1:]).clone() for k, v in _controls(1).items()}
    truth = torch.stack([torch.linspace(2, 8, t, dtype=D), torch.linspace(3, 5, t, dtype=D)], -1).expand(b, t, 2)
    z = (truth[..., None, :] - ANCHORS).norm(dim=-1) + 0.3 + 0.2 * torch.randn(b, t, 4, dtype=D)
    u["z_obs"] = z
    mask = torch.ones(b, t, 4, dtype=torch.bool)
    mask[1, 3:6, 2] = False
    z = torch.where(mask, z, torch.full_like(z, math.nan))  # NaN under a False mask must not leak
    filt = EKF(make_ranging_model(num_anchors=4, gate="soft", gate_floor=1.0))
    m0 = torch.tensor([[2.0, 3.0, 0.3]] * b, dtype=D)
    p0 = torch.diag(torch.tensor([1.0, 1.0, 0.05], dtype=D)).expand(b, 3, 3)

    def loss() -> torch.Tensor:
        res = filt(z, m0, p0, mask=mask, controls=u)
        return (res.mean[..., :2] - truth).pow(2).sum()

    params = dict(filt.named_parameters())
    grads = torch.autograd.grad(loss(), list(params.values()))
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    for (name, p), g in zip(params.items(), grads, strict=True):
        i = 0
        with torch.no_grad():
            old = p.reshape(-1)[i].item()
            p.reshape(-1)[i] = old + 1e-6
            up = loss()
            p.reshape(-1)[i] = old - 1e-6
            down = loss()
            p.reshape(-1)[i] = old
        assert float(g.reshape(-1)[i]) == pytest.approx(float((up - down) / 2e-6), rel=1e-4, abs=1e-8), name
