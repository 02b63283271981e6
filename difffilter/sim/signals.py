"""Signal helpers of the simulators: smoothing and integration on uniform time grids."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["cumtrapz", "moving_average"]


def cumtrapz(y: Tensor, h: float, y0: Tensor) -> Tensor:
    """Cumulative trapezoidal integral of samples ``y [..., N]`` spaced ``h`` apart, starting at
    ``y0 [...]``: ``[..., N]`` with ``out[..., 0] = y0``."""
    inc = 0.5 * h * (y[..., 1:] + y[..., :-1])
    return torch.cat([y0[..., None], y0[..., None] + torch.cumsum(inc, -1)], -1)


def moving_average(x: Tensor, width: int) -> Tensor:
    """Centred moving average along the last axis with edge padding (an even ``width`` is
    rounded up to the next odd one, so the window is symmetric)."""
    width += 1 - width % 2
    pad = width // 2
    xp = torch.cat([x[..., :1].expand(*x.shape[:-1], pad), x, x[..., -1:].expand(*x.shape[:-1], width - 1 - pad)], -1)
    c = torch.cumsum(torch.nn.functional.pad(xp, (1, 0)), -1)
    return (c[..., width:] - c[..., :-width]) / width
