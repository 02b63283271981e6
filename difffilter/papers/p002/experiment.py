"""p002 (Niu & Lian 2017, GPS + PDR fused by the RC-UKF): the model factory of
``experiment=p002_pdr``."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import torch

from ..._util import as_dtype
from ...models.navigation.pdr import PDRModel
from .simulator import simulate_p002_random

__all__ = ["P002Steps", "pdr_model"]


def pdr_model(
    *,
    Q_std: Sequence[float],
    R_std: Sequence[float],
    Q_structure: str = "diagonal",
    R_structure: str = "diagonal",
    dtype: torch.dtype | str = "float64",
) -> PDRModel:
    """p002's PDR model from standard deviations.

    Args:
        Q_std: per-step process noise ``[E m, N m, L m, theta deg]``.
        R_std: ``[GPS east m, GPS north m, compass deg]``.
        Q_structure, R_structure: learnable structure (``"diagonal"``...).
        dtype: ``"float64"`` or a torch dtype.
    """
    dt = as_dtype(dtype)
    q = torch.as_tensor(list(Q_std), dtype=dt).clone()
    r = torch.as_tensor(list(R_std), dtype=dt).clone()
    if q.shape != (4,) or r.shape != (3,):
        raise ValueError(f"Q_std needs 4 and R_std 3 entries, got {tuple(q.shape)}, {tuple(r.shape)}")
    q[3], r[2] = math.radians(float(q[3])), math.radians(float(r[2]))
    model = PDRModel(Q=torch.diag(q * q), R=torch.diag(r * r), Q_structure=Q_structure, R_structure=R_structure, dtype=dt)
    model.defaults = dataclasses.replace(model.defaults, controls=P002Steps())
    return model


class P002Steps:
    """In-family inputs of the PDR model: ``(batch_size, num_steps, generator, dtype) ->
    {"dtheta", "dt", "step_length"}`` of randomised p002 walks (:func:`simulate_p002_random`)."""

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        return simulate_p002_random(batch_size, seed=gen, dtype=dtype, num_steps=num_steps).controls
