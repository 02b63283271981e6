"""GNSS pseudorange measurements and the receiver dynamics that go with them (p001, smartLoc).

Per-step inputs ``u`` (dict; every entry broadcasts against the state's leading dimensions):

* ``"sat_pos" [..., K, 3]``: satellite positions in the state's position frame (see
  :class:`PseudorangeMeasurement`); ``"sat_vel" [..., K, 3]`` for pseudorange rates.
* ``"glonass" [..., K]`` (0/1 or bool): satellites that carry the inter-system bias state.
* ``"pr_var" [..., K]`` (``"prr_var"`` for rates): per-satellite noise variances when the model
  takes its noise from the data.
* ``"dt" [..., 1]``: time step of the dynamics (s); ``"speed"``, ``"yaw_rate"`` ``[..., 1]`` for
  :class:`OdometryClockDynamics`.

Satellites missing in an epoch keep a slot of the fixed ``K``: give them any finite position
away from the receiver and mark them False in the filter's per-component mask ``[B, T, K]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..params import Positive, register_constrained, register_covariance, remove_constrained
from .base import Controls, DynamicsModel, MeasurementModel

__all__ = [
    "ConstantVelocityClock",
    "GnssStateLayout",
    "OdometryClockDynamics",
    "PseudorangeMeasurement",
    "clock_process_noise",
]

_EARTH_RATE = 7.2921151467e-5
_C = 299792458.0


@dataclass(frozen=True)
class GnssStateLayout:
    """Where the receiver quantities sit in a state vector of length ``state_dim``.

    ``velocity`` (3 indices) is needed only for pseudorange rates; ``isb`` only when GLONASS
    satellites carry an inter-system bias.  Clock terms are in range units (m, m/s).
    """

    state_dim: int
    position: tuple[int, int, int] = (0, 1, 2)
    velocity: tuple[int, int, int] | None = (3, 4, 5)
    clock_bias: int = 6
    clock_drift: int | None = 7
    isb: int | None = None

    @classmethod
    def constant_velocity(cls, *, isb: bool = False) -> GnssStateLayout:
        """``[p(3), v(3), clock bias, clock drift(, ISB)]`` (p001: ECEF position/velocity)."""
        return cls(state_dim=9 if isb else 8, isb=8 if isb else None)

    @classmethod
    def odometry(cls, *, isb: bool = True) -> GnssStateLayout:
        """``[E, N, U, yaw, clock bias, clock drift(, ISB)]`` (smartLoc with odometry)."""
        return cls(state_dim=7 if isb else 6, velocity=None, clock_bias=4, clock_drift=5, isb=6 if isb else None)


_LOG_REJECT = math.log(1e6)  # the reject gate's variance factor 1e6, as a logarithm
_MIN_GATE_SOFTNESS = 1e-3


def _get(u: Controls, key: str) -> Tensor:
    if not isinstance(u, dict) or key not in u:
        raise KeyError(f"this model needs u[{key!r}] (per-step inputs dict)")
    return u[key]


class PseudorangeMeasurement(MeasurementModel):
    """Pseudoranges (and optionally pseudorange rates) to ``K`` satellites (p001, smartLoc).

    .. math::
        \\rho_j = \\|s_j - p\\| + \\frac{\\omega_e}{c}(s_{x,j} p_y - s_{y,j} p_x) + b + g_j\\,\\beta
        \\qquad \\dot\\rho_j = e_j^T (v - \\dot s_j) + d, \\quad e_j = (p - s_j)/\\|p - s_j\\|

    with receiver position ``p``, clock bias ``b`` and drift ``d`` (m, m/s), inter-system bias
    ``beta`` for satellites flagged ``g_j = u["glonass"]``, and the Sagnac (Earth-rotation)
    term in ECEF coordinates (option ``sagnac``).  Output ``[rho_1..K(, rhodot_1..K)]``.

    Frames: with ``frame_origin=None`` positions are absolute ECEF.  With an ECEF
    ``frame_origin [3]`` they are relative to it, along ECEF axes (``frame="ecef"``) or local ENU
    axes (``frame="enu"``); ``u["sat_pos"]`` must be in the same frame.  ``reduced=True``
    predicts ``rho_j - ||s_j||`` (range from the frame origin removed; the data must be reduced
    the same way in float64), computed as ``(|p|^2 - 2 s.p) / (|s - p| + |s|)``: float32 then
    keeps millimetres instead of the ~2 m spacing of float32 numbers near 2e7 m.

    Noise: ``R = sigma^2 I`` registered with ``R_structure`` (default ``"scalar"``: one learnable
    level, since a slot is not tied to one satellite), or, with ``noise_from_data=True``,
    ``R = noise_scale * diag(u["pr_var"](, u["prr_var"]))`` with learnable ``noise_scale``.
    The Jacobian is analytic.
    """

    def __init__(
        self,
        *,
        num_satellites: int,
        layout: GnssStateLayout,
        sigma_range: float = 3.0,
        sigma_rate: float = 0.1,
        rates: bool = False,
        sagnac: bool = False,
        frame_origin: Tensor | None = None,
        frame: str = "ecef",
        reduced: bool = False,
        noise_from_data: bool = False,
        R_structure: str = "scalar",
        robust: str | None = None,
        gate: float = 3.0,
        gate_floor: float = 0.0,
        gate_softness: float | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if robust not in (None, "huber", "reject"):
            raise ValueError(f"robust must be None, 'huber' or 'reject', got {robust!r}")
        self.robust, self.gate, self.gate_floor = robust, float(gate), float(gate_floor)
        self.soft_gate = False
        if rates and layout.velocity is None:
            raise ValueError("pseudorange rates need a velocity in the state layout")
        if frame not in ("ecef", "enu"):
            raise ValueError(f"frame must be 'ecef' or 'enu', got {frame!r}")
        if sagnac and frame == "enu" and frame_origin is None:
            raise ValueError("the Sagnac term in an ENU frame needs frame_origin")
        self.num_satellites, self.layout = int(num_satellites), layout
        self.rates, self.sagnac, self.reduced, self.noise_from_data = rates, sagnac, reduced, noise_from_data
        self.measurement_dim = self.num_satellites * (2 if rates else 1)
        k = self.num_satellites
        rot = torch.eye(3, dtype=dtype)
        origin = torch.zeros(3, dtype=dtype)
        if frame_origin is not None:
            origin = frame_origin.detach().to(dtype).clone()
            if frame == "enu":
                from ..sim import geometry  # lazy: difffilter.sim imports the models

                llh = geometry.ecef_to_geodetic(origin.to(torch.float64))
                rot = geometry.enu_rotation(llh[0], llh[1]).to(dtype)
        self.register_buffer("frame_origin", origin)
        self.register_buffer("frame_rotation", rot)  # rows: frame axes in ECEF
        var = torch.full((k,), sigma_range**2, dtype=dtype)
        if rates:
            var = torch.cat([var, torch.full((k,), sigma_rate**2, dtype=dtype)])
        if noise_from_data:
            register_covariance(self, "R", torch.diag(var), "fixed")
            register_constrained(self, "noise_scale", torch.ones((), dtype=dtype), Positive(1e-6))
        else:
            register_covariance(self, "R", torch.diag(var), R_structure)
        self.set_gate_softness(gate_softness)

    def set_gate_softness(self, value: float | None) -> None:
        """Hard (``None`` or ``0``) or smooth (``value > 0``) reject gate, see :meth:`robust_inflation`.

        A smooth gate registers ``gate_softness`` (its temperature, in units of the normalised
        residual ``n``) as a constrained parameter (``0.001 + softplus(raw)``), which ``learn:``
        may select by name; the hard gate has no such parameter (the module is then exactly the
        one built without the option).
        """
        if value is None or float(value) == 0.0:
            if self.soft_gate:
                remove_constrained(self, "gate_softness")
            self.soft_gate = False
            return
        if self.robust != "reject":
            raise ValueError(f"gate_softness needs robust='reject', got robust={self.robust!r}")
        if not float(value) > _MIN_GATE_SOFTNESS:
            raise ValueError(f"gate_softness must be None, 0 or > {_MIN_GATE_SOFTNESS}, got {value!r}")
        dtype = self.frame_rotation.dtype
        register_constrained(self, "gate_softness", torch.tensor(float(value), dtype=dtype), Positive(_MIN_GATE_SOFTNESS))
        self.soft_gate = True

    # -- pieces -----------------------------------------------------------------------------
    def _geometry(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        s = _get(u, "sat_pos")
        p = x[..., list(self.layout.position)]
        diff = p[..., None, :] - s  # [..., K, 3]
        rng = torch.linalg.vector_norm(diff, dim=-1)
        return p, s, diff, rng

    def _isb_flags(self, u: Controls, like: Tensor) -> Tensor:
        return _get(u, "glonass").to(like.dtype)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        lay = self.layout
        p, s, diff, rng = self._geometry(x, u)
        if self.reduced:
            s_norm = torch.linalg.vector_norm(s, dim=-1)
            pp = (p * p).sum(-1, keepdim=True)
            rho = (pp - 2.0 * (s * p[..., None, :]).sum(-1)) / (rng + s_norm)
        else:
            rho = rng
        if self.sagnac:
            pe = self.frame_origin + p @ self.frame_rotation
            se = self.frame_origin + s @ self.frame_rotation
            rho = rho + (_EARTH_RATE / _C) * (se[..., 0] * pe[..., None, 1] - se[..., 1] * pe[..., None, 0])
        rho = rho + x[..., lay.clock_bias, None]
        if lay.isb is not None:
            rho = rho + self._isb_flags(u, x) * x[..., lay.isb, None]
        if not self.rates:
            return rho
        assert lay.velocity is not None
        v = x[..., list(lay.velocity)]
        e = diff / rng[..., None]
        rate = (e * (v[..., None, :] - _get(u, "sat_vel"))).sum(-1)
        if lay.clock_drift is not None:
            rate = rate + x[..., lay.clock_drift, None]
        return torch.cat([rho, rate], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        lay = self.layout
        p, s, diff, rng = self._geometry(x, u)
        e = diff / rng[..., None]  # d|p - s|/dp
        k = self.num_satellites
        batch = e.shape[:-2]
        jac = x.new_zeros(*batch, self.measurement_dim, x.shape[-1])
        dpos = e
        if self.sagnac:
            se = self.frame_origin + s @ self.frame_rotation
            g = (_EARTH_RATE / _C) * torch.stack([-se[..., 1], se[..., 0], torch.zeros_like(se[..., 0])], -1)
            dpos = dpos + g @ self.frame_rotation.mT
        jac[..., :k, list(lay.position)] = dpos
        jac[..., :k, lay.clock_bias] = 1.0
        if lay.isb is not None:
            jac[..., :k, lay.isb] = self._isb_flags(u, x).expand(*batch, k)
        if self.rates:
            assert lay.velocity is not None
            v = x[..., list(lay.velocity)]
            w = v[..., None, :] - _get(u, "sat_vel")
            # d(e.w)/dp = (I - e e^T) w / r
            jac[..., k:, list(lay.position)] = (w - e * (e * w).sum(-1, keepdim=True)) / rng[..., None]
            jac[..., k:, list(lay.velocity)] = e
            if lay.clock_drift is not None:
                jac[..., k:, lay.clock_drift] = 1.0
        return jac

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        if not self.noise_from_data:
            r = self.R
        else:
            var = _get(u, "pr_var")
            if self.rates:
                var = torch.cat([var, _get(u, "prr_var")], -1)
            r = self.noise_scale * torch.diag_embed(var.to(x.dtype))
        if self.robust is None:
            return r
        return self.robust_inflation(x, u, r)

    def robust_inflation(self, x: Tensor, u: Controls, r: Tensor) -> Tensor:
        """Outlier gate by noise inflation (option ``robust``): ``R_ii <- f_i R_ii``.

        ``n_i = |z_i - h_i(x)| / sqrt(R_ii + gate_floor^2)`` with the observed pseudoranges
        ``u["pr_obs"] [..., K]`` and ``x`` the prior mean the filter passes in; ``"huber"``:
        ``f = max(1, n / gate)`` (the Huber M-estimator's weight ``gate / n`` as a variance
        factor), ``"reject"``: ``f = 1e6`` when ``n > gate`` (a chi-square gate with one degree
        of freedom that keeps shapes fixed).  ``gate_floor`` (m) allows for the prior position
        uncertainty, which ``R`` alone ignores.

        With ``gate_softness = t > 0`` (``"reject"`` only) the step is smoothed:
        ``f = 1e6 ** sigmoid((n - gate) / t)``, which tends to the hard gate as ``t -> 0`` and is
        differentiable in ``n``, so path-wise gradients (e.g. of a position loss) also see a range
        moving across the gate (with the step they see only the smooth pieces between switches).
        """
        k = self.num_satellites
        z = _get(u, "pr_obs").to(x.dtype)
        res = z - self.forward(x, u)[..., :k]
        var = torch.diagonal(r, dim1=-2, dim2=-1)[..., :k]
        n = res.abs() / torch.sqrt(var + self.gate_floor**2)
        if self.robust == "huber":
            f = torch.clamp(n / self.gate, min=1.0)
        elif self.soft_gate:
            f = torch.exp(_LOG_REJECT * torch.sigmoid((n - self.gate) / self.gate_softness))  # 1e6 ** sigmoid(...)
        else:
            f = torch.where(n > self.gate, torch.full_like(n, 1e6), torch.ones_like(n))
        if self.rates:
            f = torch.cat([f, torch.ones_like(f)], -1)
        d = torch.sqrt(f)
        return r * d[..., :, None] * d[..., None, :]


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
        return _get(u, "speed")[..., 0].to(x.dtype), _get(u, "yaw_rate")[..., 0].to(x.dtype), _get(u, "dt")[..., 0].to(x.dtype)

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
