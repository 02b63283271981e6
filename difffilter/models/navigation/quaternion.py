"""Unit quaternions ``[w, x, y, z]`` for attitude (the 3-D GNSS/IMU model of p004)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["quaternion_multiply", "quaternion_to_rotation", "rotation_quaternion"]


def quaternion_multiply(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product ``p * q`` of ``[..., 4]`` quaternions ``[w, x, y, z]``."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        -1,
    )


def quaternion_to_rotation(q: Tensor) -> Tensor:
    """Rotation matrix ``[..., 3, 3]`` (body -> navigation) of unit quaternions ``[..., 4]``."""
    w, x, y, z = q.unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def rotation_quaternion(theta: Tensor) -> Tensor:
    """Quaternion of the rotation vector ``theta [..., 3]``, smooth at 0."""
    sq = (theta * theta).sum(-1, keepdim=True)
    # sqrt(sq + tiny) keeps the gradient finite at theta = 0; sin(n/2)/n = sinc(n / 2 pi) / 2.
    n = torch.sqrt(sq + 1e-30)
    return torch.cat([torch.cos(n / 2), 0.5 * torch.sinc(n / (2 * math.pi)) * theta], -1)
