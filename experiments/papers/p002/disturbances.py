"""Abrupt heading disturbances of p002's walks, which the RC-UKF's fading factor exists for.

* :func:`arc_bursts` - compass-interference bursts: stretches of the walk near magnetic
  disturbances (steel structures, parked cars, electrical installations) where the compass carries
  an extra large error (p002's electromagnet test: 49.7 deg RMSE against 11.4 deg undisturbed);
* :func:`turn_heading_error` - heading transients at turns: the gyro's heading change over a turn
  is off by a per-turn relative error (p002's table 1).

Both draw from the simulator's generator (a seed gives the same disturbances).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["arc_bursts", "turn_heading_error"]


def arc_bursts(gen: torch.Generator, arc: Tensor, rate: float, length: tuple[float, float]) -> Tensor:
    """``[B, T]`` True where an event's arc length ``arc [B, T]`` (m) lies in a burst: a Poisson
    number (mean ``rate`` per metre of the walk's length) of bursts per walk, each starting
    uniformly along the walk and lasting ``U(length)`` metres."""
    b = arc.shape[0]
    total = arc[:, -1].clamp_min(0.0)
    counts = torch.poisson(rate * total, generator=gen).long()
    out = torch.zeros_like(arc, dtype=torch.bool)
    lo, hi = length
    for j in range(int(counts.max()) if counts.numel() else 0):
        start = torch.rand(b, generator=gen, dtype=torch.float64) * total
        stop = start + lo + (hi - lo) * torch.rand(b, generator=gen, dtype=torch.float64)
        out |= (arc >= start[:, None]) & (arc < stop[:, None]) & (j < counts)[:, None]
    return out


def turn_heading_error(gen: torch.Generator, dpsi: Tensor, scale_std: float, threshold: float) -> Tensor:
    """``[B, T]`` gyro heading-increment error during turns: each turn (a run of consecutive steps
    whose true heading change ``|dpsi|`` exceeds ``threshold``) gets its own relative error
    ``s ~ N(0, scale_std^2)``, so the gyro reports ``(1 + s) dpsi`` over the turn.

    p002's table 1 (gyro heading change over twelve 45/90/180 deg turns against the actual turn)
    shows such errors: 4-24 deg, RMS 9 % of the turn angle, mean ~0 (the phone yawing against the
    body while the walker turns).
    """
    turning = dpsi.abs() > threshold
    starts = turning & ~torch.cat([torch.zeros_like(turning[:, :1]), turning[:, :-1]], 1)
    episode = starts.long().cumsum(1)  # 1, 2, ... inside the k-th turn (0 before the first)
    scale = scale_std * torch.randn(dpsi.shape, generator=gen, dtype=torch.float64)
    per_step = torch.gather(scale, 1, (episode - 1).clamp_min(0))
    return torch.where(turning, per_step * dpsi, torch.zeros_like(dpsi))
