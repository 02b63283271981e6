"""The time loop's deferred rounding check (StepInfo.rounding, made for blocks of steps) flags
exactly the steps that the step-by-step check flags."""

from __future__ import annotations

import torch

from difffilter.filters import UKF, KalmanFilter
from difffilter.filters.base import ROUNDING_BLOCK
from difffilter.models import LinearModel


def _model(dtype: torch.dtype) -> LinearModel:
    f = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=dtype)
    h = torch.tensor([[1.0, 0.0]], dtype=dtype)
    return LinearModel(F=f, H=h, Q=0.01 * torch.eye(2, dtype=dtype), R=torch.eye(1, dtype=dtype))


def test_block_check_flags_the_steps_the_step_by_step_check_flags():
    dtype = torch.float32
    steps = 2 * ROUNDING_BLOCK + 19  # two full blocks and a partial one
    bsz = 3
    # positions growing to 3e6: eps |z_hat| passes 1e-2 sqrt(S) part-way, at a different step
    # per trajectory; a few missing measurements
    ramp = torch.linspace(0.0, 1.0, steps, dtype=dtype) ** 2
    z = (torch.tensor([1e5, 1e6, 3e6], dtype=dtype)[:, None] * ramp)[..., None]
    mask = torch.ones(bsz, steps, dtype=torch.bool)
    mask[1, 100:110] = False
    m0, p0 = torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype)
    for filt in (KalmanFilter(_model(dtype)), UKF(_model(dtype))):
        filt.diffuse_prior = False
        res = filt(z, m0, p0, mask=mask)
        belief = filt.initial_belief(m0, p0, bsz)
        own = []
        for t in range(steps):
            belief, _, info = filt.step(belief, z[:, t], mask[:, t])
            own.append(info.untrusted)
        step_flags = torch.stack(own, 1)
        assert 0 < int(step_flags.sum()) < bsz * steps  # the case tests something
        # the run's flags are the steps' own ones plus the run-wide checks, which flag nothing here
        assert torch.equal(res.extras["untrusted"], step_flags)
