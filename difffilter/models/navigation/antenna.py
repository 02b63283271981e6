"""Where the GNSS antenna is when its measurement was taken: lever arm and receiver time offset.

A GNSS receiver measures the position of its antenna, not of the vehicle's reference point, and
time-stamps it on its own clock, which can lag the time base of the other sensors.  Both are
small, constant and hard to survey, so they are best learned:

* **lever arm** ``l`` (body frame: forward, left, up; m): antenna = ``p + C_nb l`` with the body
  attitude ``C_nb`` (a planar vehicle: the rotation by its yaw about "up");
* **time offset** ``tau`` (s, positive: the measurement is older than its time stamp): antenna at
  ``t - tau`` ~ ``antenna(t) - tau v``.

:func:`register_antenna` adds ``lever_arm`` ``[3]`` (:class:`~difffilter.params.Bounded` to
``+-max_lever_arm``) and/or ``latency`` (``+-max_latency``) to a measurement model, by name, so
``learn: [lever_arm, latency]`` trains them; :func:`antenna_offset` is the displacement
``C_nb l - tau v`` the model adds to its position.  Used by
:class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement` (odometry layouts: yaw
state, speed input) and :class:`~experiments.papers.p004.model.GnssMeasurement` (IMU
layouts: heading or quaternion, velocity states).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ...params import Bounded, register_constrained

__all__ = ["antenna_offset", "has_antenna", "planar_rotation", "register_antenna"]


def register_antenna(
    module: nn.Module,
    *,
    lever_arm: Sequence[float] | None,
    latency: float | None,
    dtype: torch.dtype,
    max_lever_arm: float = 5.0,
    max_latency: float = 0.5,
) -> None:
    """Register ``lever_arm`` and/or ``latency`` (``None``: absent, as before) on ``module``."""
    module.antenna_terms = []  # type: ignore[assignment]
    if lever_arm is not None:
        arm = torch.as_tensor(lever_arm, dtype=dtype).reshape(-1)
        if arm.numel() != 3 or not bool((arm.abs() < max_lever_arm).all()):
            raise ValueError(f"lever_arm must be 3 numbers (forward, left, up; m) inside +-{max_lever_arm}, got {arm.tolist()}")
        register_constrained(module, "lever_arm", arm, Bounded(-max_lever_arm, max_lever_arm))
        module.antenna_terms.append("lever_arm")
    if latency is not None:
        if not abs(float(latency)) < max_latency:
            raise ValueError(f"latency must lie inside +-{max_latency} s, got {latency}")
        register_constrained(module, "latency", torch.tensor(float(latency), dtype=dtype), Bounded(-max_latency, max_latency))
        module.antenna_terms.append("latency")


def has_antenna(module: nn.Module) -> bool:
    """Whether :func:`register_antenna` gave ``module`` a lever arm or a time offset."""
    return bool(getattr(module, "antenna_terms", []))


def planar_rotation(yaw: Tensor) -> Tensor:
    """``C_nb [..., 3, 3]`` of a level body with yaw ``[...]`` (from east, counter-clockwise)."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1), torch.stack([zero, zero, one], -1)], -2)


def antenna_offset(module: nn.Module, rotation: Tensor | None, velocity: Tensor | None) -> Tensor | float:
    """``C_nb l - tau v`` ``[..., 3]`` (0 without lever arm and time offset); ``rotation`` is needed
    with a lever arm, ``velocity`` with a time offset."""
    terms = getattr(module, "antenna_terms", [])
    out: Tensor | float = 0.0
    if "lever_arm" in terms:
        if rotation is None:
            raise ValueError("a lever arm needs the body attitude (a yaw or quaternion state)")
        out = out + (rotation @ module.lever_arm.to(rotation.dtype)[:, None])[..., 0]
    if "latency" in terms:
        if velocity is None:
            raise ValueError("a receiver time offset needs the velocity (a velocity state or a speed input)")
        out = out - module.latency.to(velocity.dtype) * velocity
    return out
