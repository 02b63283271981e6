"""Extended Kalman filter (and the linear Kalman filter as its exact special case)."""

from __future__ import annotations

from torch import Tensor

from ..linalg import symmetrize
from ..models.base import Controls, StateSpaceModel
from .base import Belief, RecursiveFilter, StepInfo, diffuse_gaussian_update, gaussian_update, square_root_deviations
from .diffuse import DIFFUSE_COV, propagate_diffuse
from .jacobians import autodiff_jacobian, measurement_noise_cov, noise_jacobian
from .ukf import state_add
from .update import JosephForm

__all__ = ["EKF", "autodiff_jacobian", "noise_jacobian"]


class EKF(RecursiveFilter):
    """Extended Kalman filter.

    Predict: ``x- = f(x, u)``, ``P- = F P F^T + Q`` with ``F = df/dx`` at the posterior mean.
    Update: ``S = H P- H^T + R``, ``K = P- H^T S^{-1}``, Joseph-form covariance, ``H = dh/dx`` at
    the prior mean.  Jacobians come from the model's analytic ``jacobian`` when it provides one,
    else from ``torch.func`` (``jacobian_mode="fwd"`` or ``"rev"``).  ``joseph=False`` uses
    ``P - K S K^T`` and switches to the Joseph form where that cancels (see
    :func:`~difffilter.filters.base.gaussian_update`).

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
        return measurement_noise_cov(self.model.measurement, x, u)

    def predict(self, belief: Belief, u: Controls) -> Belief:
        mean, cov = belief["mean"], belief["cov"]
        jac = self.transition_jacobian(mean, u)
        q = self.process_noise_cov(mean, u)
        new_mean = self.model.dynamics(mean, u)
        out = {**belief, "mean": new_mean, "cov": symmetrize(jac @ cov @ jac.mT + q)}
        propagate_diffuse(belief, out, jac, self.model, u)
        return out

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        h = self.measurement_jacobian(mean, u)
        r = self.measurement_noise_cov(mean, u)
        zhat = self.model.measurement(mean, u)
        pht = cov @ h.mT
        s = h @ pht + r
        e = self.model.measurement.residual(z, zhat)
        if DIFFUSE_COV in belief:
            h = h.expand(*mean.shape[:-1], *h.shape[-2:])
            add = state_add(self.model.dynamics)
            post, info = diffuse_gaussian_update(belief, e, (*square_root_deviations(cov, h), r), mask, obs_matrix=h, add=add)
            return {**belief, **post}, info
        joseph = JosephForm.linear(h, r, always=self.joseph)
        add = state_add(self.model.dynamics)
        new_mean, new_cov, info = gaussian_update(mean, cov, e, s, pht, mask, joseph=joseph, add=add, prediction=zhat)
        return {**belief, "mean": new_mean, "cov": new_cov}, info
