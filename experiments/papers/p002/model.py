"""Pedestrian dead reckoning (PDR) step model with GPS and compass measurements (paper p002).

Heading convention used throughout difffilter's PDR code: ``theta`` is an *azimuth*, measured
from north and positive clockwise (east = +pi/2), so a step of length ``L`` moves the walker by
``(dE, dN) = (L sin theta, L cos theta)``.  p002 measures heading from north counter-clockwise;
its angles are ``theta_paper = -theta``.  Headings are carried *unwrapped* (continuous, not
reduced to a 2 pi interval), and the simulator delivers compass readings unwrapped next to the
gyro-propagated heading, so a filter without angle support never sees a 2 pi jump in the
compass innovation.  For filters that do support angles, :class:`PDRMeasurement` exposes
``angular_components = (2,)`` and :meth:`PDRMeasurement.wrap_measurement`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from difffilter.models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel, wrap_angle
from difffilter.models.layout import StateLayout, describe
from difffilter.params import check_covariance, register_covariance

__all__ = [
    "PDR_LAYOUT",
    "PDRMeasurement",
    "PDRModel",
    "PDRStepDynamics",
    "default_pdr_process_noise",
    "default_pdr_measurement_noise",
    "wrap_angle",
    "wrap_measurement",
]


#: State of p002's PDR model: east/north position, step length and azimuth (clockwise from north).
PDR_LAYOUT = StateLayout(names=("E", "N", "L", "theta"), units=("m", "m", "m", "rad"), position=(0, 1), angles=(3,))


def wrap_measurement(z: Tensor, z_pred: Tensor, angular_components: tuple[int, ...] = (2,)) -> Tensor:
    """``z`` with each angular component moved by a multiple of ``2 pi`` to lie within ``pi`` of
    ``z_pred``: ``z_i <- z_pred_i + wrap(z_i - z_pred_i)``, so ``z - z_pred`` is the wrapped
    residual.  ``z [..., m]`` and ``z_pred [..., m]`` broadcast."""
    if not angular_components:
        return z
    z, z_pred = torch.broadcast_tensors(z, z_pred)
    out = z.clone()
    for i in angular_components:
        out[..., i] = z_pred[..., i] + wrap_angle(z[..., i] - z_pred[..., i])
    return out


def default_pdr_process_noise(dtype: torch.dtype | None = None) -> Tensor:
    """Hand-tuned ``Q`` per step (p002 gives no values): position 0.06 m (step-length scatter
    of U(0.6, 0.8) steps is 0.058 m), step length 0.01 m, heading 0.5 deg (phone gyro noise
    over one step plus body sway)."""
    sd = torch.tensor([0.06, 0.06, 0.01, math.radians(0.5)], dtype=dtype)
    return torch.diag(sd * sd)


def default_pdr_measurement_noise(dtype: torch.dtype | None = None, *, gps_std: float = 2.67, compass_std_deg: float = 11.4) -> Tensor:
    """``R = diag(gps_std^2, gps_std^2, compass_std^2)`` with p002's values (GPS standard error
    2.67 m, compass heading RMSE 11.4 deg without interference)."""
    sd = torch.tensor([gps_std, gps_std, math.radians(compass_std_deg)], dtype=dtype)
    return torch.diag(sd * sd)


class PDRStepDynamics(DynamicsModel):
    """Step-event PDR dynamics of p002 (one filter step = one detected step).

    State ``x = [E, N, L, theta]`` (east m, north m, step length m, azimuth rad, see the module
    docstring for the heading convention):

    .. math::
        E_k = E_{k-1} + L_{k-1} \\sin\\theta_{k-1}, \\quad
        N_k = N_{k-1} + L_{k-1} \\cos\\theta_{k-1}, \\quad
        L_k = L_{k-1}, \\quad
        \\theta_k = \\theta_{k-1} + \\Delta\\theta^{gyro}_k

    plus ``w ~ N(0, Q)``.  Controls: ``u["dtheta"] [..., 1]``, the gyro heading increment
    (rad, clockwise positive) over the step interval; other keys are ignored.  ``u`` may also be
    a tensor ``[..., 1]`` holding ``dtheta``.  Learnable: ``Q`` (diagonal by default).

    Args:
        Q: process-noise covariance ``[4, 4]`` per step; default
            :func:`default_pdr_process_noise`.
        Q_structure: ``"diagonal"`` (one variance per state, default), ``"full"``, ``"scalar"``
            or ``"fixed"``.
        dtype: dtype of the default ``Q`` (ignored when ``Q`` is given).
    """

    state_dim = 4

    def __init__(self, *, Q: Tensor | None = None, Q_structure: str = "diagonal", dtype: torch.dtype | None = None) -> None:
        super().__init__()
        if Q is None:
            Q = default_pdr_process_noise(dtype)
        check_covariance("Q", Q, 4)
        register_covariance(self, "Q", Q, Q_structure)

    @staticmethod
    def _dtheta(x: Tensor, u: Controls) -> Tensor:
        if u is None:
            return torch.zeros_like(x[..., 3])
        d = u if isinstance(u, Tensor) else u["dtheta"]
        return d[..., 0]

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        e, n, step, theta = x.unbind(-1)
        dtheta = self._dtheta(x, u)
        out = [e + step * torch.sin(theta), n + step * torch.cos(theta), step, theta + dtheta]
        return torch.stack(torch.broadcast_tensors(*out), -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        _, _, step, theta = x.unbind(-1)
        s, c = torch.sin(theta), torch.cos(theta)
        one, zero = torch.ones_like(step), torch.zeros_like(step)
        rows = [
            [one, zero, s, step * c],
            [zero, one, c, -step * s],
            [zero, zero, one, zero],
            [zero, zero, zero, one],
        ]
        return torch.stack([torch.stack(r, -1) for r in rows], -2)


class PDRMeasurement(MeasurementModel):
    """GPS position and compass heading of p002: ``z = [E, N, theta] + v``, ``v ~ N(0, R)``.

    The GPS components are masked out (``mask[..., :2] = False``) between fixes and during
    outages; the compass is read at every step.  Component 2 is an angle
    (``angular_components = (2,)``): the compass reading must be unwrapped next to the
    predicted heading (:meth:`wrap_measurement`); the p002 simulator already does so.
    Learnable: ``R`` (diagonal by default: GPS east, GPS north, compass).

    Args:
        R: measurement-noise covariance ``[3, 3]``; default
            :func:`default_pdr_measurement_noise`.
        R_structure: ``"diagonal"`` (default), ``"full"``, ``"scalar"`` or ``"fixed"``.
        dtype: dtype of the default ``R`` and of ``H`` (ignored when ``R`` is given).
    """

    measurement_dim = 3
    angular_components: tuple[int, ...] = (2,)

    def __init__(self, *, R: Tensor | None = None, R_structure: str = "diagonal", dtype: torch.dtype | None = None) -> None:
        super().__init__()
        if R is None:
            R = default_pdr_measurement_noise(dtype)
        check_covariance("R", R, 3)
        register_covariance(self, "R", R, R_structure)
        H = torch.zeros(3, 4, dtype=R.dtype)
        H[0, 0] = H[1, 1] = H[2, 3] = 1.0
        self.register_buffer("H", H)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return torch.stack([x[..., 0], x[..., 1], x[..., 3]], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.H.to(x.dtype).expand(*x.shape[:-1], 3, 4)

    def matrix(self, u: Controls = None) -> Tensor:
        return self.H

    def wrap_measurement(self, z: Tensor, z_pred: Tensor) -> Tensor:
        """``z`` with its heading unwrapped to within ``pi`` of ``z_pred`` (see
        :func:`wrap_measurement`)."""
        return wrap_measurement(z, z_pred, self.angular_components)


class PDRModel(StateSpaceModel):
    """:class:`PDRStepDynamics` with :class:`PDRMeasurement` (p002's GPS+PDR filter model).

    Keyword arguments are forwarded: ``Q``, ``Q_structure`` to the dynamics, ``R``,
    ``R_structure`` to the measurement model; ``dtype`` to both defaults.
    """

    def __init__(
        self,
        *,
        Q: Tensor | None = None,
        R: Tensor | None = None,
        Q_structure: str = "diagonal",
        R_structure: str = "diagonal",
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__(
            PDRStepDynamics(Q=Q, Q_structure=Q_structure, dtype=dtype),
            PDRMeasurement(R=R, R_structure=R_structure, dtype=dtype),
        )
        var0 = [1.0, 1.0, 0.01, math.radians(10.0) ** 2]  # the simulator's initial position and heading spreads
        describe(self, layout=PDR_LAYOUT, learn=["Q", "R"], initial_mean=[0.0, 0.0, 0.7, 0.0], initial_var=var0)

    @property
    def angular_components(self) -> tuple[int, ...]:
        return self.measurement.angular_components
