"""Iterated extended Kalman filter: Gauss-Newton iterations of the measurement update."""

from __future__ import annotations

from torch import Tensor

from ..models.base import Controls, StateSpaceModel
from .base import Belief, StepInfo, gaussian_update
from .diffuse import DIFFUSE_COV
from .ekf import EKF
from .ukf import state_add
from .update import JosephForm

__all__ = ["IteratedEKF"]


class IteratedEKF(EKF):
    """Iterated EKF: the update relinearises ``h`` a fixed number of times (Gauss-Newton).

    Prediction as :class:`EKF`.  Update from the prior ``(x-, P-)``, starting at ``x_0 = x-``, for
    ``i = 0 .. N-1``::

        H_i = dh/dx (x_i),  S_i = H_i P- H_i^T + R,  K_i = P- H_i^T S_i^{-1}
        x_{i+1} = x- + K_i (z - h(x_i) - H_i (x- - x_i))

    then ``P = (I - K H) P- (I - K H)^T + K R K^T`` with the last ``K_{N-1}``, ``H_{N-1}``.  Each
    iteration is one Gauss-Newton step on ``(x - x-)^T P-^{-1} (x - x-) + (z - h(x))^T R^{-1}
    (z - h(x))``, so the mean approaches the maximum a-posteriori state; ``iterations=1`` is the
    EKF exactly.  The count is fixed (no data-dependent stopping), so the filter stays
    differentiable and batched.  The step's log-likelihood is ``log N(e; 0, S)`` of the last
    linearisation (the EKF's for one iteration).  Masks, non-additive measurement noise
    (``H_v R H_v^T`` at the current iterate), angular states and a diffuse prior (whose updates
    are the EKF's) as in :class:`EKF`.

    Args:
        model: the state-space model.
        iterations: ``N >= 1`` Gauss-Newton iterations per update.
        jacobian_mode, joseph: as :class:`EKF`.

    Learnable: the model's parameters.
    """

    def __init__(self, model: StateSpaceModel, *, iterations: int = 3, jacobian_mode: str = "fwd", joseph: bool = True) -> None:
        super().__init__(model, jacobian_mode=jacobian_mode, joseph=joseph)
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
        self.iterations = iterations

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        if DIFFUSE_COV in belief:  # a diffuse prior's first updates: the EKF's exact two-part update
            return super().update(belief, z, mask, u)
        mean, cov = belief["mean"], belief["cov"]
        hm = self.model.measurement
        x = mean
        for _ in range(self.iterations):
            h = self.measurement_jacobian(x, u)
            r = self.measurement_noise_cov(x, u)
            pht = cov @ h.mT
            zhat = hm(x, u)
            e = hm.residual(z, zhat) + (h @ self.model.dynamics.residual(x, mean)[..., None])[..., 0]
            joseph = JosephForm.linear(h, r, always=self.joseph)
            x, new_cov, info = gaussian_update(
                mean, cov, e, h @ pht + r, pht, mask, joseph=joseph, add=state_add(self.model.dynamics), prediction=zhat
            )
        return {**belief, "mean": x, "cov": new_cov}, info
