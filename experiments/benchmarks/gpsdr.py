"""Self-contained p000 GPS/DR model and data for benchmarking (plain torch ops, fixed numbers).

The benchmark keeps its own copy of the p000 model so that its timings do not move when the
library's navigation models change.  State (8)::

    x = [s_e, v_e, a_e, s_n, v_n, a_n, eps, psi]

east/north position (m), velocity (m/s), acceleration (m/s^2), gyro drift ``eps`` (deg/s) and
odometer scale ``psi``.  Linear dynamics ``x_k = F x_{k-1} + w_k``: a Singer block per axis
(manoeuvre time constant ``tau_a``), a first-order Gauss-Markov drift (``tau_eps``) and a random
walk scale.  Four nonlinear measurements (p000, with its [fix] of the odometer)::

    z = [s_e, s_n, (180/pi) (v_n a_e - v_e a_n) / (v_e^2 + v_n^2) + eps, psi T sqrt(v_e^2 + v_n^2)]

The yaw rate is in deg/s (not rad/s) so that the drift state is O(1e-2) rather than O(1e-4),
which keeps the covariance conditioning within reach of float32.  ``Q`` and ``R`` are
learnable (full log-Cholesky by default; the benchmark trains a diagonal ``R`` only).

Also here: a linear constant-velocity model (the KF case) and the scripted-truth simulator.
The numpy/JAX twins of ``f``/``h`` used by the peers live in :mod:`experiments.benchmarks.filterpy_peer`
and :mod:`experiments.benchmarks.dynamax_peer` and read :func:`gpsdr_constants`, so every library sees
the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from difffilter.models.base import Controls, DynamicsModel, LinearModel, MeasurementModel, StateSpaceModel
from difffilter.params import register_covariance

__all__ = [
    "GpsDrConstants",
    "BenchData",
    "GpsDrDynamics",
    "GpsDrMeasurement",
    "cv_matrices",
    "gpsdr_constants",
    "gpsdr_matrices",
    "make_gpsdr_model",
    "make_cv_model",
    "simulate_gpsdr",
]

_RAD2DEG = 180.0 / math.pi


@dataclass(frozen=True)
class GpsDrConstants:
    """Numbers of the benchmark model (p000 values where the paper gives them)."""

    dt: float = 0.1
    tau_a: float = 100.0
    sigma_a: float = 1.0
    tau_eps: float = 100.0
    sigma_eps: float = 0.015  # deg/s
    sigma_psi_step: float = 1e-5
    sigma_gps: float = 15.0
    sigma_gyro: float = 0.4  # deg/s
    sigma_odo: float = 1.0
    cv_sigma_a: float = 1.0  # white-acceleration density of the linear CV model


def gpsdr_constants() -> GpsDrConstants:
    return GpsDrConstants()


def _singer_block(alpha: float, dt: float) -> list[list[float]]:
    e = math.exp(-alpha * dt)
    return [[1.0, dt, (alpha * dt - 1.0 + e) / alpha**2], [0.0, 1.0, (1.0 - e) / alpha], [0.0, 0.0, e]]


def _ca_noise_block(sigma2: float, dt: float) -> list[list[float]]:
    t = dt
    q = [[t**5 / 20, t**4 / 8, t**3 / 6], [t**4 / 8, t**3 / 3, t**2 / 2], [t**3 / 6, t**2 / 2, t]]
    return [[2.0 * sigma2 * v for v in row] for row in q]


def gpsdr_matrices(c: GpsDrConstants, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor, Tensor]:
    """``(F [8, 8], Q [8, 8], R [4, 4])`` of the GPS/DR model."""
    f = torch.zeros(8, 8, dtype=torch.float64)
    q = torch.zeros(8, 8, dtype=torch.float64)
    blk = torch.tensor(_singer_block(1.0 / c.tau_a, c.dt), dtype=torch.float64)
    qb = torch.tensor(_ca_noise_block(c.sigma_a**2, c.dt), dtype=torch.float64)
    for i in (0, 3):
        f[i : i + 3, i : i + 3] = blk
        q[i : i + 3, i : i + 3] = qb
    phi = math.exp(-c.dt / c.tau_eps)
    f[6, 6], f[7, 7] = phi, 1.0
    q[6, 6] = c.sigma_eps**2 * (1.0 - phi**2)
    q[7, 7] = c.sigma_psi_step**2
    r = torch.diag(torch.tensor([c.sigma_gps**2, c.sigma_gps**2, c.sigma_gyro**2, c.sigma_odo**2], dtype=torch.float64))
    return f.to(dtype), q.to(dtype), r.to(dtype)


class GpsDrDynamics(DynamicsModel):
    """Linear p000 dynamics ``x_k = F x_{k-1} + w_k``, ``w ~ N(0, Q)``; learnable ``Q``."""

    def __init__(self, *, F: Tensor, Q: Tensor, Q_structure: str = "full") -> None:  # noqa: N803
        super().__init__()
        self.state_dim = 8
        self.register_buffer("F", F.detach().clone())
        register_covariance(self, "Q", Q, Q_structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return x @ self.F.mT

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.F.expand(*x.shape[:-1], 8, 8)

    def matrix(self, u: Controls = None) -> Tensor:
        return self.F


class GpsDrMeasurement(MeasurementModel):
    """p000 GPS position, gyro yaw rate and odometer distance; learnable ``R``.

    ``analytic_jacobian=False`` makes :meth:`jacobian` return ``None`` so that the EKF uses
    ``torch.func`` autodiff (what a user who writes no Jacobian gets).
    """

    def __init__(self, *, R: Tensor, dt: float, R_structure: str = "full", analytic_jacobian: bool = True) -> None:  # noqa: N803
        super().__init__()
        self.measurement_dim = 4
        self.dt = float(dt)
        self.analytic_jacobian = analytic_jacobian
        register_covariance(self, "R", R, R_structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        # One unbind instead of eight selects: one backward node instead of eight zero-filled scatters.
        se, ve, ae, sn, vn, an, eps, psi = x.unbind(-1)
        sp2 = ve * ve + vn * vn
        yaw = _RAD2DEG * (vn * ae - ve * an) / sp2 + eps
        return torch.stack([se, sn, yaw, psi * self.dt * torch.sqrt(sp2)], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        if not self.analytic_jacobian:
            return None
        _, ve, ae, _, vn, an, _, psi = x.unbind(-1)
        sp2 = ve * ve + vn * vn
        sp = torch.sqrt(sp2)
        num = vn * ae - ve * an
        zero, one = torch.zeros_like(ve), torch.ones_like(ve)
        d_ve = _RAD2DEG * (-an / sp2 - 2.0 * ve * num / (sp2 * sp2))
        d_vn = _RAD2DEG * (ae / sp2 - 2.0 * vn * num / (sp2 * sp2))
        rows = [
            [one, zero, zero, zero, zero, zero, zero, zero],
            [zero, zero, zero, one, zero, zero, zero, zero],
            [zero, d_ve, _RAD2DEG * vn / sp2, zero, d_vn, -_RAD2DEG * ve / sp2, one, zero],
            [zero, psi * self.dt * ve / sp, zero, zero, psi * self.dt * vn / sp, zero, zero, self.dt * sp],
        ]
        return torch.stack([torch.stack(r, -1) for r in rows], -2)


def make_gpsdr_model(
    *,
    dtype: torch.dtype = torch.float64,
    q_scale: float = 1.0,
    analytic_jacobian: bool = True,
    structure: str = "full",
    Q_structure: str | None = None,  # noqa: N803
    R_structure: str | None = None,  # noqa: N803
) -> StateSpaceModel:
    """The benchmark's p000 GPS/DR model (``Q`` multiplied by ``q_scale``, e.g. for IMM modes);
    ``Q_structure``/``R_structure`` override ``structure`` for one matrix."""
    c = gpsdr_constants()
    f, q, r = gpsdr_matrices(c, dtype)
    return StateSpaceModel(
        GpsDrDynamics(F=f, Q=q * q_scale, Q_structure=Q_structure or structure),
        GpsDrMeasurement(R=r, dt=c.dt, R_structure=R_structure or structure, analytic_jacobian=analytic_jacobian),
    )


def cv_matrices(c: GpsDrConstants, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(F [4, 4], H [2, 4], Q [4, 4], R [2, 2])`` of the constant-velocity model ``[s_e, v_e, s_n, v_n]``."""
    t = c.dt
    fa = torch.tensor([[1.0, t], [0.0, 1.0]], dtype=torch.float64)
    qa = c.cv_sigma_a**2 * torch.tensor([[t**3 / 3, t**2 / 2], [t**2 / 2, t]], dtype=torch.float64)
    f = torch.block_diag(fa, fa)
    q = torch.block_diag(qa, qa)
    h = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    r = c.sigma_gps**2 * torch.eye(2, dtype=torch.float64)
    return f.to(dtype), h.to(dtype), q.to(dtype), r.to(dtype)


def make_cv_model(
    *,
    dtype: torch.dtype = torch.float64,
    structure: str = "full",
    Q_structure: str | None = None,
    R_structure: str | None = None,  # noqa: N803
) -> LinearModel:
    """Linear CV model on the GPS positions (the Kalman-filter case)."""
    f, h, q, r = cv_matrices(gpsdr_constants(), dtype)
    return LinearModel(F=f, H=h, Q=q, R=r, Q_structure=Q_structure or structure, R_structure=R_structure or structure)


@dataclass
class BenchData:
    """One benchmark data set.

    Attributes:
        truth: ``[B, T + 1, 8]`` true states (index 0 = before the first measurement).
        measurements: ``[B, T, 4]`` GPS/DR measurements.
        initial_mean: ``[B, 8]``; initial_cov: ``[8, 8]`` (``I_8``, p000).
        cv_measurements ``[B, T, 2]``, cv_initial_mean ``[B, 4]``, cv_initial_cov ``[4, 4]``:
            the same GPS positions for the linear CV model.
    """

    truth: Tensor
    measurements: Tensor
    initial_mean: Tensor
    initial_cov: Tensor
    cv_measurements: Tensor
    cv_initial_mean: Tensor
    cv_initial_cov: Tensor

    def subset(self, batch_size: int) -> BenchData:
        """The first ``batch_size`` trajectories."""
        return BenchData(
            self.truth[:batch_size],
            self.measurements[:batch_size],
            self.initial_mean[:batch_size],
            self.initial_cov,
            self.cv_measurements[:batch_size],
            self.cv_initial_mean[:batch_size],
            self.cv_initial_cov,
        )


def simulate_gpsdr(*, batch_size: int, steps: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> BenchData:
    """Scripted vehicle trajectories (not drawn from the filter's model) and noisy measurements.

    Each vehicle drives with speed ``s(t) = s0 + ds sin(w1 t + p1)`` and a sinusoidal turn rate,
    so velocity and acceleration are smooth and the speed stays in ``[5, 20]`` m/s; the gyro
    drift and odometer scale are random constants per trajectory.
    """
    c = gpsdr_constants()
    g = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64

    def uni(lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(batch_size, 1, generator=g, dtype=f64)

    t = torch.arange(steps + 1, dtype=f64)[None] * c.dt
    s0, ds, w1, p1 = uni(10.0, 15.0), uni(0.0, 3.0), uni(0.02, 0.3), uni(0.0, 2 * math.pi)
    h0, turn, w2, p2 = uni(0.0, 2 * math.pi), uni(0.0, 0.2), uni(0.02, 0.2), uni(0.0, 2 * math.pi)
    speed = s0 + ds * torch.sin(w1 * t + p1)
    dspeed = ds * w1 * torch.cos(w1 * t + p1)
    heading = h0 + turn / w2 * (torch.sin(w2 * t + p2) - torch.sin(p2))
    dheading = turn * torch.cos(w2 * t + p2)
    ve, vn = speed * torch.sin(heading), speed * torch.cos(heading)
    ae = dspeed * torch.sin(heading) + speed * dheading * torch.cos(heading)
    an = dspeed * torch.cos(heading) - speed * dheading * torch.sin(heading)
    # Trapezoidal position integration; error O(dt^3) per step, irrelevant next to 15 m GPS noise.
    se = torch.cat([torch.zeros(batch_size, 1, dtype=f64), torch.cumsum(0.5 * c.dt * (ve[:, 1:] + ve[:, :-1]), 1)], 1)
    sn = torch.cat([torch.zeros(batch_size, 1, dtype=f64), torch.cumsum(0.5 * c.dt * (vn[:, 1:] + vn[:, :-1]), 1)], 1)
    eps = (0.02 * torch.randn(batch_size, 1, generator=g, dtype=f64)).expand_as(se)
    psi = (1.0 + 0.005 * torch.randn(batch_size, 1, generator=g, dtype=f64)).expand_as(se)
    truth = torch.stack([se, ve, ae, sn, vn, an, eps, psi], -1)
    x = truth[:, 1:]
    sp2 = x[..., 1] ** 2 + x[..., 4] ** 2
    clean = torch.stack(
        [
            x[..., 0],
            x[..., 3],
            _RAD2DEG * (x[..., 4] * x[..., 2] - x[..., 1] * x[..., 5]) / sp2 + x[..., 6],
            x[..., 7] * c.dt * torch.sqrt(sp2),
        ],
        -1,
    )
    sig = torch.tensor([c.sigma_gps, c.sigma_gps, c.sigma_gyro, c.sigma_odo], dtype=f64)
    z = clean + sig * torch.randn(clean.shape, generator=g, dtype=f64)
    m0 = truth[:, 0].clone()
    m0[:, 6], m0[:, 7] = 0.0, 1.0  # the filter starts from the nominal sensor errors
    cv_m0 = truth[:, 0][:, [0, 1, 3, 4]]
    return BenchData(
        truth=truth.to(dtype),
        measurements=z.to(dtype),
        initial_mean=m0.to(dtype),
        initial_cov=torch.eye(8, dtype=dtype),
        cv_measurements=z[..., :2].contiguous().to(dtype),
        cv_initial_mean=cv_m0.contiguous().to(dtype),
        cv_initial_cov=(100.0 * torch.eye(4, dtype=f64)).to(dtype),
    )
