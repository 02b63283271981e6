"""Extended Kalman filter (and the linear Kalman filter as its exact special case)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor
from torch.func import jacrev, jvp, vmap

from ..linalg import symmetrize
from ..models.base import Controls, StateSpaceModel
from ._common import expand_controls
from .base import Belief, RecursiveFilter, StepInfo, gaussian_update

__all__ = ["EKF", "autodiff_jacobian"]


def autodiff_jacobian(fn: Callable[[Tensor, Controls], Tensor], x: Tensor, u: Controls, *, mode: str = "fwd") -> Tensor:
    """Per-batch-element Jacobian ``d fn / d x`` ``[B, out, n]`` of ``fn(x [B, n], u)``.

    ``mode="fwd"``: one forward-mode ``torch.func.jvp`` on ``x`` repeated along a new axis with
    the identity as tangents (``[B, n, n]``): every model accepts arbitrary leading dimensions,
    so the whole batch's Jacobian costs one evaluation of ``fn`` on ``B * n`` states.
    ``mode="rev"``: ``vmap`` over the batch of ``jacrev`` (``u`` mapped along its first
    dimension).  Both stay differentiable for the outer backward pass.
    """
    if mode == "fwd":
        n = x.shape[-1]
        basis = torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], n, n).contiguous()
        rep = x[..., None, :].expand(*x.shape[:-1], n, n).contiguous()
        u1 = expand_controls(u, x.ndim - 1)
        _, tangents = jvp(lambda xx: fn(xx, u1), (rep,), (basis,))
        out = tangents.mT  # tangents [..., n (direction), out]
    elif u is None:
        out = vmap(jacrev(lambda xi: fn(xi, None)))(x)
    else:
        out = vmap(jacrev(fn, argnums=0), in_dims=(0, 0))(x, u)
    # Forward-mode AD can promote tangents of float32 inputs to float64 when a Python scalar
    # is added (seen in torch 2.13): keep the state's dtype.
    return out.to(x.dtype)


class EKF(RecursiveFilter):
    """Extended Kalman filter.

    Predict: ``x- = f(x, u)``, ``P- = F P F^T + Q`` with ``F = df/dx`` at the posterior mean.
    Update: ``S = H P- H^T + R``, ``K = P- H^T S^{-1}``, Joseph-form covariance, ``H = dh/dx`` at
    the prior mean.  Jacobians come from the model's analytic ``jacobian`` when it provides one,
    else from ``torch.func`` (``jacobian_mode="fwd"`` or ``"rev"``).

    Learnable: whatever the model registers (Q, R, model parameters).
    """

    def __init__(self, model: StateSpaceModel, *, jacobian_mode: str = "fwd", joseph: bool = True) -> None:
        super().__init__(model)
        if jacobian_mode not in ("fwd", "rev"):
            raise ValueError(f"jacobian_mode must be 'fwd' or 'rev', got {jacobian_mode!r}")
        self.jacobian_mode = jacobian_mode
        self.joseph = joseph

    def transition_jacobian(self, x: Tensor, u: Controls) -> Tensor:
        jac = self.model.dynamics.jacobian(x, u)
        if jac is None:
            jac = autodiff_jacobian(self.model.dynamics, x, u, mode=self.jacobian_mode)
        return jac

    def measurement_jacobian(self, x: Tensor, u: Controls) -> Tensor:
        jac = self.model.measurement.jacobian(x, u)
        if jac is None:
            jac = autodiff_jacobian(self.model.measurement, x, u, mode=self.jacobian_mode)
        return jac

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        jac = self.transition_jacobian(mean, u)
        q = self.model.dynamics.process_noise(mean, u)
        new_mean = self.model.dynamics(mean, u)
        return {**belief, "mean": new_mean, "cov": symmetrize(jac @ cov @ jac.mT + q)}

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        h = self.measurement_jacobian(mean, u)
        r = self.model.measurement.measurement_noise(mean, u)
        r = r.expand(*mean.shape[:-1], *r.shape[-2:])
        zhat = self.model.measurement(mean, u)
        pht = cov @ h.mT
        s = h @ pht + r
        e = self.model.measurement.residual(z, zhat)
        new_mean, new_cov, info = gaussian_update(mean, cov, e, s, pht, mask, joseph=(h, r) if self.joseph else None)
        return {**belief, "mean": new_mean, "cov": new_cov}, info
