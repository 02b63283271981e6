"""GNSS pseudorange measurements (p001, p003's receiver, smartLoc); the receiver dynamics that go
with them are in :mod:`difffilter.models.navigation.clock`.

Per-step inputs ``u`` (dict; every entry broadcasts against the state's leading dimensions):

* ``"sat_pos" [..., K, 3]``: satellite positions in the state's position frame (see
  :class:`PseudorangeMeasurement`); ``"sat_vel" [..., K, 3]`` for pseudorange rates.
* ``"glonass" [..., K]`` (0/1 or bool): satellites that carry the inter-system bias state.
* ``"pr_var" [..., K]`` (``"prr_var"`` for rates): per-satellite noise variances when the model
  takes its noise from the data.
* ``"pr_obs" [..., K]``: the observed pseudoranges, for the robust outlier gate.

Satellites missing in an epoch keep a slot of the fixed ``K``: give them any finite position
away from the receiver and mark them False in the filter's per-component mask ``[B, T, K]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ... import geometry as geo
from ..._util import control
from ...params import Positive, register_constrained, register_covariance, remove_constrained
from ..base import Controls, MeasurementModel

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
                llh = geo.ecef_to_geodetic(origin.to(torch.float64))
                rot = geo.enu_rotation(llh[0], llh[1]).to(dtype)
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
            rho = rho + (geo.EARTH_RATE / geo.SPEED_OF_LIGHT) * (se[..., 0] * pe[..., None, 1] - se[..., 1] * pe[..., None, 0])
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
            g = (geo.EARTH_RATE / geo.SPEED_OF_LIGHT) * torch.stack([-se[..., 1], se[..., 0], torch.zeros_like(se[..., 0])], -1)
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
