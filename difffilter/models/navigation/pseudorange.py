"""GNSS pseudorange measurements (p001, p003's receiver, smartLoc); the receiver dynamics that go
with them are in :mod:`difffilter.models.navigation.clock`.

Per-step inputs ``u`` (dict; every entry broadcasts against the state's leading dimensions):

* ``"sat_pos" [..., K, 3]``: satellite positions in the state's position frame (see
  :class:`PseudorangeMeasurement`); ``"sat_vel" [..., K, 3]`` for pseudorange rates.
* ``"glonass" [..., K]`` (0/1 or bool): satellites that carry the inter-system bias state.
* ``"pr_var" [..., K]`` (``"prr_var"`` for rates): per-satellite noise variances when the model
  takes its noise from the data.
* ``"pr_obs" [..., K]``: the observed pseudoranges, for the robust outlier gate.
* ``"elevation" [..., K]`` (deg) and ``"constellation" [..., K]`` (group index): for the
  elevation-dependent bias (option ``elevation_bias``).

Satellites missing in an epoch keep a slot of the fixed ``K``: give them any finite position
away from the receiver and mark them False in the filter's per-component mask ``[B, T, K]``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ... import geometry as geo
from ..._util import control
from ...params import Bounded, Positive, register_constrained, register_covariance
from ..base import Controls, MeasurementModel
from ..heteroscedastic import RobustGate
from .antenna import antenna_offset, has_antenna, planar_rotation, register_antenna

__all__ = ["GnssStateLayout", "PseudorangeMeasurement"]


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
    yaw: int | None = None

    @classmethod
    def constant_velocity(cls, *, isb: bool = False) -> GnssStateLayout:
        """``[p(3), v(3), clock bias, clock drift(, ISB)]`` (p001: ECEF position/velocity)."""
        return cls(state_dim=9 if isb else 8, isb=8 if isb else None)

    @classmethod
    def odometry(cls, *, isb: bool = True) -> GnssStateLayout:
        """``[E, N, U, yaw, clock bias, clock drift(, ISB)]`` (smartLoc with odometry)."""
        return cls(state_dim=7 if isb else 6, velocity=None, clock_bias=4, clock_drift=5, isb=6 if isb else None, yaw=3)


def _get(u: Controls, key: str) -> Tensor:
    return control(u, key)


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
    axes (``frame="enu"``); ``u["sat_pos"]`` must be in the same frame.  Per-step inputs
    ``u["frame_origin"] [..., 3]`` and ``u["frame_rotation"] [..., 3, 3]`` (rows: frame axes in
    ECEF) override them per trajectory (one batch holding drives with different local frames).  ``reduced=True``
    predicts ``rho_j - ||s_j||`` (range from the frame origin removed; the data must be reduced
    the same way in float64), computed as ``(|p|^2 - 2 s.p) / (|s - p| + |s|)``: float32 then
    keeps millimetres instead of the ~2 m spacing of float32 numbers near 2e7 m.

    Antenna (:mod:`~difffilter.models.navigation.antenna`, odometry layouts in an ENU frame):
    ``lever_arm`` (body forward, left, up; m) and ``latency`` (receiver time offset, s) move the
    measured position to ``p + C(yaw) l - latency v``, ``v`` the odometry velocity
    (``u["speed"]`` along the yaw); both are learnable by name when given.

    Bias: ``elevation_bias`` ``[G]`` (m, one per constellation group ``u["constellation"]``)
    adds ``c_g / sin(max(el, 5 deg))`` to each pseudorange (a residual tropospheric or multipath
    bias that grows at low elevation), learnable by name, :class:`~difffilter.params.Bounded` to
    ``+-max_elevation_bias``.  A constant per-constellation bias is not a parameter: the clock
    bias and inter-system bias states absorb it.

    Noise: ``R = sigma^2 I`` registered with ``R_structure`` (default ``"scalar"``: one learnable
    level, since a slot is not tied to one satellite), or, with ``noise_from_data=True``,
    ``R = noise_scale * diag(u["pr_var"](, u["prr_var"]))`` with learnable ``noise_scale``, or,
    with ``noise_model`` (a variance module of :mod:`difffilter.models.heteroscedastic`, e.g.
    ``ElevationVariance(groups=2)`` reading ``u["elevation"]``, ``u["constellation"]``),
    ``R = diag(noise_model(u))`` (pseudoranges only).  ``robust`` adds the outlier gate
    :attr:`robust_gate` (a :class:`~difffilter.models.heteroscedastic.RobustGate`, see
    :meth:`robust_inflation`).  The Jacobian is analytic.
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
        gate_learnable: bool = False,
        noise_model: nn.Module | None = None,
        lever_arm: Sequence[float] | None = None,
        latency: float | None = None,
        elevation_bias: Sequence[float] | None = None,
        max_elevation_bias: float = 10.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if robust not in (None, "huber", "reject"):
            raise ValueError(f"robust must be None, 'huber' or 'reject', got {robust!r}")
        if noise_model is not None and (rates or noise_from_data):
            raise ValueError("noise_model gives the pseudorange variances: it excludes rates=True and noise_from_data=True")
        self.robust = robust
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
                llh = geo.ecef_to_geodetic(origin.to(torch.float64))
                rot = geo.enu_rotation(llh[0], llh[1]).to(dtype)
        self.register_buffer("frame_origin", origin)
        self.register_buffer("frame_rotation", rot)  # rows: frame axes in ECEF
        var = torch.full((k,), sigma_range**2, dtype=dtype)
        if rates:
            var = torch.cat([var, torch.full((k,), sigma_rate**2, dtype=dtype)])
        self.noise_model = noise_model
        if noise_from_data:
            register_covariance(self, "R", torch.diag(var), "fixed")
            register_constrained(self, "noise_scale", torch.ones((), dtype=dtype), Positive(1e-6))
        else:
            register_covariance(self, "R", torch.diag(var), "fixed" if noise_model is not None else R_structure)
        if (lever_arm is not None or latency is not None) and (frame != "enu" or layout.yaw is None):
            raise ValueError("lever_arm and latency need an ENU frame and a yaw state (GnssStateLayout.odometry)")
        if latency is not None and rates:
            raise ValueError("latency is not modelled for pseudorange rates")
        register_antenna(self, lever_arm=lever_arm, latency=latency, dtype=dtype)
        self.has_elevation_bias = elevation_bias is not None
        if elevation_bias is not None:
            eb = torch.as_tensor(elevation_bias, dtype=dtype).reshape(-1)
            if eb.numel() == 0 or not bool((eb.abs() < float(max_elevation_bias)).all()):
                raise ValueError(
                    f"elevation_bias must be one number per constellation group (m) inside +-{max_elevation_bias}, got {eb.tolist()}"
                )
            register_constrained(self, "elevation_bias", eb, Bounded(-float(max_elevation_bias), float(max_elevation_bias)))
        self.robust_gate = None if robust is None else RobustGate(kind=robust, threshold=gate, floor=gate_floor, dtype=dtype)
        self.set_gate_softness(gate_softness)
        if gate_learnable:
            self.set_gate_learnable(True)

    @property
    def soft_gate(self) -> bool:
        """Whether the reject gate is the smooth one."""
        return self.robust_gate is not None and self.robust_gate.soft

    @property
    def gate_softness(self) -> Tensor:
        """The smooth gate's temperature (only when :attr:`soft_gate`)."""
        if not self.soft_gate:
            raise AttributeError("gate_softness exists only with the smooth gate (set_gate_softness(t > 0))")
        return self.robust_gate.gate_softness  # type: ignore[union-attr]

    def set_gate_softness(self, value: float | None) -> None:
        """Hard (``None`` or ``0``) or smooth (``value > 0``) reject gate, see :meth:`robust_inflation`.

        A smooth gate registers ``robust_gate.gate_softness`` (its temperature, in units of the
        normalised residual ``n``) as a constrained parameter (``0.001 + softplus(raw)``), which
        ``learn: [gate_softness]`` selects; the hard gate has no such parameter.
        """
        if value is None or float(value) == 0.0:
            if self.robust_gate is not None:
                self.robust_gate.set_softness(None)
            return
        if self.robust != "reject":
            raise ValueError(f"gate_softness needs robust='reject', got robust={self.robust!r}")
        self.robust_gate.set_softness(value, dtype=self.frame_rotation.dtype)  # type: ignore[union-attr]

    def set_gate_learnable(self, flag: bool) -> None:
        """Make the smooth gate's threshold and floor learnable (``gate_threshold``, ``gate_floor``)."""
        if self.robust_gate is None:
            raise ValueError("a learnable gate needs robust='reject'")
        self.robust_gate.set_learnable(flag)

    # -- pieces -----------------------------------------------------------------------------
    def _geometry(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        s = _get(u, "sat_pos")
        p = x[..., list(self.layout.position)]
        if has_antenna(self):
            rot, vel = self._attitude_velocity(x, u)
            p = p + antenna_offset(self, rot, vel)
        diff = p[..., None, :] - s  # [..., K, 3]
        rng = torch.linalg.vector_norm(diff, dim=-1)
        return p, s, diff, rng

    def _attitude_velocity(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor]:
        """Body attitude (rotation by the yaw state) and velocity (odometry speed along the yaw)."""
        yaw = x[..., self.layout.yaw]
        speed = _get(u, "speed")[..., 0].to(x.dtype) if "latency" in self.antenna_terms else torch.zeros_like(yaw)
        vel = torch.stack([speed * torch.cos(yaw), speed * torch.sin(yaw), torch.zeros_like(yaw * speed)], -1)
        return planar_rotation(yaw), vel

    def _antenna_yaw_derivative(self, x: Tensor, u: Controls) -> Tensor:
        """``d(antenna offset)/d yaw`` ``[..., 3]``."""
        yaw = x[..., self.layout.yaw]
        c, sn = torch.cos(yaw), torch.sin(yaw)
        out = torch.zeros(*yaw.shape, 3, dtype=x.dtype, device=x.device)
        if "lever_arm" in self.antenna_terms:
            arm = self.lever_arm.to(x.dtype)
            out = out + torch.stack([-sn * arm[0] - c * arm[1], c * arm[0] - sn * arm[1], torch.zeros_like(c)], -1)
        if "latency" in self.antenna_terms:
            speed = _get(u, "speed")[..., 0].to(x.dtype)
            out = out - self.latency.to(x.dtype) * torch.stack([-speed * sn, speed * c, torch.zeros_like(c * speed)], -1)
        return out

    def _frame(self, u: Controls, like: Tensor) -> tuple[Tensor, Tensor]:
        """Frame origin ``[..., 3]`` and rotation ``[..., 3, 3]``: per trajectory from
        ``u["frame_origin"]`` / ``u["frame_rotation"]`` when given (batches pooling drives with
        their own ENU frames), else the constructor's."""
        if isinstance(u, dict) and "frame_origin" in u:
            return u["frame_origin"].to(like.dtype), control(u, "frame_rotation").to(like.dtype)
        return self.frame_origin, self.frame_rotation

    def _isb_flags(self, u: Controls, like: Tensor) -> Tensor:
        return _get(u, "glonass").to(like.dtype)

    def _elevation_bias(self, u: Controls, like: Tensor) -> Tensor:
        """``c_g / sin(max(el, 5 deg))`` ``[..., K]``; the floor keeps empty slots (elevation 0) finite."""
        el = _get(u, "elevation").to(like.dtype).clamp_min(5.0) * (math.pi / 180.0)  # not deg2rad: the compiled engine lacks it
        group = _get(u, "constellation").long().clamp(0, self.elevation_bias.numel() - 1)
        return self.elevation_bias.to(like.dtype)[group] / torch.sin(el)

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
            origin, rot = self._frame(u, x)
            pe = origin + (p[..., None, :] @ rot)[..., 0, :]
            se = origin[..., None, :] + s @ rot
            rho = rho + (geo.EARTH_RATE / geo.SPEED_OF_LIGHT) * (se[..., 0] * pe[..., None, 1] - se[..., 1] * pe[..., None, 0])
        rho = rho + x[..., lay.clock_bias, None]
        if lay.isb is not None:
            rho = rho + self._isb_flags(u, x) * x[..., lay.isb, None]
        if self.has_elevation_bias:
            rho = rho + self._elevation_bias(u, x)
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
            origin, rot = self._frame(u, x)
            se = origin[..., None, :] + s @ rot
            g = (geo.EARTH_RATE / geo.SPEED_OF_LIGHT) * torch.stack([-se[..., 1], se[..., 0], torch.zeros_like(se[..., 0])], -1)
            dpos = dpos + g @ rot.mT
        jac[..., :k, list(lay.position)] = dpos
        if has_antenna(self):
            d_yaw = (dpos * self._antenna_yaw_derivative(x, u)[..., None, :]).sum(-1)
            jac[..., :k, lay.yaw] = jac[..., :k, lay.yaw] + d_yaw
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
        if self.noise_model is not None:
            r = torch.diag_embed(self.noise_model(u, x))
        elif not self.noise_from_data:
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
        """Outlier gate by noise inflation (option ``robust``): ``R_ii <- f_i R_ii`` by
        :attr:`robust_gate` (:meth:`~difffilter.models.heteroscedastic.RobustGate.inflate`).

        ``n_i = |z_i - h_i(x)| / sqrt(R_ii + gate_floor^2)`` with the observed pseudoranges
        ``u["pr_obs"] [..., K]`` and ``x`` the prior mean the filter passes in; ``"huber"``:
        ``f = max(1, n / gate)``, ``"reject"``: ``f = 1e6`` when ``n > gate``.  ``gate_floor`` (m)
        allows for the prior position uncertainty, which ``R`` alone ignores.  With
        ``gate_softness = t > 0`` (``"reject"`` only) the step is smoothed,
        ``f = 1e6 ** sigmoid((n - gate) / t)``, differentiable in ``n`` (so path-wise gradients
        also see a range moving across the gate) and, with ``gate_learnable``, in the threshold
        and floor.  Rate components are never inflated.
        """
        k = self.num_satellites
        z = _get(u, "pr_obs").to(x.dtype)
        res = z - self.forward(x, u)[..., :k]
        return self.robust_gate.inflate(r, res)  # type: ignore[union-attr]
