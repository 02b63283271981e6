"""Issue 17, defect 5, in the smoothers: the backward step of an angular state near +-pi.

A heading and turn-rate track crosses the +-pi cut.  Reference that cannot share a wrapping
bug: the same scene rotated by pi (every heading and measurement shifted by pi) never comes
near the cut, so plain arithmetic is right there; the smoothed headings near the cut must be
that result rotated back, to rounding.  A backward step with plain differences jumps by
2 pi across the cut (checked below, so the comparison can fail).
"""

from __future__ import annotations

import math

import pytest
import torch

from difffilter.filters import EKF, UKF
from difffilter.models import FunctionalModel
from difffilter.models.base import wrap_angle
from difffilter.smoothers import FixedLagSmoother, RTSSmoother
from difffilter.smoothers.base import rts_backward

F64 = torch.float64
DT = 0.5


def heading_rate_model(angular: bool = True) -> FunctionalModel:
    return FunctionalModel(
        f=lambda x: torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1]], -1),
        h=lambda x: x[..., :1],
        Q=torch.diag(torch.tensor([1e-3, 1e-3], dtype=F64)),
        R=torch.tensor([[0.05**2]], dtype=F64),
        angular_states=(0,) if angular else (),
        angular_measurements=(0,),
    )


def scene(shift: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Headings turning through pi at 0.1 rad/s, measured with seeded noise, all shifted by ``shift``."""
    g = torch.Generator().manual_seed(2)
    t = torch.arange(12, dtype=F64)
    heading = math.pi - 0.5 + 0.05 * DT * t * 2 + 0.05 * torch.randn(12, generator=g, dtype=F64)
    z = wrap_angle(heading + shift)[None, :, None]
    m0 = torch.tensor([float(wrap_angle(torch.tensor(math.pi - 0.55 + shift, dtype=F64))), 0.1], dtype=F64)
    p0 = torch.diag(torch.tensor([0.1**2, 0.05**2], dtype=F64))
    return z, m0, p0


SMOOTHERS = {
    "urts": lambda m: RTSSmoother(UKF(m)),
    "erts": lambda m: RTSSmoother(EKF(m)),
    "fixed_lag_ukf": lambda m: FixedLagSmoother(UKF(m), lag=3),
}


def smoothed(name: str, shift: float, angular: bool = True) -> torch.Tensor:
    z, m0, p0 = scene(shift)
    return SMOOTHERS[name](heading_rate_model(angular))(z, m0, p0).mean[0]


@pytest.mark.parametrize("name", list(SMOOTHERS))
def test_smoothed_heading_near_pi_equals_the_scene_rotated_away_from_the_cut(name):
    near_pi = smoothed(name, 0.0)
    away = smoothed(name, -math.pi)  # headings near 0: no wrap anywhere
    assert bool(((near_pi[:, 0] > 2.5) | (near_pi[:, 0] < -2.5)).all())  # the track does straddle the cut
    assert bool((near_pi[:, 0] > 0).any() and (near_pi[:, 0] < 0).any())
    torch.testing.assert_close(wrap_angle(near_pi[:, 0] - away[:, 0] - math.pi), torch.zeros(12, dtype=F64), rtol=0, atol=1e-9)
    torch.testing.assert_close(near_pi[:, 1], away[:, 1], rtol=0, atol=1e-9)
    assert bool(((near_pi[:, 0] > -math.pi) & (near_pi[:, 0] <= math.pi)).all())


def test_plain_differences_in_the_backward_step_fail_near_pi():
    """The filter's posteriors are wrapped, so a backward step that subtracts headings plainly
    (no ``space``) jumps by 2 pi across the cut: the check above would catch it."""
    z, m0, p0 = scene(0.0)
    smoother = RTSSmoother(UKF(heading_rate_model()))
    with torch.no_grad():
        result = smoother.filter(z, m0, p0)
        initial = {"mean": m0[None], "cov": p0[None]}
        gains, prior_cov = smoother.gains(result, initial)
        args = (result.mean, result.cov, result.prior_mean, prior_cov, gains, m0[None], p0[None])
        wrapped = rts_backward(*args, smoother.dynamics)[0][0]
        plain = rts_backward(*args)[0][0]
    torch.testing.assert_close(wrapped, smoothed("urts", 0.0).detach(), rtol=0, atol=1e-12)
    assert float((plain - wrapped).abs().max()) > 1.0  # heading and turn rate move by a multiple of the 2 pi jump
