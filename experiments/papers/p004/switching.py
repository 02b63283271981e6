"""p004's switching statistics, eqs. (1) and (2), which decide between the EKF and the UKF.

``gamma = max(sigma_alpha, sigma_beta) / max(sigma_GNSS, sigma_IMU)`` (noise regime: EKF when
below 3x the system-noise std) and ``mu = sqrt(alpha^2 / 9.8^2 + beta^2 / pi^2)`` (motion regime:
UKF when above the sensor's tolerated error), with ``alpha`` the accelerometer output and
``beta`` the gyro output (magnitudes).  Three entry points over one computation:

* :func:`switching_statistics` - from magnitudes ``alpha``, ``beta`` (``gamma`` broadcast to
  ``mu``'s shape);
* :func:`imu_switching_statistics` - from IMU vector readings ``[..., k]`` (optionally removing
  gravity from the up axis; ``gamma`` keeps the broadcast shape of the sigmas);
* :class:`ImuSwitchingStatistics` - the ``statistics`` callable of
  :class:`~difffilter.mixers.Blend`, from a step's IMU controls.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from difffilter.models.base import Controls
from experiments.papers.p004.model import GNSS_IMU_PAPER, GRAVITY

__all__ = ["ImuSwitchingStatistics", "imu_switching_statistics", "switching_statistics"]


Sigma = float | Tensor


def _gamma_mu(
    alpha: Tensor, beta: Tensor, sigma_accel: Sigma, sigma_gyro: Sigma, sigma_gnss: Sigma, sigma_imu: Sigma, g: float
) -> tuple[Tensor, Tensor]:
    t = lambda v: torch.as_tensor(v, dtype=alpha.dtype, device=alpha.device)  # noqa: E731
    gamma = torch.maximum(t(sigma_accel), t(sigma_gyro)) / torch.maximum(t(sigma_gnss), t(sigma_imu))
    mu = torch.sqrt(alpha * alpha / g**2 + beta * beta / math.pi**2)
    return gamma, mu


def switching_statistics(
    accel: Tensor,
    gyro: Tensor,
    *,
    sigma_accel: float | Tensor,
    sigma_gyro: float | Tensor,
    sigma_gnss: float | Tensor,
    sigma_imu: float | Tensor,
    gravity: float = 9.8,
) -> tuple[Tensor, Tensor]:
    """``(gamma, mu)`` from magnitudes (module docstring).

    Args:
        accel: accelerometer output magnitude ``alpha`` (m/s^2), ``[...]`` (pass
            ``a.norm(dim=-1)`` for three-axis readings).
        gyro: angular-rate magnitude ``beta`` (rad/s), ``[...]``.
        sigma_accel, sigma_gyro: noise of the IMU-derived acceleration and rate.
        sigma_gnss, sigma_imu: observation noise levels (floats or tensors broadcasting against
            ``[...]``).
        gravity: ``g`` in eq. (2).

    Returns:
        ``(gamma, mu)``, both ``[...]``.
    """
    gamma, mu = _gamma_mu(accel, gyro, sigma_accel, sigma_gyro, sigma_gnss, sigma_imu, gravity)
    return torch.broadcast_to(gamma, mu.shape), mu


def imu_switching_statistics(
    accel: Tensor,
    gyro: Tensor,
    sigma_accel: Tensor | float,
    sigma_gyro: Tensor | float,
    sigma_gnss: Tensor | float,
    sigma_imu: Tensor | float,
    *,
    gravity: float | None = None,
) -> tuple[Tensor, Tensor]:
    """``(gamma, mu)`` from the accelerometer output ``[..., k]`` and the gyro output ``[..., k]``
    (vector norms).

    ``mu`` is meant for the motion-induced acceleration: pass gravity-compensated ``accel``, or
    ``gravity=9.80665`` to subtract it from the last (up) axis of a level vehicle's reading.
    Returns ``(gamma, mu)``; ``gamma`` has the broadcast shape of the sigmas, ``mu`` is ``[...]``.
    """
    if gravity is not None:
        accel = torch.cat([accel[..., :-1], accel[..., -1:] - gravity], -1)
    alpha = torch.linalg.vector_norm(accel, dim=-1)
    beta = torch.linalg.vector_norm(gyro, dim=-1)
    return _gamma_mu(alpha, beta, sigma_accel, sigma_gyro, sigma_gnss, sigma_imu, 9.8)


class ImuSwitchingStatistics:
    """p004's switching statistics from the step's IMU controls, for :class:`~difffilter.mixers.Blend`.

    ``gamma`` (eq. (1)) is constant here: the configured noise levels; ``mu`` (eq. (2)) uses the
    accelerometer reading without gravity and the gyro reading.  Readings of 3-axis IMUs include
    gravity on the up axis; it is removed.

    Args:
        sigma_accel, sigma_gyro, sigma_gnss: noise levels in eq. (1) (defaults: p004's).
        sigma_imu: IMU observation noise in eq. (1) (default: ``sigma_accel``).
    """

    def __init__(
        self,
        *,
        sigma_accel: float = GNSS_IMU_PAPER["sigma_accel"],
        sigma_gyro: float = GNSS_IMU_PAPER["sigma_gyro"],
        sigma_gnss: float = GNSS_IMU_PAPER["sigma_gnss"],
        sigma_imu: float | None = None,
    ) -> None:
        self.sigma_accel, self.sigma_gyro, self.sigma_gnss = float(sigma_accel), float(sigma_gyro), float(sigma_gnss)
        self.sigma_imu = float(sigma_accel if sigma_imu is None else sigma_imu)

    def __call__(self, u: Controls) -> tuple[Tensor, Tensor]:
        if not isinstance(u, dict) or "accel" not in u or "gyro" not in u:
            raise ValueError('ImuSwitchingStatistics needs controls {"accel": [B, k], "gyro": [B, k]}')
        accel = u["accel"]
        gamma, mu = imu_switching_statistics(
            accel,
            u["gyro"],
            self.sigma_accel,
            self.sigma_gyro,
            self.sigma_gnss,
            self.sigma_imu,
            gravity=GRAVITY if accel.shape[-1] == 3 else None,
        )
        return torch.broadcast_to(gamma, mu.shape), mu

    def __repr__(self) -> str:
        return f"ImuSwitchingStatistics(sigma_accel={self.sigma_accel}, sigma_gyro={self.sigma_gyro}, sigma_gnss={self.sigma_gnss})"
