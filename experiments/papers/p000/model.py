"""GPS / dead-reckoning vehicle model of p000 (Yang & Zhang): manoeuvre model plus gyro and odometer.

State (8): ``x = [s_e, v_e, a_e, s_n, v_n, a_n, eps, psi]``: east/north position (m), velocity
(m/s) and acceleration (m/s^2), gyro drift ``eps`` (rad/s) and odometer scale factor ``psi``.
Measurements (4): GPS east and north position (m), gyro yaw rate (rad/s) and odometer distance
over one sample (m).  Headings are azimuths (clockwise from north), so the yaw rate is
``d/dt atan(v_e / v_n)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from difffilter.linalg import block_diag
from difffilter.models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from difffilter.models.layout import StateLayout, describe
from difffilter.models.motion import ConstantAcceleration, CurrentStatistical, Singer, _Kinematic
from difffilter.params import Interval, Positive, register_constrained, register_covariance

__all__ = [
    "A_MAX_VEHICLE",
    "GPSDR_LAYOUT",
    "GPSDR_PAPER",
    "GpsDrDynamics",
    "GpsDrMeasurement",
    "GpsDrModel",
    "gpsdr_paper_initial_belief",
]

#: Largest acceleration expected of a passenger car in ordinary driving (m/s^2): the deceleration
#: AASHTO's "A Policy on Geometric Design of Highways and Streets" (Green Book, 2011, sec. 3.2.2)
#: takes as comfortable for most drivers (3.4 m/s^2, the stopping-sight-distance design value).
A_MAX_VEHICLE = 3.4

#: p000's published settings (SI units).  p000 gives no manoeuvre std ``sigma_a``: it follows from
#: the current-statistical model of its ref. [3] (Zhou Hongren), ``sigma_a^2 = (4 - pi)/pi a_max^2``
#: (the variance of the modified Rayleigh acceleration density at zero mean acceleration) with
#: ``a_max`` = :data:`A_MAX_VEHICLE`: ``sigma_a = 1.777 m/s^2``.
GPSDR_PAPER: dict[str, float] = {
    "dt": 0.1,
    "sigma_gps": 15.0,
    "sigma_gyro": math.radians(0.4),
    "sigma_odometer": 1.0,
    "sigma_eps": math.radians(0.015),
    "sigma_psi": 0.005,
    "tau": 100.0,
    "tau_eps": 100.0,
    "sigma_a": math.sqrt((4.0 - math.pi) / math.pi) * A_MAX_VEHICLE,
    "a_max": A_MAX_VEHICLE,
}


#: State of the p000 GPS/DR models: east/north position, velocity, acceleration, gyro drift
#: ``eps`` and odometer scale ``psi``.
GPSDR_LAYOUT = StateLayout(
    names=("s_e", "v_e", "a_e", "s_n", "v_n", "a_n", "eps", "psi"),
    units=("m", "m/s", "m/s^2", "m", "m/s", "m/s^2", "rad/s", "1"),
    position=(0, 3),
)


class GpsDrDynamics(DynamicsModel):
    """p000 dynamics: a two-axis manoeuvre model for ``[s_e, v_e, a_e, s_n, v_n, a_n]`` plus the
    sensor-error states.

    * gyro drift, first-order Gauss-Markov: ``eps_k = e^{-T/tau_eps} eps_{k-1} + w``, with
      ``Var w = sigma_eps^2 (1 - e^{-2T/tau_eps})`` so ``sigma_eps`` is its stationary std;
    * odometer scale, random walk: ``psi_k = psi_{k-1} + w``, ``Var w = sigma_psi^2 T / 100 s``
      (its std grows by ``sigma_psi`` per 100 s; p000 only says "sigma_psi = 0.005").

    Args:
        motion: a 2-axis acceleration model from :mod:`~difffilter.models.motion`
            (:class:`~difffilter.models.motion.ConstantAcceleration` for p000's eq. (19),
            ``Singer`` for eq. (18), ``CurrentStatistical``); its parameters are learnable.
        tau_eps: gyro-drift correlation time (s); learnable (``Interval(1, 1e5)``).
        sigma_eps: gyro-drift stationary std (rad/s); learnable (``Positive``).
        sigma_psi: odometer-scale random-walk std per 100 s; learnable (``Positive``).
    """

    psi_time = 100.0

    def __init__(
        self,
        *,
        motion: _Kinematic,
        tau_eps: float = 100.0,
        sigma_eps: float = GPSDR_PAPER["sigma_eps"],
        sigma_psi: float = GPSDR_PAPER["sigma_psi"],
    ) -> None:
        super().__init__()
        if motion.state_dim != 6 or motion.order != 3:
            raise ValueError("motion must be a 2-axis acceleration model (state [s, v, a] per axis, 6 states)")
        self.motion = motion
        self.state_dim = 8
        dtype = motion.dt.dtype
        register_constrained(self, "tau_eps", torch.tensor(tau_eps, dtype=dtype), Interval(1.0, 1e5))
        register_constrained(self, "sigma_eps", torch.tensor(sigma_eps, dtype=dtype), Positive())
        register_constrained(self, "sigma_psi", torch.tensor(sigma_psi, dtype=dtype), Positive())

    def _sensor_decay(self, u: Controls) -> tuple[Tensor, Tensor]:
        dt = self.motion.step_dt(u)
        return torch.exp(-dt / self.tau_eps), dt

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        decay, _ = self._sensor_decay(u)
        kin = self.motion(x[..., :6], u)
        return torch.cat([kin, (decay * x[..., 6])[..., None], x[..., 7:8]], -1)

    def _sensor_matrix(self, u: Controls) -> Tensor:
        decay, _ = self._sensor_decay(u)
        return torch.diag_embed(torch.stack([decay, torch.ones_like(decay)], -1))

    def matrix(self, u: Controls = None) -> Tensor:
        return block_diag(self.motion.matrix(u), self._sensor_matrix(u))

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        jac = block_diag(self.motion.jacobian(x[..., :6], u), self._sensor_matrix(u))
        return jac.expand(*torch.broadcast_shapes(x.shape[:-1], jac.shape[:-2]), 8, 8)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        decay, dt = self._sensor_decay(u)
        q_eps = self.sigma_eps**2 * (1.0 - decay * decay)
        q_psi = self.sigma_psi**2 * dt / self.psi_time * torch.ones_like(q_eps)
        return block_diag(self.motion.process_noise(x[..., :6], u), torch.diag_embed(torch.stack([q_eps, q_psi], -1)))

    @property
    def Q(self) -> Tensor:  # noqa: N802 - field notation
        """Process noise at the constructor's ``dt`` and the zero state."""
        return self.process_noise(torch.zeros(8, dtype=self.motion.dt.dtype, device=self.motion.dt.device))


class GpsDrMeasurement(MeasurementModel):
    """p000 measurements ``z = [s_e, s_n, omega, s]`` (eq. (20), (23)).

    .. math::
        \\omega = \\frac{v_n a_e - v_e a_n}{D} + \\varepsilon, \\qquad
        s = \\psi T \\sqrt{D + v_0^2}, \\qquad D = g v_e^2 + v_n^2 + v_0^2 \\text{ (for } \\omega)

    ``g`` is p000's nonlinearity factor (1 = the physical model, 1.5 in its second experiment).
    Speed protection: ``v_0`` (``speed_floor``, default 0.1 m/s) is added in quadrature to the
    speed in both denominators and under the root, so ``h`` and its Jacobian are smooth and
    finite at standstill (the yaw rate tends to ``eps``, the odometer to ``psi T v_0``); the
    relative bias at speed ``v`` is ``(v_0 / v)^2`` for the gyro and ``v_0^2 / (2 v^2)`` for the
    odometer (1e-4 and 5e-5 at 10 m/s).

    Args:
        dt: sample interval ``T`` (s) for the odometer unless ``u["dt"]`` is given.
        sigma_gps, sigma_gyro, sigma_odometer: noise standard deviations (m, rad/s, m) giving
            ``R = diag(sigma_gps^2, sigma_gps^2, sigma_gyro^2, sigma_odometer^2)``; learnable
            with ``R_structure`` (default ``"diagonal"``).
        g: nonlinearity factor (fixed).
        speed_floor: ``v_0`` (m/s, fixed).
    """

    def __init__(
        self,
        *,
        dt: float = GPSDR_PAPER["dt"],
        sigma_gps: float = GPSDR_PAPER["sigma_gps"],
        sigma_gyro: float = GPSDR_PAPER["sigma_gyro"],
        sigma_odometer: float = GPSDR_PAPER["sigma_odometer"],
        g: float = 1.0,
        speed_floor: float = 0.1,
        R_structure: str = "diagonal",  # noqa: N803
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        dtype = dtype or torch.get_default_dtype()
        if not (g > 0 and speed_floor > 0 and dt > 0):
            raise ValueError("g, speed_floor and dt must be positive")
        self.measurement_dim = 4
        self.g, self.speed_floor = float(g), float(speed_floor)
        self.register_buffer("dt", torch.tensor(float(dt), dtype=dtype))
        sig = torch.tensor([sigma_gps, sigma_gps, sigma_gyro, sigma_odometer], dtype=dtype)
        register_covariance(self, "R", torch.diag(sig * sig), R_structure)

    def _terms(self, x: Tensor, u: Controls) -> tuple[Tensor, ...]:
        ve, ae, vn, an = x[..., 1], x[..., 2], x[..., 4], x[..., 5]
        v0sq = self.speed_floor**2
        den = self.g * ve * ve + vn * vn + v0sq
        dt = u["dt"][..., 0] if isinstance(u, dict) and "dt" in u else self.dt
        return ve, ae, vn, an, den, torch.sqrt(den), vn * ae - ve * an, dt

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        ve, ae, vn, an, den, speed, num, dt = self._terms(x, u)
        omega = num / den + x[..., 6]
        dist = x[..., 7] * dt * speed
        return torch.stack([x[..., 0], x[..., 3], omega, dist], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        ve, ae, vn, an, den, speed, num, dt = self._terms(x, u)
        psi = x[..., 7]
        zero, one = torch.zeros_like(ve), torch.ones_like(ve)
        dt = dt * one
        r = num / (den * den)
        gyro = [zero, -an / den - 2.0 * self.g * ve * r, vn / den, zero, ae / den - 2.0 * vn * r, -ve / den, one, zero]
        k = psi * dt / speed
        odo = [zero, k * self.g * ve, zero, zero, k * vn, zero, zero, dt * speed]
        gps_e = [one, zero, zero, zero, zero, zero, zero, zero]
        gps_n = [zero, zero, zero, one, zero, zero, zero, zero]
        return torch.stack([torch.stack(row, -1) for row in (gps_e, gps_n, gyro, odo)], -2)


def _motion(kind: str, dt: float, sigma_a: float, tau: float, a_max: float, dtype: torch.dtype | None) -> _Kinematic:
    if kind == "paper":
        return ConstantAcceleration.paper(axes=2, dt=dt, sigma_a=sigma_a, dtype=dtype)
    if kind == "singer":
        return Singer(axes=2, dt=dt, tau=tau, sigma_a=sigma_a, dtype=dtype)
    if kind == "current_statistical":
        return CurrentStatistical(axes=2, dt=dt, tau=tau, a_max=a_max, dtype=dtype)
    raise ValueError(f"motion must be 'paper', 'singer', 'current_statistical' or a motion model, got {kind!r}")


class GpsDrModel(StateSpaceModel):
    """p000's GPS/DR model: :class:`GpsDrDynamics` + :class:`GpsDrMeasurement`.

    Args:
        motion: ``"paper"`` (p000 eq. (19): constant-acceleration transition,
            ``Q = diag(2 sigma_a^2 Q_axis, 2 sigma_a^2 Q_axis)``), ``"singer"`` (eq. (18) with the
            exact Singer ``Q``), ``"current_statistical"`` (Zhou's adaptive variance, bounded by
            ``a_max``) or a 2-axis motion module.
        dt: sample interval ``T`` (s).
        sigma_a: manoeuvre acceleration std (m/s^2), per axis or scalar (``paper``/``singer``).
        tau: manoeuvre time constant (s) (``singer``/``current_statistical``).
        a_max: largest acceleration (m/s^2) (``current_statistical``).
        tau_eps, sigma_eps, sigma_psi: sensor-error states (see :class:`GpsDrDynamics`).
        sigma_gps, sigma_gyro, sigma_odometer, g, speed_floor, R_structure: see
            :class:`GpsDrMeasurement`.

    Learnable: the motion model's ``q`` or ``tau``/``sigma_a``/``a_max``, ``tau_eps``,
    ``sigma_eps``, ``sigma_psi`` and ``R``.  :meth:`paper` builds the hand-tuned filter.
    """

    def __init__(
        self,
        *,
        motion: str | _Kinematic = "paper",
        dt: float = GPSDR_PAPER["dt"],
        sigma_a: float = GPSDR_PAPER["sigma_a"],
        tau: float = GPSDR_PAPER["tau"],
        a_max: float = GPSDR_PAPER["a_max"],
        tau_eps: float = GPSDR_PAPER["tau_eps"],
        sigma_eps: float = GPSDR_PAPER["sigma_eps"],
        sigma_psi: float = GPSDR_PAPER["sigma_psi"],
        sigma_gps: float = GPSDR_PAPER["sigma_gps"],
        sigma_gyro: float = GPSDR_PAPER["sigma_gyro"],
        sigma_odometer: float = GPSDR_PAPER["sigma_odometer"],
        g: float = 1.0,
        speed_floor: float = 0.1,
        R_structure: str = "diagonal",  # noqa: N803
        dtype: torch.dtype | None = None,
    ) -> None:
        kin = _motion(motion, dt, sigma_a, tau, a_max, dtype) if isinstance(motion, str) else motion
        dynamics = GpsDrDynamics(motion=kin, tau_eps=tau_eps, sigma_eps=sigma_eps, sigma_psi=sigma_psi)
        measurement = GpsDrMeasurement(
            dt=dt,
            sigma_gps=sigma_gps,
            sigma_gyro=sigma_gyro,
            sigma_odometer=sigma_odometer,
            g=g,
            speed_floor=speed_floor,
            R_structure=R_structure,
            dtype=dtype,
        )
        super().__init__(dynamics, measurement)
        mean0, cov0 = gpsdr_paper_initial_belief()
        describe(
            self,
            layout=GPSDR_LAYOUT,
            learn=[*kin.parametrizations.keys(), "R"],  # type: ignore[union-attr]
            initial_mean=mean0.tolist(),
            initial_var=torch.diagonal(cov0).tolist(),
        )

    @classmethod
    def paper(cls, *, motion: str = "paper", g: float = 1.0, dtype: torch.dtype | None = None, **overrides: float) -> GpsDrModel:
        """The hand-tuned p000 filter model (:data:`GPSDR_PAPER`; keyword overrides allowed)."""
        opts = {k: v for k, v in GPSDR_PAPER.items()}
        opts.update(overrides)
        return cls(motion=motion, g=g, dtype=dtype, **opts)


def gpsdr_paper_initial_belief(dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
    """p000's initial belief: ``X(0|0) = [0, 10, 0, 0, 10, 0, 0, 1]`` (``psi = 1``, the [fix]),
    ``P(0|0) = I_8``."""
    dtype = dtype or torch.get_default_dtype()
    mean = torch.tensor([0.0, 10.0, 0.0, 0.0, 10.0, 0.0, 0.0, 1.0], dtype=dtype)
    return mean, torch.eye(8, dtype=dtype)
