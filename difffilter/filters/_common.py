"""Pieces shared by the recursive filters: per-step statistics, controls slicing and masking
(the Gaussian measurement updates are in :mod:`difffilter.filters.update`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..models.base import Controls
from .protocol import Belief

__all__ = [
    "cast_controls",
    "StepInfo",
    "detach_belief",
    "expand_controls",
    "mask_measurement_system",
    "rounding_flags",
    "slice_controls",
]


@dataclass
class StepInfo:
    """Per-step update statistics ``[B]``: log-likelihood ``log N(e; 0, S)`` of the observed
    components, normalised innovation squared ``e^T S^{-1} e`` and number of observed components.
    ``untrusted [B]`` (bool, optional) marks updates whose rounding error cannot be vouched for
    and ``jitter [B]`` (optional) the innovation covariance's repair (see
    :func:`~difffilter.filters.update.gaussian_update`); read the flags with :meth:`flags`, which
    adds the check that ``rounding`` defers."""

    log_likelihood: Tensor
    nis: Tensor
    num_observed: Tensor
    innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    untrusted: Tensor | None = None
    jitter: Tensor | None = None
    #: the inputs of a rounding check not yet made, ``(chol, whitened, var, prediction, mask)``
    #: (:func:`rounding_flags`): the time loop makes it once for a
    #: block of steps; :meth:`flags` makes it now
    rounding: tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None] | None = None

    def flags(self) -> Tensor | None:
        """``[B]`` every flag of the step: ``untrusted`` and the pending :attr:`rounding` check."""
        if self.rounding is None:
            return self.untrusted
        rounding = rounding_flags(*self.rounding)
        return rounding if self.untrusted is None else self.untrusted | rounding


def rounding_flags(chol: Tensor, whitened: Tensor, var: Tensor, prediction: Tensor | None, mask: Tensor | None) -> Tensor:
    """:func:`~difffilter.filters.update.rounding_untrusted` from ``diag S`` ``var [..., m]``; any leading dimensions
    (``[B, T, ...]``: a block of steps at once, the same flags as step by step)."""
    eps = torch.finfo(chol.dtype).eps
    with torch.no_grad():
        pivots = torch.diagonal(chol, dim1=-2, dim2=-1).detach().square()
        var = var.detach()
        v = whitened.detach()
        s_inv_e = torch.linalg.solve_triangular(chol.detach().mT, v[..., None], upper=True)[..., 0]
        spread = pivots.reciprocal().sum(-1) + s_inv_e.square().sum(-1)
        bad = ~((0.5 * chol.shape[-1] * eps) * var.amax(-1) * spread <= 1e-2 + 1e-4 * v.square().sum(-1))
        if prediction is not None:
            lost = ~((eps / 1e-2) ** 2 * prediction.detach().square() <= var)
            bad = bad | (lost if mask is None else lost & mask).any(-1)
    return bad


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


def cast_controls(controls: Controls, like: object) -> Controls:
    """Floating-point controls in the dtype of the filter's measurements ``like`` (float64
    inputs into a float32 filter are rounded as float32 measurements would be); other dtypes
    (integer indices, masks) and non-tensors unchanged."""
    if controls is None or not isinstance(like, Tensor) or not like.is_floating_point():
        return controls

    def cast(v: object) -> object:
        return v.to(like.dtype) if isinstance(v, Tensor) and v.is_floating_point() and v.dtype != like.dtype else v

    if isinstance(controls, Tensor):
        return cast(controls)  # type: ignore[return-value]
    if isinstance(controls, dict):
        return {k: cast(v) for k, v in controls.items()}  # type: ignore[misc]
    return controls


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
