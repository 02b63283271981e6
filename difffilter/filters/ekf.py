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

__all__ = ["EKF", "autodiff_jacobian", "noise_jacobian"]


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


def noise_jacobian(fn: Callable[[Tensor, Tensor, Controls], Tensor], x: Tensor, noise_dim: int, u: Controls) -> Tensor:
    """``d fn(x, w, u) / d w`` at ``w = 0``, ``[B, out, q]`` for ``x [B, n]`` (forward mode: one
    evaluation of ``fn`` on ``B * q`` points, differentiable for the outer backward pass)."""
    n = x.shape[-1]
    lead = x.shape[:-1]
    basis = torch.eye(noise_dim, dtype=x.dtype, device=x.device).expand(*lead, noise_dim, noise_dim).contiguous()
    rep = x[..., None, :].expand(*lead, noise_dim, n)
    u1 = expand_controls(u, x.ndim - 1)
    _, tangents = jvp(lambda w: fn(rep, w, u1), (torch.zeros_like(basis),), (basis,))
    return tangents.mT.to(x.dtype)


class EKF(RecursiveFilter):
    """Extended Kalman filter.

    Predict: ``x- = f(x, u)``, ``P- = F P F^T + Q`` with ``F = df/dx`` at the posterior mean.
    Update: ``S = H P- H^T + R``, ``K = P- H^T S^{-1}``, Joseph-form covariance, ``H = dh/dx`` at
    the prior mean.  Jacobians come from the model's analytic ``jacobian`` when it provides one,
    else from ``torch.func`` (``jacobian_mode="fwd"`` or ``"rev"``).

    Non-additive noise (``dynamics.additive_noise`` / ``measurement.additive_noise`` False, e.g.
    :class:`~difffilter.models.noise.NonAdditiveModel`): ``x- = f(x, 0, u)``,
    ``P- = F P F^T + F_w Q F_w^T`` and ``S = H P- H^T + H_v R H_v^T`` with the Jacobians
    ``F_w = df/dw``, ``H_v = dh/dv`` at zero noise (the model's ``noise_jacobian`` or forward-mode
    autodiff of ``with_noise``).

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

    def process_noise_cov(self, x: Tensor, u: Controls) -> Tensor:
        """``Q``, or ``F_w Q F_w^T`` at ``x`` for non-additive process noise."""
        dyn = self.model.dynamics
        q = dyn.process_noise(x, u)
        if dyn.additive_noise:
            return q
        fw = dyn.noise_jacobian(x, u)
        fw = noise_jacobian(dyn.with_noise, x, q.shape[-1], u) if fw is None else fw
        return fw @ q @ fw.mT

    def measurement_noise_cov(self, x: Tensor, u: Controls) -> Tensor:
        """``R`` expanded to ``[B, m, m]``, or ``H_v R H_v^T`` at ``x`` for non-additive noise."""
        hm = self.model.measurement
        r = hm.measurement_noise(x, u)
        if not hm.additive_noise:
            hv = hm.noise_jacobian(x, u)
            hv = noise_jacobian(hm.with_noise, x, r.shape[-1], u) if hv is None else hv
            r = hv @ r @ hv.mT
        return r.expand(*x.shape[:-1], *r.shape[-2:])

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        jac = self.transition_jacobian(mean, u)
        q = self.process_noise_cov(mean, u)
        new_mean = self.model.dynamics(mean, u)
        return {**belief, "mean": new_mean, "cov": symmetrize(jac @ cov @ jac.mT + q)}

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        h = self.measurement_jacobian(mean, u)
        r = self.measurement_noise_cov(mean, u)
        zhat = self.model.measurement(mean, u)
        pht = cov @ h.mT
        s = h @ pht + r
        e = self.model.measurement.residual(z, zhat)
        new_mean, new_cov, info = gaussian_update(mean, cov, e, s, pht, mask, joseph=(h, r) if self.joseph else None)
        return {**belief, "mean": new_mean, "cov": new_cov}, info
