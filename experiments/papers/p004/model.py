"""IMU-driven GNSS/IMU vehicle models of p004 (Li, Zhu, Wang & Lyu); its switching statistics are
in :mod:`experiments.papers.p004.switching`.

Frames: navigation frame ENU (east, north, up), body frame FLU (forward, left, up); gravity
``g_n = [0, 0, -9.80665]`` m/s^2, flat non-rotating earth (a 400 s, 5 km drive).  Headings are
azimuths ``psi`` (clockwise from north); the body yaw about "up" is ``pi/2 - psi``.

IMU inputs per step ``k`` (controls, interval ``(t_{k-1}, t_k]``, what an IMU's velocity and
angle increments divided by ``T`` deliver):

* ``u["accel"]``: mean specific force ``(1/T) C_bn(t_{k-1}) (v(t_k) - v(t_{k-1}) - g_n T)``,
  resolved in the body frame at the *start* of the interval (m/s^2), ``[..., 3]`` (planar:
  ``[..., 2]``, forward and left);
* ``u["gyro"]``: mean angular rate ``Delta theta / T`` (rad/s), ``[..., 3]`` (planar: ``[..., 1]``,
  yaw rate about up, counter-clockwise positive);
* optional ``u["dt"] [..., 1]`` overriding the constructor's ``T``.

With these inputs the velocity update ``v_k = v_{k-1} + (C_nb(q_{k-1}) (f - b_a) + g_n) T`` is exact;
position uses the trapezoid ``p_k = p_{k-1} + (v_{k-1} + v_k) T / 2`` (error ``O(T^3)`` jerk,
absorbed by ``Q``) and attitude the exact rotation by ``(omega - b_g) T``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from difffilter._util import control
from difffilter.linalg import block_diag
from difffilter.models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel, wrap_angle
from difffilter.models.layout import StateLayout, describe
from difffilter.models.navigation.antenna import antenna_offset, has_antenna, planar_rotation, register_antenna
from difffilter.models.navigation.quaternion import quaternion_multiply, quaternion_to_rotation, rotation_quaternion
from difffilter.params import Bounded, Positive, register_constrained, register_covariance

__all__ = [
    "PLANAR_LAYOUT",
    "SPATIAL_LAYOUT",
    "GNSS_IMU_PAPER",
    "GRAVITY",
    "GnssImuDynamics",
    "GnssImuModel",
    "GnssMeasurement",
    "PlanarGnssImuDynamics",
    "quaternion_multiply",
    "quaternion_to_rotation",
    "wrap_angle",
]

GRAVITY = 9.80665

#: Settings used for p004 (SI units).  Paper values: accelerometer bias 0.05 mg, gyro bias
#: 0.1 deg/h (constant biases: p004 gives one value each and no drift), process-noise variance
#: 0.01 (read as the accelerometer white noise, 0.1 m/s^2 on each 1 s mean), azimuth error
#: variance 1 deg^2 (the optional dual-antenna heading).  Our choices: GNSS position noise 0.1 m
#: for the paper's "20 dB" (10^(-20/20) of a 1 m reference, which fits the published cm-level
#: RMSEs), GNSS velocity noise 0.05 m/s, gyro white noise 0.1 deg/s on each 1 s mean.  The bias
#: random walks of the filter encode p004's constant biases by a stated rule: a walk that adds 1 %
#: of the bias prior's variance over the 400 s drive, sigma_walk = 0.1 sigma_bias / sqrt(400 s):
#: 2.45e-6 m/s^2/sqrt(s) and 2.42e-9 rad/s/sqrt(s) (the parameters are ``Positive``, so not 0; the
#: earlier 1e-5 / 1e-6 grew the gyro-bias variance ~1700x beyond the constant true bias, NEES of
#: ``b_g`` 0.005 instead of 1; 1e-9 / 1e-12 were out of reach of a learner in ~100 steps).
#: ``sigma_position_step`` (m per step): std of the trapezoidal position step's own error, 1 cm
#: measured on p004's drives (rms 0.010 m on the fixed script, 0.011 m on randomised ones).
GNSS_IMU_PAPER: dict[str, float] = {
    "dt": 1.0,
    "sigma_accel": 0.1,
    "sigma_gyro": math.radians(0.1),
    "sigma_accel_bias": 0.05e-3 * GRAVITY,
    "sigma_gyro_bias": math.radians(0.1) / 3600.0,
    "sigma_accel_bias_walk": 0.1 * 0.05e-3 * GRAVITY / 20.0,
    "sigma_gyro_bias_walk": 0.1 * math.radians(0.1) / 3600.0 / 20.0,
    "sigma_position_step": 0.01,
    "sigma_gnss": 0.1,
    "sigma_gnss_velocity": 0.05,
    "sigma_heading": math.radians(1.0),
}


#: Planar state ``[p_e, p_n, v_e, v_n, psi, b_f, b_l, b_g]`` and the 16-state ``[p, v, q, b_a, b_g]``.
PLANAR_LAYOUT = StateLayout(
    names=("p_e", "p_n", "v_e", "v_n", "psi", "b_f", "b_l", "b_g"),
    units=("m", "m", "m/s", "m/s", "rad", "m/s^2", "m/s^2", "rad/s"),
    position=(0, 1),
    angles=(4,),
)
SPATIAL_LAYOUT = StateLayout(
    names=("p_e", "p_n", "p_u", "v_e", "v_n", "v_u", "q_w", "q_x", "q_y", "q_z", "b_ax", "b_ay", "b_az", "b_gx", "b_gy", "b_gz"),
    units=("m",) * 3 + ("m/s",) * 3 + ("1",) * 4 + ("m/s^2",) * 3 + ("rad/s",) * 3,
    position=(0, 1, 2),
)


def _step_dt(u: Controls, default: Tensor) -> Tensor:
    if isinstance(u, dict) and "dt" in u:
        return u["dt"][..., 0]
    return default


def _imu(u: Controls) -> tuple[Tensor, Tensor]:
    if not isinstance(u, dict) or "accel" not in u or "gyro" not in u:
        raise ValueError('GNSS/IMU models need controls {"accel": [B, T, k], "gyro": [B, T, k]}')
    return u["accel"], u["gyro"]


def _kinematic_noise(dt: Tensor, var: Tensor, dims: int, step_var: Tensor) -> Tensor:
    """Position/velocity noise ``[..., 2 d, 2 d]`` (layout ``[p (d), v (d)]``) for accelerometer
    noise of variance ``var`` on each ``T``-mean (what the IMU model delivers: one draw per
    interval), ``var [[T^4/4, T^3/2], [T^3/2, T^2]]``, plus ``step_var`` on position: the
    variance of the trapezoidal position step's own error (``O(T^3)`` jerk), which also keeps
    ``Q`` positive definite (the sample-mean part alone is singular)."""
    eye = torch.eye(dims, dtype=dt.dtype, device=dt.device)
    blk = lambda c: c[..., None, None] * eye  # noqa: E731
    top = torch.cat([blk(var * dt**4 / 4 + step_var), blk(var * dt**3 / 2)], -1)
    bottom = torch.cat([blk(var * dt**3 / 2), blk(var * dt**2)], -1)
    return torch.cat([top, bottom], -2)


class _ImuNoise(DynamicsModel):
    """Learnable IMU noise levels shared by the 3-D and planar models."""

    def _register_noise(self, dt: float, opts: dict[str, float], dtype: torch.dtype | None) -> None:
        dtype = dtype or torch.get_default_dtype()
        self.register_buffer("dt", torch.tensor(float(dt), dtype=dtype))
        step = float(opts["sigma_position_step"])
        if not (math.isfinite(step) and step > 0.0):
            raise ValueError(f"sigma_position_step must be a positive number (m), got {step}")
        self.register_buffer("position_step_var", torch.tensor(step * step, dtype=dtype))
        for name in ("sigma_accel", "sigma_gyro", "sigma_accel_bias_walk", "sigma_gyro_bias_walk"):
            register_constrained(self, name, torch.tensor(float(opts[name]), dtype=dtype), Positive())

    @property
    def Q(self) -> Tensor:  # noqa: N802 - field notation
        """Process noise at the constructor's ``T``."""
        return self.process_noise(torch.zeros(self.state_dim, dtype=self.dt.dtype, device=self.dt.device))


class GnssImuDynamics(_ImuNoise):
    """p004 strapdown prediction, state (16) ``[p (3), v (3), q (4), b_a (3), b_g (3)]``.

    .. math::
        q_k = \\frac{\\bar q \\otimes \\exp((\\omega - b_g) T / 2)}{\\|\\cdot\\|}, \\;
        v_k = v + (C(\\bar q)(f - b_a) + g_n) T, \\; p_k = p + (v + v_k) T/2,

    ``bar q = q / |q|`` (``f`` keeps the quaternion normalised, so sigma points and updates that
    leave the unit sphere are projected back).  Biases are random walks.

    ``Q = blockdiag(Q_pv, (sigma_gyro T / 2)^2 I_4, sigma_ba_walk^2 T I_3, sigma_bg_walk^2 T I_3)``
    with ``Q_pv`` from white accelerometer noise (``sigma_accel`` on each ``T``-mean;
    isotropic, so rotating it to the navigation frame changes nothing).  The quaternion block is
    isotropic in 4-D: its tangential part is the gyro noise ``(T/2) Xi(q) n_g``, and its radial
    part is removed by the next normalisation, while keeping ``Q`` positive definite.

    Learnable (``Positive``): ``sigma_accel`` (m/s^2), ``sigma_gyro`` (rad/s),
    ``sigma_accel_bias_walk`` (m/s^2/sqrt(s)), ``sigma_gyro_bias_walk`` (rad/s/sqrt(s)).
    Controls: ``accel [..., 3]``, ``gyro [..., 3]`` (module docstring).
    """

    def __init__(self, *, dt: float = 1.0, dtype: torch.dtype | None = None, **noise: float) -> None:
        super().__init__()
        self.state_dim = 16
        self._register_noise(dt, {**GNSS_IMU_PAPER, **noise}, dtype)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        accel, gyro = _imu(u)
        dt = _step_dt(u, self.dt)[..., None]
        p, v, q, ba, bg = x[..., 0:3], x[..., 3:6], x[..., 6:10], x[..., 10:13], x[..., 13:16]
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        a = (quaternion_to_rotation(q) @ (accel - ba)[..., None])[..., 0]
        a = a + torch.tensor([0.0, 0.0, -GRAVITY], dtype=x.dtype, device=x.device)
        v_new = v + a * dt
        q_new = quaternion_multiply(q, rotation_quaternion((gyro - bg) * dt))
        q_new = q_new / torch.linalg.vector_norm(q_new, dim=-1, keepdim=True)
        p_new = p + 0.5 * (v + v_new) * dt
        shape = torch.broadcast_shapes(p_new.shape, q_new.shape[:-1] + (3,))
        parts = [p_new, v_new, q_new, ba, bg]
        return torch.cat([t.expand(*shape[:-1], t.shape[-1]) for t in parts], -1)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = _step_dt(u, self.dt)
        one = torch.ones_like(dt)
        eye = lambda d, var: var[..., None, None] * torch.eye(d, dtype=dt.dtype, device=dt.device)  # noqa: E731
        return block_diag(
            _kinematic_noise(dt, self.sigma_accel**2 * one, 3, self.position_step_var * one),
            eye(4, (self.sigma_gyro * dt / 2) ** 2),
            eye(3, self.sigma_accel_bias_walk**2 * dt),
            eye(3, self.sigma_gyro_bias_walk**2 * dt),
        )


class PlanarGnssImuDynamics(_ImuNoise):
    """Planar reduction of :class:`GnssImuDynamics` for a level vehicle, state (8)
    ``[p_e, p_n, v_e, v_n, psi, b_f, b_l, b_g]`` (heading ``psi`` clockwise from north,
    unwrapped).

    .. math::
        \\psi_k = \\psi - (\\omega - b_g) T, \\;
        a = R(\\psi) (f - b), \\; R(\\psi) = \\begin{bmatrix}\\sin\\psi & -\\cos\\psi \\\\
        \\cos\\psi & \\sin\\psi\\end{bmatrix}, \\; v_k = v + a T, \\; p_k = p + (v + v_k) T / 2.

    It keeps p004's nonlinearity (velocity rotated by an uncertain heading) with half the states
    and no quaternion constraint, which makes the EKF/UKF comparison cheaper and cleaner.
    ``Q = blockdiag(Q_pv, (sigma_gyro T)^2, sigma_ba_walk^2 T I_2, sigma_bg_walk^2 T)``.
    Learnable: as :class:`GnssImuDynamics`.  Controls: ``accel [..., 2]`` (forward, left),
    ``gyro [..., 1]`` (counter-clockwise yaw rate).  Has an analytic Jacobian.
    """

    def __init__(self, *, dt: float = 1.0, dtype: torch.dtype | None = None, **noise: float) -> None:
        super().__init__()
        self.state_dim = 8
        self._register_noise(dt, {**GNSS_IMU_PAPER, **noise}, dtype)

    def _parts(self, x: Tensor, u: Controls) -> tuple[Tensor, ...]:
        accel, gyro = _imu(u)
        dt = _step_dt(u, self.dt)
        psi = x[..., 4]
        ff, fl = accel[..., 0] - x[..., 5], accel[..., 1] - x[..., 6]
        s, c = torch.sin(psi), torch.cos(psi)
        return dt, psi, ff, fl, s, c, gyro[..., 0] - x[..., 7]

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        dt, psi, ff, fl, s, c, w = self._parts(x, u)
        a = torch.stack([ff * s - fl * c, ff * c + fl * s], -1)
        v = x[..., 2:4]
        v_new = v + a * dt[..., None]
        p_new = x[..., 0:2] + 0.5 * (v + v_new) * dt[..., None]
        return torch.cat([p_new, v_new, (psi - w * dt)[..., None], x[..., 5:8].expand(*p_new.shape[:-1], 3)], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        dt, psi, ff, fl, s, c, w = self._parts(x, u)
        shape = torch.broadcast_shapes(x.shape[:-1], ff.shape)
        jac = torch.eye(8, dtype=x.dtype, device=x.device).expand(*shape, 8, 8).clone()
        dt = dt * torch.ones(shape, dtype=x.dtype, device=x.device)
        # d a / d [psi, b_f, b_l]
        da = torch.stack(
            [torch.stack([ff * c + fl * s, -s, c], -1), torch.stack([-ff * s + fl * c, -c, -s], -1)],
            -2,
        ).expand(*shape, 2, 3)
        cols = [4, 5, 6]
        jac[..., 2:4, cols] = da * dt[..., None, None]
        jac[..., 0:2, cols] = da * (0.5 * dt * dt)[..., None, None]
        jac[..., 0, 2] = dt
        jac[..., 1, 3] = dt
        jac[..., 4, 7] = dt
        return jac

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = _step_dt(u, self.dt)
        eye = lambda d, var: var[..., None, None] * torch.eye(d, dtype=dt.dtype, device=dt.device)  # noqa: E731
        return block_diag(
            _kinematic_noise(dt, self.sigma_accel**2 * torch.ones_like(dt), 2, self.position_step_var * torch.ones_like(dt)),
            eye(1, (self.sigma_gyro * dt) ** 2),
            eye(2, self.sigma_accel_bias_walk**2 * dt),
            eye(1, self.sigma_gyro_bias_walk**2 * dt),
        )


class GnssMeasurement(MeasurementModel):
    """GNSS fix: position, optionally velocity and dual-antenna heading (p004 ``z_GNSS``).

    ``z = [p, (v), (psi)]`` with ``psi`` the azimuth of the body's forward axis (3-D:
    ``atan2(C_e1, C_n1)`` from the quaternion; planar: the heading state).  ``residual`` wraps the
    heading component to ``[-pi, pi)``.

    Args:
        planar: state layout of :class:`PlanarGnssImuDynamics` (else :class:`GnssImuDynamics`).
        velocity, heading: whether the fix includes velocity / heading.
        sigma_gnss, sigma_gnss_velocity, sigma_heading: noise stds giving a diagonal ``R``,
            learnable with ``R_structure``.
        accuracy_exponent: ``None`` (default): ``R`` is constant.  A number ``gamma`` registers a
            learnable ``accuracy_exponent`` (``Bounded(-4, 4)``) and scales the position block by
            the receiver's reported accuracy ``u["gnss_accuracy"] [..., 1]`` (m):
            ``R_pp,k = R_pp (a_k / sigma_gnss)^(2 gamma)``; ``gamma = 0`` is the constant ``R``.
        lever_arm, latency: optional antenna lever arm (body forward, left, up; m) and receiver
            time offset (s), learnable by name: the position fix is ``p + C_nb l - latency v``
            (:mod:`~difffilter.models.navigation.antenna`; the filters then differentiate ``h``).
    """

    def __init__(
        self,
        *,
        planar: bool = False,
        velocity: bool = False,
        heading: bool = False,
        sigma_gnss: float = GNSS_IMU_PAPER["sigma_gnss"],
        sigma_gnss_velocity: float = GNSS_IMU_PAPER["sigma_gnss_velocity"],
        sigma_heading: float = GNSS_IMU_PAPER["sigma_heading"],
        R_structure: str = "diagonal",  # noqa: N803
        accuracy_exponent: float | None = None,
        lever_arm: Sequence[float] | None = None,
        latency: float | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        d = 2 if planar else 3
        self.planar, self.velocity, self.heading = planar, velocity, heading
        self._lin = list(range(d)) + (list(range(d, 2 * d)) if velocity else [])
        sig = [sigma_gnss] * d + ([sigma_gnss_velocity] * d if velocity else []) + ([sigma_heading] if heading else [])
        self.measurement_dim = len(sig)
        self.angular = (self.measurement_dim - 1,) if heading else ()  # the heading wraps (residual)
        s = torch.tensor(sig, dtype=dtype or torch.get_default_dtype())
        register_covariance(self, "R", torch.diag(s * s), R_structure)
        self.accuracy_reference = float(sigma_gnss)
        self.scales_with_accuracy = accuracy_exponent is not None
        if accuracy_exponent is not None:
            if not abs(float(accuracy_exponent)) < 4.0:
                raise ValueError(f"accuracy_exponent must lie in (-4, 4), got {accuracy_exponent}")
            register_constrained(self, "accuracy_exponent", torch.tensor(float(accuracy_exponent), dtype=s.dtype), Bounded(-4.0, 4.0))
        register_antenna(self, lever_arm=lever_arm, latency=latency, dtype=s.dtype)

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        if not self.scales_with_accuracy:
            return self.R
        acc = control(u, "gnss_accuracy", "GnssMeasurement(accuracy_exponent=...)")[..., 0].to(self.R.dtype)
        factor = (acc / self.accuracy_reference) ** self.accuracy_exponent  # the position std's factor
        d = 2 if self.planar else 3
        ones = torch.ones_like(factor)[..., None].expand(*factor.shape, self.measurement_dim - d)
        f = torch.cat([factor[..., None].expand(*factor.shape, d), ones], -1)
        return self.R * f[..., :, None] * f[..., None, :]

    def _antenna(self, x: Tensor) -> Tensor:
        """``C_nb l - latency v`` in the position's components."""
        if self.planar:
            rot = planar_rotation(math.pi / 2 - x[..., 4])  # body yaw from east = 90 deg - azimuth
            vel = torch.cat([x[..., 2:4], torch.zeros_like(x[..., :1])], -1)
            return antenna_offset(self, rot, vel)[..., :2]  # type: ignore[index]
        q = x[..., 6:10]
        return antenna_offset(self, quaternion_to_rotation(q / q.norm(dim=-1, keepdim=True)), x[..., 3:6])  # type: ignore[return-value]

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        z = x[..., self._lin]
        if has_antenna(self):
            d = 2 if self.planar else 3
            z = torch.cat([z[..., :d] + self._antenna(x), z[..., d:]], -1)
        if not self.heading:
            return z
        if self.planar:
            psi = x[..., 4]
        else:
            w, qx, qy, qz = x[..., 6:10].unbind(-1)
            # forward axis in ENU: first column of C(q) (scale-free, so |q| != 1 is harmless)
            east = w * w + qx * qx - qy * qy - qz * qz
            north = 2 * (qx * qy + w * qz)
            psi = torch.atan2(east, north)
        return torch.cat([z, psi[..., None]], -1)

    def residual(self, z: Tensor, z_ref: Tensor) -> Tensor:
        r = z - z_ref
        if not self.heading:
            return r
        return torch.cat([r[..., :-1], wrap_angle(r[..., -1:])], -1)

    def matrix(self, u: Controls = None) -> Tensor | None:
        if (self.heading and not self.planar) or has_antenna(self):
            return None
        n = 8 if self.planar else 16
        rows = self._lin + ([4] if self.heading else [])
        return torch.eye(n, dtype=self.R.dtype, device=self.R.device)[rows]

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        h = self.matrix(u)
        return None if h is None else h.expand(*x.shape[:-1], *h.shape)


class GnssImuModel(StateSpaceModel):
    """p004's GNSS/IMU model: IMU-driven prediction, GNSS correction.

    Args:
        planar: use :class:`PlanarGnssImuDynamics` (8 states) instead of the 16-state
            :class:`GnssImuDynamics`.
        dt: sample interval (s).
        velocity, heading: extra GNSS observations (see :class:`GnssMeasurement`).
        R_structure: learnable structure of ``R``.
        accuracy_exponent: see :class:`GnssMeasurement` (``None``: constant ``R``).
        lever_arm, latency: optional learnable antenna lever arm and receiver time offset
            (see :class:`GnssMeasurement`).
        **settings: overrides of :data:`GNSS_IMU_PAPER` (noise levels).

    Learnable: the four IMU noise levels (``Q``) and ``R``.
    """

    def __init__(
        self,
        *,
        planar: bool = False,
        dt: float = GNSS_IMU_PAPER["dt"],
        velocity: bool = False,
        heading: bool = False,
        R_structure: str = "diagonal",  # noqa: N803
        accuracy_exponent: float | None = None,
        lever_arm: Sequence[float] | None = None,
        latency: float | None = None,
        dtype: torch.dtype | None = None,
        **settings: float,
    ) -> None:
        opts = {**GNSS_IMU_PAPER, **settings}
        noise = {k: opts[k] for k in ("sigma_accel", "sigma_gyro", "sigma_accel_bias_walk", "sigma_gyro_bias_walk", "sigma_position_step")}
        cls = PlanarGnssImuDynamics if planar else GnssImuDynamics
        measurement = GnssMeasurement(
            planar=planar,
            velocity=velocity,
            heading=heading,
            sigma_gnss=opts["sigma_gnss"],
            sigma_gnss_velocity=opts["sigma_gnss_velocity"],
            sigma_heading=opts["sigma_heading"],
            R_structure=R_structure,
            accuracy_exponent=accuracy_exponent,
            lever_arm=lever_arm,
            latency=latency,
            dtype=dtype,
        )
        super().__init__(cls(dt=dt, dtype=dtype, **noise), measurement)
        p = GNSS_IMU_PAPER
        if planar:
            layout, mean0 = PLANAR_LAYOUT, [0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0, 0.0]
            std = [p["sigma_gnss"]] * 2 + [0.1] * 2 + [p["sigma_heading"]] + [p["sigma_accel_bias"]] * 2 + [p["sigma_gyro_bias"]]
        else:
            layout, mean0 = SPATIAL_LAYOUT, [0.0] * 4 + [10.0, 0.0, 1.0] + [0.0] * 9
            std = [p["sigma_gnss"]] * 3 + [0.1] * 3 + [p["sigma_heading"] / 2] * 4
            std += [p["sigma_accel_bias"]] * 3 + [p["sigma_gyro_bias"]] * 3
        # the default belief: the start of p004's drive (north at 10 m/s) with the simulator's spreads
        describe(self, layout=layout, learn=["sigma_accel", "sigma_gyro", "R"], initial_mean=mean0, initial_var=[s * s for s in std])
