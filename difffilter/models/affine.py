"""An affine-Gaussian model whose matrices are given per step: time-varying Kalman filtering,
and the linearised models of the iterated smoothers."""

from __future__ import annotations

from torch import Tensor

from .._util import control
from .base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel

__all__ = ["TimeVaryingLinearModel"]


def _mv(a: Tensor, x: Tensor) -> Tensor:
    return (a @ x[..., None])[..., 0]


class _AffineDynamics(DynamicsModel):
    def __init__(self, n: int) -> None:
        super().__init__()
        self.state_dim = n

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        out = _mv(control(u, "F", "TimeVaryingLinearModel"), x)
        return out + u["c"] if "c" in u else out  # type: ignore[operator,index]  # control() above proved u a dict

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        f = control(u, "F", "TimeVaryingLinearModel")
        return f.expand(*x.shape[:-1], *f.shape[-2:])

    def matrix(self, u: Controls = None) -> Tensor:
        return control(u, "F", "TimeVaryingLinearModel")

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        return control(u, "Q", "TimeVaryingLinearModel")


class _AffineMeasurement(MeasurementModel):
    def __init__(self, m: int) -> None:
        super().__init__()
        self.measurement_dim = m

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        out = _mv(control(u, "H", "TimeVaryingLinearModel"), x)
        return out + u["d"] if "d" in u else out  # type: ignore[operator,index]  # control() above proved u a dict

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        h = control(u, "H", "TimeVaryingLinearModel")
        return h.expand(*x.shape[:-1], *h.shape[-2:])

    def matrix(self, u: Controls = None) -> Tensor:
        return control(u, "H", "TimeVaryingLinearModel")

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        return control(u, "R", "TimeVaryingLinearModel")


class TimeVaryingLinearModel(StateSpaceModel):
    """``x_t = F_t x_{t-1} + c_t + w_t``, ``w_t ~ N(0, Q_t)``; ``z_t = H_t x_t + d_t + v_t``,
    ``v_t ~ N(0, R_t)`` with every matrix read from the per-step inputs.

    ``controls`` is a dict with ``"F" [B, T, n, n]``, ``"Q" [B, T, n, n]``, ``"H" [B, T, m, n]``,
    ``"R" [B, T, m, m]`` and optionally the offsets ``"c" [B, T, n]``, ``"d" [B, T, m]``.  Any
    filter that reads ``matrix()`` (:class:`~difffilter.filters.KalmanFilter`,
    :class:`~difffilter.filters.ParallelKalmanFilter`) runs it exactly.  Nothing is learnable
    here: gradients flow to whatever produced the matrices (e.g. the linearisations of
    :class:`~difffilter.smoothers.IteratedSmoother`).

    Args:
        state_dim: ``n``.
        measurement_dim: ``m``.
    """

    def __init__(self, *, state_dim: int, measurement_dim: int) -> None:
        for name, value in (("state_dim", state_dim), ("measurement_dim", measurement_dim)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        super().__init__(_AffineDynamics(state_dim), _AffineMeasurement(measurement_dim))
