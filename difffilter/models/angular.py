"""Angular declarations that a model part's ``residual`` must agree with."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .base import DynamicsModel, MeasurementModel, wrap_components

__all__ = ["check_angular_declaration"]


def check_angular_declaration(space: nn.Module) -> None:
    """Refuse a model part whose overridden ``residual`` changes components it does not list in
    ``angular`` (e.g. wraps a heading without declaring it).

    The unscented filters average sigma-point images as angles (around a reference point) only
    for the declared components; for the others they take the plain weighted mean and then the
    model's ``residual``, which gives a silently wrong posterior when that residual wraps.  The
    check compares ``residual(a, b)`` with ``a - b`` (declared components wrapped) on spread-out
    probe values; a residual that cannot be evaluated on them is left alone."""
    if not isinstance(space, (DynamicsModel, MeasurementModel)):
        return
    base = DynamicsModel if isinstance(space, DynamicsModel) else MeasurementModel
    if type(space).residual is base.residual:
        return
    dim = int(getattr(space, "state_dim", None) or getattr(space, "measurement_dim", 0) or 0)
    if dim <= 0:
        return
    dtype = next((p.dtype for p in space.parameters() if p.is_floating_point()), torch.float64)
    gen = torch.Generator().manual_seed(0)
    a, b = (10.0 * torch.randn(2, 16, dim, generator=gen, dtype=torch.float64)).to(dtype)
    try:
        with torch.no_grad():
            got = space.residual(a, b)
    except Exception:  # noqa: BLE001 - a residual that needs more than values: nothing to probe
        return
    want = wrap_components(a - b, tuple(space.angular))
    if not isinstance(got, Tensor) or got.shape != want.shape:
        return
    bad = [i for i in range(dim) if not torch.allclose(got[:, i], want[:, i], rtol=1e-5, atol=1e-5)]
    if bad:
        raise ValueError(
            f"{type(space).__name__}.residual changes components {bad} beyond a plain difference, but its angular = "
            f"{tuple(space.angular)} does not list them: the unscented filters average only declared components as angles, "
            f"so the posterior would be silently wrong; declare them (angular = {tuple(sorted(set(space.angular) | set(bad)))}, "
            "the default residual then wraps them) or make residual a plain difference there"
        )
