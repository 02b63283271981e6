"""Linear Kalman filter."""

from __future__ import annotations

from torch import Tensor

from ..models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from .ekf import EKF

__all__ = ["KalmanFilter"]


class KalmanFilter(EKF):
    """Kalman filter for linear-Gaussian models (``LinearModel`` or any model whose dynamics and
    measurement implement ``matrix()``).

    ``x- = F x + B u``, ``P- = F P F^T + Q``; ``K = P- H^T S^{-1}``, ``S = H P- H^T + R``;
    Joseph-form covariance update.  Learnable: ``Q``, ``R`` (and model parameters).
    """

    def __init__(self, model: StateSpaceModel, *, joseph: bool = True) -> None:
        super().__init__(model, joseph=joseph)
        if type(model.dynamics).matrix is DynamicsModel.matrix or type(model.measurement).matrix is MeasurementModel.matrix:
            raise TypeError("KalmanFilter needs a linear model: dynamics and measurement must implement matrix() (e.g. LinearModel)")

    def transition_jacobian(self, x: Tensor, u: Controls) -> Tensor:
        # un-expanded [n, n] (or per-batch [B, n, n]): broadcasting matmuls are cheaper
        return self.model.dynamics.matrix(u)

    def measurement_jacobian(self, x: Tensor, u: Controls) -> Tensor:
        return self.model.measurement.matrix(u)
