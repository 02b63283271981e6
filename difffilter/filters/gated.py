"""EKF with an outlier gate on the normalised innovation (the predicted innovation covariance
``H P- H^T + R``, not ``R`` alone)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..models.base import Controls, StateSpaceModel
from ..models.heteroscedastic import RobustGate
from .base import Belief, StepInfo, gaussian_update
from .diffuse import DIFFUSE_COV
from .ekf import EKF
from .ukf import state_add
from .update import JosephForm

__all__ = ["GatedEKF", "innovation_gate_factor"]


def innovation_gate_factor(gate: RobustGate, innovation: Tensor, innovation_cov: Tensor) -> Tensor:
    """Variance factors ``f [..., m]`` of ``gate`` on the normalised innovation
    ``n_j = |e_j| / sqrt(S_jj + floor^2)``.

    Args:
        gate: the gate (its ``threshold``, ``floor``, ``softness`` and ``kind``).
        innovation: ``e [..., m]``.
        innovation_cov: ``S = H P- H^T + R`` ``[..., m, m]`` before the gate inflates ``R``.
    """
    return gate.factor(innovation, torch.diagonal(innovation_cov, dim1=-2, dim2=-1))


class GatedEKF(EKF):
    """EKF whose update inflates ``R_jj`` by a :class:`~difffilter.models.heteroscedastic.RobustGate`
    factor ``f_j`` of the component's normalised innovation ``n_j = |e_j| / sqrt(S_jj + floor^2)``,
    ``S = H P- H^T + R`` (the textbook chi-square gate with one degree of freedom when hard):

    ``R' = D R D``, ``D = diag(sqrt(f))``, then the EKF update with ``S' = H P- H^T + R'``.

    Normalising by ``S`` rather than ``R`` means a filter that is unsure of its state (large
    ``P-``, e.g. after its start or a gap) accepts residuals in proportion to that uncertainty
    instead of rejecting every measurement and dead-reckoning away from them.  ``floor`` (m)
    allows for model error beyond ``S``; 0 for the plain gate.  A step in the exact diffuse form
    (:mod:`~difffilter.filters.diffuse`) is not gated: its prior variance is unbounded.
    Components under a False mask are removed from the update as in every filter; their factor
    is computed on the zero placeholder and discarded.

    Args:
        model: the state-space model; its own measurement noise should carry no gate.
        gate: the gate; its parameters (a learnable smooth gate's ``gate_threshold``,
            ``gate_floor``, ``gate_softness``) are this filter's ``gate.*``.
        jacobian_mode, joseph: as :class:`~difffilter.filters.EKF`.
    """

    def __init__(self, model: StateSpaceModel, *, gate: RobustGate, jacobian_mode: str = "fwd", joseph: bool = True) -> None:
        super().__init__(model, jacobian_mode=jacobian_mode, joseph=joseph)
        if not isinstance(gate, RobustGate):
            raise TypeError(f"gate must be a RobustGate, got {type(gate).__name__}")
        self.gate = gate

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        if DIFFUSE_COV in belief:
            return super().update(belief, z, mask, u)
        mean, cov = belief["mean"], belief["cov"]
        h = self.measurement_jacobian(mean, u)
        r = self.measurement_noise_cov(mean, u)
        e = self.model.measurement.residual(z, self.model.measurement(mean, u))
        pht = cov @ h.mT
        hph = h @ pht
        d = torch.sqrt(innovation_gate_factor(self.gate, e, hph + r))
        r = r * d[..., :, None] * d[..., None, :]
        joseph = JosephForm.linear(h, r, always=self.joseph)
        new_mean, new_cov, info = gaussian_update(mean, cov, e, hph + r, pht, mask, joseph=joseph, add=state_add(self.model.dynamics))
        return {**belief, "mean": new_mean, "cov": new_cov}, info
