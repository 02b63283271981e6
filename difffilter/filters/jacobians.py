"""Jacobians of a model's transition and measurement, analytic when the model has them.

Shared by the EKF (every step) and by the exact diffuse-prior handling of every filter
(:mod:`difffilter.filters.diffuse`, only while a diffuse part is present).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor
from torch.func import jacrev, jvp, vmap

from ..models.base import Controls, DynamicsModel, MeasurementModel
from ._common import expand_controls

__all__ = [
    "autodiff_jacobian",
    "difference_jacobian",
    "expand_controls",
    "measurement_matrix",
    "measurement_noise_cov",
    "noise_jacobian",
    "transition_matrix",
]


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


def difference_jacobian(fn: Callable[[Tensor, Controls], Tensor], x: Tensor, u: Controls) -> Tensor:
    """Forward-difference Jacobian ``[B, out, n]`` of ``fn(x [B, n], u)`` (steps
    ``sqrt(eps) max(1, |x_i|)``): one call of ``fn`` on ``n + 1`` points per batch element, so
    it works for any model a sigma-point filter can run (no autograd through the model)."""
    step = torch.finfo(x.dtype).eps ** 0.5 * x.abs().clamp_min(1.0)  # [B, n]
    pts = torch.cat([x[..., None, :], x[..., None, :] + torch.diag_embed(step)], -2)  # [B, n + 1, n]
    out = fn(pts, expand_controls(u, x.ndim - 1))
    return ((out[..., 1:, :] - out[..., :1, :]) / step[..., :, None]).mT


def _model_jacobian(model: DynamicsModel | MeasurementModel, base: type, x: Tensor, u: Controls, out_dim: int, differences: bool) -> Tensor:
    jac = model.jacobian(x, u)
    if jac is None and type(model).matrix is not base.matrix:
        jac = model.matrix(u)
    if jac is None:
        jac = difference_jacobian(model, x, u) if differences else autodiff_jacobian(model, x, u)
    return jac.expand(*x.shape[:-1], out_dim, x.shape[-1])


def transition_matrix(dynamics: DynamicsModel, x: Tensor, u: Controls, *, differences: bool = False) -> Tensor:
    """``df/dx`` at ``x [B, n]`` as ``[B, n, n]``: the model's analytic ``jacobian``, else its
    ``matrix`` (linear dynamics), else forward-mode autodiff (``differences=True``: forward
    differences, :func:`difference_jacobian`)."""
    return _model_jacobian(dynamics, DynamicsModel, x, u, x.shape[-1], differences)


def measurement_matrix(measurement: MeasurementModel, x: Tensor, u: Controls, *, differences: bool = False) -> Tensor:
    """``dh/dx`` at ``x [B, n]`` as ``[B, m, n]`` (as :func:`transition_matrix`)."""
    return _model_jacobian(measurement, MeasurementModel, x, u, int(measurement.measurement_dim), differences)


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


def measurement_noise_cov(measurement: MeasurementModel, x: Tensor, u: Controls) -> Tensor:
    """The measurement noise as it enters the measurement space: ``R``, or ``H_v R H_v^T`` at ``x``
    when the noise is not additive (``H_v = dh/dv`` at ``v = 0``: the model's ``noise_jacobian``
    or forward mode), expanded to ``[B, m, m]``."""
    r = measurement.measurement_noise(x, u)
    if not measurement.additive_noise:
        hv = measurement.noise_jacobian(x, u)
        hv = noise_jacobian(measurement.with_noise, x, r.shape[-1], u) if hv is None else hv
        r = hv @ r @ hv.mT
    return r.expand(*x.shape[:-1], *r.shape[-2:])
