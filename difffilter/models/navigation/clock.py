"""Receiver dynamics with a two-state clock (p001's static receiver, the smartLoc car): positions in
the frame of :class:`~difffilter.models.navigation.pseudorange.PseudorangeMeasurement`, clock
bias and drift in range units.  Per-step inputs: ``"dt" [..., 1]`` (or a fixed ``dt``), and
``"speed"``, ``"yaw_rate"`` ``[..., 1]`` for :class:`OdometryClockDynamics`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..._util import control
from ...params import Positive, register_constrained
from ..base import Controls, DynamicsModel
from .pseudorange import GnssStateLayout

__all__ = ["ConstantVelocityClock", "OdometryClockDynamics", "clock_process_noise"]


def clock_process_noise(dt: Tensor, bias_psd: Tensor, drift_psd: Tensor) -> Tensor:
    """Discrete covariance ``[..., 2, 2]`` of the two-state clock ``b' = d + w_b, d' = w_d``:
    ``[[q_b dt + q_d dt^3/3, q_d dt^2/2], [q_d dt^2/2, q_d dt]]`` (PSDs in m^2/s and m^2/s^3)."""
    q11 = bias_psd * dt + drift_psd * dt**3 / 3.0
    q12 = drift_psd * dt**2 / 2.0
    q22 = drift_psd * dt
    return torch.stack([torch.stack([q11, q12], -1), torch.stack([q12, q22], -1)], -2)


def _dt(u: Controls, default: float | None, like: Tensor) -> Tensor:
    if isinstance(u, dict) and "dt" in u:
        return u["dt"][..., 0].to(like.dtype)
    if default is None:
        raise KeyError("this model needs u['dt'] [..., 1] or a fixed dt= at construction")
    return torch.full((), default, dtype=like.dtype, device=like.device)


class ConstantVelocityClock(DynamicsModel):
    """Constant-velocity receiver with a two-state clock (and an ISB random walk), p001.

    ``p_k = p_{k-1} + v_{k-1} dt``, ``v_k = v_{k-1}`` (white-noise acceleration with PSD
    ``accel_psd`` per axis, m^2/s^3), ``b_k = b_{k-1} + d_{k-1} dt``, ``d_k = d_{k-1}``
    (:func:`clock_process_noise`), ``beta_k = beta_{k-1}`` (PSD ``isb_psd``).  State layout
    :meth:`GnssStateLayout.constant_velocity`.  ``dt`` is fixed or read from ``u["dt"]``.

    Learnable (positive): ``accel_psd [3]``, ``clock_bias_psd``, ``clock_drift_psd``, ``isb_psd``.
    """

    def __init__(
        self,
        *,
        dt: float | None = None,
        accel_psd: float | Tensor = 1e-2,
        clock_bias_psd: float = 1e-2,
        clock_drift_psd: float = 1e-2,
        isb: bool = False,
        isb_psd: float = 1e-4,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.layout = GnssStateLayout.constant_velocity(isb=isb)
        self.state_dim = self.layout.state_dim
        self.dt = dt
        acc = torch.as_tensor(accel_psd, dtype=dtype).expand(3).clone()
        register_constrained(self, "accel_psd", acc, Positive(1e-12))
        register_constrained(self, "clock_bias_psd", torch.tensor(clock_bias_psd, dtype=dtype), Positive(1e-12))
        register_constrained(self, "clock_drift_psd", torch.tensor(clock_drift_psd, dtype=dtype), Positive(1e-12))
        if isb:
            register_constrained(self, "isb_psd", torch.tensor(isb_psd, dtype=dtype), Positive(1e-12))

    def matrix(self, u: Controls = None) -> Tensor:
        dt = _dt(u, self.dt, self.clock_bias_psd)
        n = self.state_dim
        eye = torch.eye(n, dtype=dt.dtype, device=dt.device)
        hot = torch.zeros(n, n, dtype=dt.dtype, device=dt.device)
        hot[0, 3] = hot[1, 4] = hot[2, 5] = hot[6, 7] = 1.0
        return eye + dt[..., None, None] * hot

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = _dt(u, self.dt, x)[..., None]
        pos = x[..., 0:3] + x[..., 3:6] * dt
        clk = x[..., 6:7] + x[..., 7:8] * dt
        return torch.cat([pos, x[..., 3:6], clk, x[..., 7:]], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        f = self.matrix(u)
        return f.expand(*torch.broadcast_shapes(x.shape[:-1], f.shape[:-2]), *f.shape[-2:])

    @property
    def Q(self) -> Tensor:  # noqa: N802 - field notation
        """Process noise for the fixed ``dt`` (requires ``dt`` at construction)."""
        return self.process_noise(self.accel_psd.new_zeros(self.state_dim), None)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = _dt(u, self.dt, x)
        q = self.accel_psd
        d3, d2, d1 = (dt**3 / 3.0)[..., None], (dt**2 / 2.0)[..., None], dt[..., None]
        pp, pv, vv = torch.diag_embed(d3 * q), torch.diag_embed(d2 * q), torch.diag_embed(d1 * q)
        top = torch.cat([pp, pv], -1)
        bottom = torch.cat([pv, vv], -1)
        kin = torch.cat([top, bottom], -2)
        clk = clock_process_noise(dt, self.clock_bias_psd, self.clock_drift_psd)
        n = self.state_dim
        out = kin.new_zeros(*kin.shape[:-2], n, n)
        out[..., :6, :6] = kin
        out[..., 6:8, 6:8] = clk
        if self.layout.isb is not None:
            out[..., 8, 8] = self.isb_psd * dt
        return out


class OdometryClockDynamics(DynamicsModel):
    """Planar odometry (speed + yaw rate) with height, clock and ISB states (smartLoc).

    State ``[E, N, U, yaw, b, d(, beta)]`` (:meth:`GnssStateLayout.odometry`), ``yaw`` measured
    from east, counter-clockwise (ENU), controls ``u["speed"]`` (m/s), ``u["yaw_rate"]`` (rad/s,
    positive = left turn) and ``u["dt"]``, all ``[..., 1]``:

    ``E += s dt cos(yaw + w dt/2)``, ``N += s dt sin(yaw + w dt/2)``, ``yaw += w dt``,
    ``b += d dt``.  Process noise: speed and yaw-rate noise (``speed_sigma``, ``yaw_rate_sigma``)
    mapped through ``df/du`` (state dependent), plus random walks with PSDs
    ``horizontal_psd`` (m^2/s, slip and lever-arm effects), ``vertical_psd``, ``yaw_psd``
    (rad^2/s, gyro bias), the clock PSDs and ``isb_psd``.  All of these are learnable.
    """

    def __init__(
        self,
        *,
        isb: bool = True,
        speed_sigma: float = 0.05,
        yaw_rate_sigma: float = 0.002,
        horizontal_psd: float = 0.5,
        vertical_psd: float = 0.5,
        yaw_psd: float = 1e-4,
        clock_bias_psd: float = 1.0,
        clock_drift_psd: float = 1.0,
        isb_psd: float = 1e-2,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.layout = GnssStateLayout.odometry(isb=isb)
        self.state_dim = self.layout.state_dim
        for name, val in [
            ("speed_sigma", speed_sigma),
            ("yaw_rate_sigma", yaw_rate_sigma),
            ("horizontal_psd", horizontal_psd),
            ("vertical_psd", vertical_psd),
            ("yaw_psd", yaw_psd),
            ("clock_bias_psd", clock_bias_psd),
            ("clock_drift_psd", clock_drift_psd),
            ("isb_psd", isb_psd),
        ]:
            register_constrained(self, name, torch.tensor(val, dtype=dtype), Positive(1e-12))

    def _controls(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor, Tensor]:
        return control(u, "speed")[..., 0].to(x.dtype), control(u, "yaw_rate")[..., 0].to(x.dtype), control(u, "dt")[..., 0].to(x.dtype)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        s, w, dt = self._controls(x, u)
        mid = x[..., 3] + 0.5 * w * dt
        e = x[..., 0] + s * dt * torch.cos(mid)
        n = x[..., 1] + s * dt * torch.sin(mid)
        yaw = x[..., 3] + w * dt
        b = x[..., 4] + x[..., 5] * dt
        e, n, yaw, b = torch.broadcast_tensors(e, n, yaw, b)
        rest = x[..., 5:].expand(*e.shape, x.shape[-1] - 5)
        return torch.cat([torch.stack([e, n, x[..., 2].expand_as(e), yaw, b], -1), rest], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        s, w, dt = self._controls(x, u)
        mid = x[..., 3] + 0.5 * w * dt
        de, dn = -s * dt * torch.sin(mid), s * dt * torch.cos(mid)
        de, dn, dtb = torch.broadcast_tensors(de, dn, dt * torch.ones_like(x[..., 0]))
        jac = torch.eye(self.state_dim, dtype=x.dtype, device=x.device).expand(*de.shape, self.state_dim, self.state_dim).clone()
        jac[..., 0, 3] = de
        jac[..., 1, 3] = dn
        jac[..., 4, 5] = dtb
        return jac

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        s, w, dt = self._controls(x, u)
        mid = x[..., 3] + 0.5 * w * dt
        c, sn = torch.cos(mid), torch.sin(mid)
        c, sn, s, dt = torch.broadcast_tensors(c, sn, s, dt)
        zero = torch.zeros_like(c)
        # columns of df/d(speed, yaw_rate) restricted to (E, N, yaw)
        g_v = torch.stack([dt * c, dt * sn, zero], -1) * self.speed_sigma
        g_w = torch.stack([-0.5 * s * dt * dt * sn, 0.5 * s * dt * dt * c, dt], -1) * self.yaw_rate_sigma
        kin = g_v[..., :, None] * g_v[..., None, :] + g_w[..., :, None] * g_w[..., None, :]
        kin = kin + torch.diag_embed(torch.stack([self.horizontal_psd * dt, self.horizontal_psd * dt, self.yaw_psd * dt], -1))
        n = self.state_dim
        out = x.new_zeros(*c.shape, n, n)
        idx = [0, 1, 3]
        out[..., [[i] for i in idx], idx] = kin
        out[..., 2, 2] = self.vertical_psd * dt
        out[..., 4:6, 4:6] = clock_process_noise(dt, self.clock_bias_psd, self.clock_drift_psd)
        if self.layout.isb is not None:
            out[..., 6, 6] = self.isb_psd * dt
        return out
