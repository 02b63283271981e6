"""GPS/SINS ultra-tight error-state model (paper p003): 18 SINS error states + 2 clock states.

State ``x [..., 20]``::

    0-2   dL, dlambda, dh      position error (rad, rad, m) of the INS w.r.t. the truth
    3-5   dv_E, dv_N, dv_U     velocity error (m/s), local-level ENU
    6-8   phi_E, phi_N, phi_U  platform misalignment (phi-angle, rad): C_b^p = (I - [phi x]) C_b^n
    9-11  eps_b                gyro constant drift (rad/s, body frame)
    12-14 eps_r                gyro first-order Markov drift (rad/s, body frame)
    15-17 nabla                accelerometer bias, first-order Markov (m/s^2, body frame)
    18-19 dt_u, dt_ru          receiver clock bias (m) and drift (m/s)

Errors are "INS minus truth".  With ``position_in_metres=True`` states 0-1 become
``(R_M + h) dL`` and ``(R_N + h) cos L dlambda`` (north, east metres), which keeps float32
covariances well conditioned.  The metre scale ``S`` is evaluated at the INS-indicated position,
which moves, so the metre-state error equation carries the rate term ``S' S^-1`` besides
``S F S^-1`` (see :meth:`SinsErrorDynamics.continuous_matrix`).

Per-step inputs ``u`` (dict, entries broadcast against ``x``): ``"llh" [..., 3]`` INS-indicated
latitude/longitude (rad) and height (m), ``"vel" [..., 3]`` INS ENU velocity, ``"f_n" [..., 3]``
INS specific force in the navigation frame (mean over the step), ``"C_bn" [..., 3, 3]`` INS
body-to-ENU attitude matrix, ``"dt" [..., 1]`` (or a fixed ``dt``), and for the measurements
``"sat_pos"``/``"sat_vel" [..., K, 3]`` ECEF satellite positions/velocities.  Optional
``"feedback" [..., 20]``: the error estimate fed back into the INS at the previous epoch (closed-loop
integration); the error then restarts from ``x - feedback``, i.e. ``x_k = Phi_k (x_{k-1} - c_{k-1})``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from difffilter import geometry as geo
from difffilter._util import control
from difffilter.models.base import Controls, DynamicsModel
from difffilter.params import register_covariance

__all__ = [
    "DEG_PER_HOUR",
    "MILLI_G",
    "SinsErrorDynamics",
    "sins_error_matrix",
    "sins_noise_psd",
]

DEG_PER_HOUR = math.pi / 180.0 / 3600.0  # rad/s
MILLI_G = 9.80665e-3  # m/s^2


def _get(u: Controls, key: str) -> Tensor:
    return control(u, key, "the SINS model")


def _skew(v: Tensor) -> Tensor:
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([torch.stack([z, -w, y], -1), torch.stack([w, z, -x], -1), torch.stack([-y, x, z], -1)], -2)


def _position_scale(llh: Tensor) -> Tensor:
    """``[..., 3]`` metres per unit of (dL, dlambda, dh)."""
    rm, rn = geo.radii_of_curvature(llh[..., 0])
    h = llh[..., 2]
    return torch.stack([rm + h, (rn + h) * torch.cos(llh[..., 0]), torch.ones_like(h)], -1)


def _position_scale_rate(llh: Tensor, vel: Tensor) -> Tensor:
    """``[..., 3]`` logarithmic rate ``d ln s_i / dt`` of :func:`_position_scale` along a trajectory
    at ``llh`` moving with ENU velocity ``vel``: with ``L' = v_N / (R_M + h)``, ``h' = v_U``,
    ``dR_N/dL = R_N e^2 sin L cos L / q``, ``dR_M/dL = 3 R_M e^2 sin L cos L / q``
    (``q = 1 - e^2 sin^2 L``):
    ``[(R_M' + h') / (R_M + h), (R_N' + h') / (R_N + h) - tan L L', 0]``."""
    lat, h = llh[..., 0], llh[..., 2]
    rm, rn = geo.radii_of_curvature(lat)
    sl, cl = torch.sin(lat), torch.cos(lat)
    k = geo.WGS84_E2 * sl * cl / (1.0 - geo.WGS84_E2 * sl * sl)
    vn, vu = vel[..., 1], vel[..., 2]
    ldot = vn / (rm + h)
    north = (3.0 * rm * k * ldot + vu) / (rm + h)
    east = (rn * k * ldot + vu) / (rn + h) - sl / cl * ldot
    return torch.stack([north, east, torch.zeros_like(north)], -1)


def sins_error_matrix(
    llh: Tensor, vel: Tensor, f_n: Tensor, C_bn: Tensor, *, gyro_markov_time: float, accel_markov_time: float, clock_time: float
) -> Tensor:
    """Continuous-time ``F [..., 20, 20]`` of the phi-angle ENU error model (``x' = F x + w``).

    With ``R_m = R_M + h``, ``R_n = R_N + h``, Earth rate ``w_ie = [0, W cos L, W sin L]``,
    transport rate ``w_en = [-v_N/R_m, v_E/R_n, v_E tan L/R_n]``, ``w_in = w_ie + w_en``:

    * ``dL' = dv_N/R_m - v_N dh/R_m^2``;
      ``dlambda' = dv_E/(R_n cos L) + v_E tan L dL/(R_n cos L) - v_E dh/(R_n^2 cos L)``; ``dh' = dv_U``.
    * ``dv' = f^n x phi - (2 w_ie + w_en) x dv - (2 dw_ie + dw_en) x v + C_b^n nabla + dg``, with
      ``dw_ie = [0, -W sin L dL, W cos L dL]``,
      ``dw_en = [-dv_N/R_m + v_N dh/R_m^2, dv_E/R_n - v_E dh/R_n^2,
      tan L dv_E/R_n + v_E sec^2 L dL/R_n - v_E tan L dh/R_n^2]`` and the normal-gravity error
      ``dg_U = -(dg/dL) dL - (dg/dh) dh``.
    * ``phi' = -w_in x phi + dw_ie + dw_en - C_b^n (eps_b + eps_r)``.
    * ``eps_b' = 0``, ``eps_r' = -eps_r/T_g``, ``nabla' = -nabla/T_a``,
      ``dt_u' = dt_ru``, ``dt_ru' = -dt_ru/tau_clk`` (p003's clock model, **[fix]** of the paper).
    """
    lat, h = llh[..., 0], llh[..., 2]
    rm, rn = geo.radii_of_curvature(lat)
    rm, rn = rm + h, rn + h
    sl, cl = torch.sin(lat), torch.cos(lat)
    tl = sl / cl
    ve, vn = vel[..., 0], vel[..., 1]
    batch = torch.broadcast_shapes(lat.shape, vel.shape[:-1], f_n.shape[:-1], C_bn.shape[:-2])
    F = lat.new_zeros(*batch, 20, 20)
    F[..., 0, 4] = 1.0 / rm
    F[..., 0, 2] = -vn / rm**2
    F[..., 1, 3] = 1.0 / (rn * cl)
    F[..., 1, 0] = ve * tl / (rn * cl)
    F[..., 1, 2] = -ve / (rn**2 * cl)
    F[..., 2, 5] = 1.0
    # d(w_ie), d(w_en) as [..., 3, 20] maps of the state
    d_ie = lat.new_zeros(*batch, 3, 20)
    d_ie[..., 1, 0] = -geo.EARTH_RATE * sl
    d_ie[..., 2, 0] = geo.EARTH_RATE * cl
    d_en = lat.new_zeros(*batch, 3, 20)
    d_en[..., 0, 4] = -1.0 / rm
    d_en[..., 0, 2] = vn / rm**2
    d_en[..., 1, 3] = 1.0 / rn
    d_en[..., 1, 2] = -ve / rn**2
    d_en[..., 2, 3] = tl / rn
    d_en[..., 2, 0] = ve / (rn * cl * cl)
    d_en[..., 2, 2] = -ve * tl / rn**2
    zero = torch.zeros_like(sl)
    w_ie = torch.stack([zero, geo.EARTH_RATE * cl, geo.EARTH_RATE * sl], -1)
    w_en = torch.stack([-vn / rm, ve / rn, ve * tl / rn], -1)
    cbn = C_bn.expand(*batch, 3, 3)
    vel_rows = _skew(vel).expand(*batch, 3, 3) @ (2.0 * d_ie + d_en)
    vel_rows[..., :, 6:9] += _skew(f_n)
    vel_rows[..., :, 3:6] -= _skew(2.0 * w_ie + w_en)
    vel_rows[..., :, 15:18] += cbn
    s2 = sl * sl
    dg_dl = 9.7803267714 * (5.27094e-3 + 2.0 * 2.32718e-5 * s2) * 2.0 * sl * cl
    vel_rows[..., 2, 0] -= dg_dl
    vel_rows[..., 2, 2] += 3.086e-6
    F[..., 3:6, :] = vel_rows
    att_rows = d_ie + d_en
    att_rows[..., :, 6:9] -= _skew(w_ie + w_en)
    att_rows[..., :, 9:12] -= cbn
    att_rows[..., :, 12:15] -= cbn
    F[..., 6:9, :] = att_rows
    idx = torch.arange(3)
    F[..., 12 + idx, 12 + idx] = -1.0 / gyro_markov_time
    F[..., 15 + idx, 15 + idx] = -1.0 / accel_markov_time
    F[..., 18, 19] = 1.0
    F[..., 19, 19] = -1.0 / clock_time
    return F


def sins_noise_psd(
    *,
    gyro_white: float = 0.01 * DEG_PER_HOUR,
    gyro_markov: float = 0.1 * DEG_PER_HOUR,
    gyro_markov_time: float = 3600.0,
    accel_white: float = 0.1 * MILLI_G,
    accel_markov: float = 0.1 * MILLI_G,
    accel_markov_time: float = 3600.0,
    clock_bias_psd: float = 0.01,
    clock_drift_psd: float = 0.04,
    position_in_metres: bool = False,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Diagonal continuous-time PSD ``[20]`` of ``w`` (p003's sensor specification).

    White noises are given as the standard deviation of 1 Hz samples, so their PSD is
    ``sigma^2 * 1 s``; Markov drivers have PSD ``2 sigma^2 / T`` (``sigma`` = steady-state std).
    Clock PSDs: a TCXO (``h_0 = 2e-19``, ``h_-2 = 2e-20`` give ``c^2 h_0 / 2 = 0.009 m^2/s`` and
    ``2 pi^2 c^2 h_-2 = 0.035 m^2/s^3``).  Position and constant-drift entries get tiny floors
    (1e-6 m^2/s, (1e-4 deg/h)^2/s) so ``"diagonal"`` structures stay positive definite.
    """
    pos = torch.tensor([1e-6, 1e-6, 1e-6], dtype=dtype)
    if not position_in_metres:
        pos[:2] = pos[:2] / 6.371e6**2
    vals = torch.cat(
        [
            pos,
            torch.full((3,), accel_white**2, dtype=dtype),
            torch.full((3,), gyro_white**2, dtype=dtype),
            torch.full((3,), (1e-4 * DEG_PER_HOUR) ** 2, dtype=dtype),
            torch.full((3,), 2.0 * gyro_markov**2 / gyro_markov_time, dtype=dtype),
            torch.full((3,), 2.0 * accel_markov**2 / accel_markov_time, dtype=dtype),
            torch.tensor([clock_bias_psd, clock_drift_psd], dtype=dtype),
        ]
    )
    return vals


class SinsErrorDynamics(DynamicsModel):
    """Discretised 20-state SINS/GPS error dynamics (p003), linear: ``x_k = Phi_k x_{k-1} + w``.

    ``Phi = expm(F dt)`` (``discretization="expm"``, :func:`torch.linalg.matrix_exp`) or its first-
    or second-order series ``I + F dt (+ (F dt)^2 / 2)``, with ``F`` from :func:`sins_error_matrix`
    evaluated at the INS-indicated navigation solution in ``u``.  Process noise by the trapezoidal
    rule ``Q_d = (Phi Q Phi^T + Q) dt / 2``.  :meth:`discrete_system` returns ``(Phi, Q_d)`` and
    :meth:`linear_prediction` ``(Phi x, Phi, Q_d)`` from one construction of ``F`` (what
    :class:`~difffilter.filters.SimplifiedUKF` uses).  ``Phi`` depends on the inputs only, so
    :meth:`precompute_controls` (called by every filter's ``forward``) builds it for the whole
    ``[B, T]`` run in one batched call, shared by the IMM modes of one configuration; the steps
    read it from ``u`` (a step without it builds its own).

    Learnable: ``Q``, the **continuous-time** PSD matrix ``[20, 20]`` (default structure
    ``"scalar"``: one positive scale on :func:`sins_noise_psd`, the per-mode scale of p003's IMM).
    """

    def __init__(
        self,
        *,
        dt: float | None = None,
        Q: Tensor | None = None,
        Q_structure: str = "scalar",
        gyro_markov_time: float = 3600.0,
        accel_markov_time: float = 3600.0,
        clock_time: float = 3600.0,
        discretization: str = "expm",
        position_in_metres: bool = False,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if discretization not in ("expm", "first", "second"):
            raise ValueError(f"discretization must be 'expm', 'first' or 'second', got {discretization!r}")
        self.state_dim = 20
        self.dt, self.discretization, self.position_in_metres = dt, discretization, position_in_metres
        self.gyro_markov_time, self.accel_markov_time, self.clock_time = gyro_markov_time, accel_markov_time, clock_time
        if Q is None:
            Q = torch.diag(
                sins_noise_psd(
                    gyro_markov_time=gyro_markov_time,
                    accel_markov_time=accel_markov_time,
                    position_in_metres=position_in_metres,
                    dtype=dtype,
                )
            )
        register_covariance(self, "Q", Q, Q_structure)

    def _dt(self, u: Controls, like: Tensor) -> Tensor:
        if isinstance(u, dict) and "dt" in u:
            return u["dt"][..., 0].to(like.dtype)
        if self.dt is None:
            raise KeyError("SinsErrorDynamics needs u['dt'] or a fixed dt")
        return torch.full((), self.dt, dtype=like.dtype, device=like.device)

    def continuous_matrix(self, u: Controls) -> Tensor:
        """``F [..., 20, 20]`` in this model's state units.

        In metres (``x = S y``, ``S = diag(s_N, s_E, 1, 1, ...)`` of the INS-indicated position,
        ``y`` the radian state): ``x' = (S F S^-1 + S' S^-1) x``.  The rate term
        (:func:`_position_scale_rate`, e.g. ``-tan L v_N / (R_M + h)`` on the east position) is
        first order in the position error; dropping it leaves a per-step model error that grows
        with the free-inertial drift (open-loop p003 flight, 1800 s: 0.074 m rms per 1 s step
        on east without it, 0.012 m with it, the rest being second-order error products).
        """
        llh, vel = _get(u, "llh"), _get(u, "vel")
        F = sins_error_matrix(
            llh, vel, _get(u, "f_n"), _get(u, "C_bn"),
            gyro_markov_time=self.gyro_markov_time, accel_markov_time=self.accel_markov_time, clock_time=self.clock_time,
        )  # fmt: skip
        if self.position_in_metres:
            s = torch.ones_like(F[..., 0])
            s[..., :3] = _position_scale(llh).expand(*F.shape[:-2], 3)
            F = s[..., :, None] * F / s[..., None, :]
            rate = _position_scale_rate(llh, vel).expand(*F.shape[:-2], 3)
            idx = torch.arange(3, device=F.device)
            F[..., idx, idx] = F[..., idx, idx] + rate
        return F

    @property
    def transition_key(self) -> str:
        """Name of the ``Phi`` entry that :meth:`precompute_controls` adds: it spells out every
        setting ``Phi`` depends on besides the inputs, so models that would compute different
        matrices never share one (two IMM modes of one configuration do)."""
        unit = "m" if self.position_in_metres else "rad"
        times = f"{self.gyro_markov_time!r},{self.accel_markov_time!r},{self.clock_time!r}"
        return f"sins.Phi[{self.discretization},{unit},{times},dt={self.dt!r}]"

    def precompute_controls(self, controls: Controls) -> Controls:
        """Add ``Phi [B, T, 20, 20]`` (:meth:`matrix` of every step, one batched call) under
        :attr:`transition_key`.  ``Phi`` depends on the INS inputs only, not on the state or on
        ``Q``, so the per-step matrix exponentials of a run (and of every IMM mode of this
        configuration) become one.  Inputs without the SINS entries (or not a dict) are returned
        unchanged (the per-step path then reports what is missing)."""
        if not isinstance(controls, Mapping) or not all(k in controls for k in ("llh", "vel", "f_n", "C_bn")):
            return controls
        key = self.transition_key
        if key in controls:
            phi = controls[key]
            lead = controls["llh"].shape[:-1]
            if not isinstance(phi, Tensor) or tuple(phi.shape) != (*lead, 20, 20):
                shape = tuple(phi.shape) if isinstance(phi, Tensor) else type(phi).__name__
                raise ValueError(f"controls[{key!r}] must be a tensor [B, T, 20, 20] = [{', '.join(map(str, lead))}, 20, 20], got {shape}")
            return controls
        if "dt" not in controls and self.dt is None:
            return controls
        return {**controls, key: self._transition(controls)}

    def matrix(self, u: Controls = None) -> Tensor:
        if isinstance(u, Mapping):
            phi = u.get(self.transition_key)
            if phi is not None:
                return phi
        return self._transition(u)

    def _transition(self, u: Controls) -> Tensor:
        """``Phi = expm(F dt)`` (or its series) of the inputs ``u [..., ...]``."""
        F = self.continuous_matrix(u)
        a = F * self._dt(u, F)[..., None, None]
        if self.discretization == "expm":
            return torch.linalg.matrix_exp(a)
        eye = torch.eye(20, dtype=F.dtype, device=F.device)
        return eye + a if self.discretization == "first" else eye + a + 0.5 * a @ a

    @staticmethod
    def _fed_back(x: Tensor, u: Controls) -> Tensor:
        """The error after the previous epoch's feedback correction ``u["feedback"]`` (if any)."""
        if isinstance(u, dict) and "feedback" in u:
            return x - u["feedback"].to(x.dtype)
        return x

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return (self.matrix(u) @ self._fed_back(x, u)[..., None])[..., 0]

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        phi = self.matrix(u)
        return phi.expand(*torch.broadcast_shapes(x.shape[:-1], phi.shape[:-2]), 20, 20)

    def _discrete_noise(self, phi: Tensor, u: Controls) -> Tensor:
        q = self.Q
        dt = self._dt(u, phi)[..., None, None]
        qd = 0.5 * (phi @ q @ phi.mT + q) * dt
        return 0.5 * (qd + qd.mT)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        return self._discrete_noise(self.matrix(u), u)

    def discrete_system(self, u: Controls = None) -> tuple[Tensor, Tensor]:
        """``(Phi, Q_d)`` from one construction of ``F`` (equal to ``(matrix(u), process_noise(x, u))``)."""
        phi = self.matrix(u)
        return phi, self._discrete_noise(phi, u)

    def linear_prediction(self, x: Tensor, u: Controls = None) -> tuple[Tensor, Tensor, Tensor]:
        """``(f(x, u), Phi, Q_d)`` from one construction of ``F``: the Kalman prediction's inputs."""
        phi, qd = self.discrete_system(u)
        return (phi @ self._fed_back(x, u)[..., None])[..., 0], phi, qd
