"""Pieces shared by the recursive filters: per-step statistics, controls slicing, masking and the
Gaussian measurement update (every Kalman-family update goes through :func:`gaussian_update`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..linalg import joseph_update, safe_cholesky, symmetrize
from ..models.base import Controls
from .protocol import Belief

__all__ = [
    "StepInfo",
    "detach_belief",
    "expand_controls",
    "gaussian_update",
    "mask_measurement_system",
    "slice_controls",
]

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass
class StepInfo:
    """Per-step update statistics ``[B]``: log-likelihood ``log N(e; 0, S)`` of the observed
    components, normalised innovation squared ``e^T S^{-1} e`` and number of observed components."""

    log_likelihood: Tensor
    nis: Tensor
    num_observed: Tensor
    innovation: Tensor | None = None
    innovation_cov: Tensor | None = None


def slice_controls(controls: Controls, t: int) -> Controls:
    """Step ``t`` of per-step inputs ``[B, T, ...]`` (tensor or dict of tensors)."""
    if controls is None:
        return None
    if isinstance(controls, Tensor):
        return controls[:, t]
    return {k: v[:, t] for k, v in controls.items()}


def expand_controls(u: Controls, dim: int = 1) -> Controls:
    """Insert a singleton sigma-point dimension so ``u [B, ...]`` broadcasts with ``x [B, S, n]``."""
    if u is None:
        return None
    if isinstance(u, Tensor):
        return u.unsqueeze(dim)
    return {k: v.unsqueeze(dim) for k, v in u.items()}


def detach_belief(belief: Belief) -> Belief:
    """Detach every tensor of a belief (truncated back-propagation boundaries)."""
    return {k: v.detach() for k, v in belief.items()}


def mask_measurement_system(
    innovation: Tensor, cov: Tensor, deviations: Tensor, mask: Tensor | None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Remove unobserved measurement components exactly from an update.

    ``innovation [B, m]``, ``cov [B, m, m]`` (innovation or noise covariance), ``deviations
    [..., m]`` (anything indexed by measurement component last: ``P_xz``, sigma-point
    deviations); ``mask [B, m]`` True = observed.  Missing components get a zero innovation
    (``where``, so NaN never propagates), zero deviations, zero covariance rows/columns and a unit
    diagonal: the padded system's update equals the update on the observed subset, and each
    missing component adds exactly ``log N(0; 0, 1)`` to the log-density.  Returns the masked
    ``(innovation, cov, deviations, num_observed [B])``.
    """
    m = innovation.shape[-1]
    if mask is None:
        num_obs = torch.full(innovation.shape[:-1], float(m), dtype=innovation.dtype, device=innovation.device)
        return innovation, cov, deviations, num_obs
    observed = mask.to(innovation.dtype)
    innovation = torch.where(mask, innovation, torch.zeros_like(innovation))
    cov = cov * (observed[..., :, None] * observed[..., None, :]) + torch.diag_embed(1.0 - observed)
    return innovation, cov, deviations * observed[..., None, :], observed.sum(-1)


def gaussian_update(
    mean: Tensor,
    cov: Tensor,
    innovation: Tensor,
    innovation_cov: Tensor,
    cross_cov: Tensor,
    mask: Tensor | None,
    *,
    joseph: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, StepInfo]:
    """Linear-Gaussian measurement update shared by every Kalman-family filter.

    Args:
        mean, cov: prior ``[B, n]``, ``[B, n, n]``.
        innovation: ``e = z - z_hat`` ``[B, m]``.
        innovation_cov: ``S [B, m, m]`` (measurement noise included).
        cross_cov: ``P_xz [B, n, m]``.
        mask: ``[B, m]`` bool, True = observed (``None``: all observed).
        joseph: ``(H [B, m, n], R [B, m, m])`` to use the Joseph form (KF/EKF) instead of
            ``P - K S K^T``.

    Returns the posterior mean and covariance and the :class:`StepInfo`.  The gain is never
    formed through an inverse: with ``S = L L^T``, ``W = L^{-1} P_xz^T`` gives
    ``K e = W^T L^{-1} e`` and ``K S K^T = W^T W``.
    """
    innovation, innovation_cov, cross_cov, num_obs = mask_measurement_system(innovation, innovation_cov, cross_cov, mask)
    chol = safe_cholesky(innovation_cov).factor
    rhs = torch.cat([cross_cov.mT, innovation[..., None]], -1)  # [B, m, n+1]
    sol = torch.linalg.solve_triangular(chol, rhs, upper=False)
    w, v = sol[..., :-1], sol[..., -1]  # W [B, m, n], v = L^{-1} e [B, m]
    new_mean = mean + (w.mT @ v[..., None])[..., 0]
    if joseph is None:
        new_cov = symmetrize(cov - w.mT @ w)
    else:
        h, r = joseph
        gain = torch.linalg.solve_triangular(chol.mT, w, upper=True).mT  # K = W^T L^{-1}
        if mask is not None:
            observed = mask.to(h.dtype)
            h = h * observed[..., :, None]
            r = r * (observed[..., :, None] * observed[..., None, :])
        new_cov = joseph_update(cov, gain, h, r)
    maha = (v * v).sum(-1)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    loglik = -0.5 * (maha + logdet + num_obs * _LOG_2PI)
    info = StepInfo(loglik, maha, num_obs, innovation, innovation_cov)
    return new_mean, new_cov, info
