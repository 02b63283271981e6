"""A coordinated-turn target defined outside the package: the acceptance test of "adding a model
takes one Python file and one YAML" (``tests/assets/conf/model/ct.yaml``).

State ``[x, y, v, psi, omega]`` (position m, speed m/s, heading rad from the x axis, turn rate
rad/s); over a step ``T`` the target moves along the arc of constant speed and turn rate
(the exact coordinated-turn transition, written with ``sinc``-type terms so ``omega -> 0`` is the
straight line), and its position is observed.  Learnable: ``Q`` (diagonal) and ``R``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from difffilter import as_dtype
from difffilter.models import FunctionalModel, StateLayout, StateSpaceModel, describe

__all__ = ["ct_model"]

CT_LAYOUT = StateLayout(names=("x", "y", "v", "psi", "omega"), units=("m", "m", "m/s", "rad", "rad/s"), position=(0, 1), angles=(3,))


def _transition(dt: float):  # noqa: ANN202 - a closure over the step
    def f(x: Tensor) -> Tensor:
        px, py, v, psi, w = x.unbind(-1)
        a = w * dt
        small = a.abs() < 1e-6
        safe = torch.where(small, torch.ones_like(a), a)
        # sin(a)/a and (1 - cos a)/a, with their series near a = 0
        s1 = torch.where(small, 1.0 - a * a / 6.0, torch.sin(safe) / safe)
        s2 = torch.where(small, a / 2.0, (1.0 - torch.cos(safe)) / safe)
        dx = v * dt * (torch.cos(psi) * s1 - torch.sin(psi) * s2)
        dy = v * dt * (torch.sin(psi) * s1 + torch.cos(psi) * s2)
        return torch.stack([px + dx, py + dy, v, psi + a, w], -1)

    return f


def _position(x: Tensor) -> Tensor:
    return x[..., :2]


def ct_model(
    *, dt: float = 1.0, q: Sequence[float], r: float, initial_mean: Sequence[float], initial_var: Sequence[float], dtype: str = "float64"
) -> StateSpaceModel:
    """The coordinated-turn model with process-noise variances ``q [5]`` per step and position
    noise variance ``r`` (m^2); ``initial_mean``/``initial_var`` are its default belief."""
    dt_ = as_dtype(dtype)
    if len(q) != 5:
        raise ValueError(f"q must hold 5 variances (one per state component), got {len(q)}")
    model = FunctionalModel(
        f=_transition(float(dt)),
        h=_position,
        Q=torch.diag(torch.tensor(list(q), dtype=dt_)),
        R=float(r) * torch.eye(2, dtype=dt_),
        Q_structure="diagonal",
        R_structure="diagonal",
    )
    return describe(model, layout=CT_LAYOUT, learn=["Q", "R"], initial_mean=initial_mean, initial_var=initial_var, name="ct")
