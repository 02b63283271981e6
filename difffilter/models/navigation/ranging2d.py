"""2-D ranging to fixed anchors with odometry (UWB, acoustic or radio beacons; the libRSF
``range2`` + ``odom2``/``odom2diff`` data sets, :mod:`difffilter.datasets.ranging`).

State ``x = [p_x, p_y, theta]`` (position, m; heading, rad).  The odometry of each step is a
control, the measurement is one range per anchor slot.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..._util import control
from ...constraints import Bounded, Positive
from ...params import register_constrained
from ...selection import parameter_owners
from ..base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from ..heteroscedastic import RobustGate
from ..layout import StateLayout, describe

__all__ = ["OdometryDynamics2D", "RangeMeasurement2D", "heading_jacobian", "make_ranging_model", "multilateration", "range_gate"]


# The state of OdometryDynamics2D: the position first, the heading last.
_LAYOUT = StateLayout(names=("x", "y", "theta"), units=("m", "m", "rad"), position=(0, 1), angles=(2,))


def _rot(theta: Tensor) -> tuple[Tensor, Tensor]:
    return torch.cos(theta), torch.sin(theta)


def heading_jacobian(x: Tensor, u: Controls, *, heading: int) -> Tensor:
    """``d f / d x`` ``[..., n, n]`` of odometry dead reckoning whose body-frame velocity (control
    ``odom``, forward and left first) is rotated by the heading ``x[..., heading]`` into the first
    two (x, y) components; every other component moves independently of the state."""
    odom, dt = control(u, "odom").to(x.dtype), control(u, "dt").to(x.dtype)[..., 0]
    c, s = _rot(x[..., heading])
    vx, vy = odom[..., 0], odom[..., 1]
    n = x.shape[-1]
    f = torch.eye(n, dtype=x.dtype, device=x.device).expand(*torch.broadcast_shapes(x.shape[:-1], dt.shape), n, n).clone()
    f[..., 0, heading] = (-s * vx - c * vy) * dt
    f[..., 1, heading] = (c * vx - s * vy) * dt
    return f


class OdometryDynamics2D(DynamicsModel):
    """Dead reckoning with body-frame odometry ``u = (v_x, v_y, w)`` over ``dt``:

    .. math::
        p_k = p_{k-1} + R(\\theta_{k-1}) [v_x, v_y]^T dt, \\qquad \\theta_k = \\theta_{k-1} + w\\, dt

    with ``Q = s G Sigma_u G^T + diag(q) dt``, ``G = d f / d u = blockdiag(R(theta) dt, dt)``,
    ``Sigma_u`` the odometry covariance of the step (control ``odom_cov``, the file's variances),
    ``s`` = ``odom_scale`` and ``q`` = ``process_psd`` ``[3]`` (m^2/s, m^2/s, rad^2/s).

    Controls: ``odom [..., 3]``, ``odom_cov [..., 3, 3]``, ``dt [..., 1]``.
    Learnable: ``odom_scale`` (``Positive(1e-6)``), ``process_psd`` (``Positive(1e-12)``).
    """

    state_dim = 3
    angular = (2,)

    def __init__(
        self, *, odom_scale: float = 1.0, process_psd: tuple[float, float, float] = (1e-4, 1e-4, 1e-6), dtype: torch.dtype = torch.float64
    ) -> None:
        super().__init__()
        if not float(odom_scale) > 0 or len(process_psd) != 3 or min(process_psd) <= 0:
            raise ValueError(f"odom_scale must be > 0 and process_psd three positive numbers, got {odom_scale}, {process_psd}")
        register_constrained(self, "odom_scale", torch.tensor(float(odom_scale), dtype=dtype), Positive(1e-6))
        register_constrained(self, "process_psd", torch.tensor([float(q) for q in process_psd], dtype=dtype), Positive(1e-12))

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        odom, dt = control(u, "odom").to(x.dtype), control(u, "dt").to(x.dtype)[..., 0]
        c, s = _rot(x[..., 2])
        vx, vy, w = odom[..., 0], odom[..., 1], odom[..., 2]
        return torch.stack([x[..., 0] + (c * vx - s * vy) * dt, x[..., 1] + (s * vx + c * vy) * dt, x[..., 2] + w * dt], -1)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return heading_jacobian(x, u, heading=2)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        cov, dt = control(u, "odom_cov").to(x.dtype), control(u, "dt").to(x.dtype)[..., 0]
        c, s = _rot(x[..., 2])
        z = torch.zeros_like(c * dt)
        g = torch.stack([torch.stack([c * dt, -s * dt, z], -1), torch.stack([s * dt, c * dt, z], -1), torch.stack([z, z, z + dt], -1)], -2)
        q = self.odom_scale * (g @ cov @ g.transpose(-1, -2)) + torch.diag_embed(self.process_psd * dt[..., None])
        return 0.5 * (q + q.transpose(-1, -2))


class RangeMeasurement2D(MeasurementModel):
    """Ranges to ``A`` anchor slots:

    .. math::
        z_j = \\lVert p - a_j \\rVert + b_j + v_j, \\qquad v_j \\sim N(0, \\sigma^2_j f_j), \\quad
        \\sigma^2_j = s_j\\, r_j

    with ``a_j`` the anchor positions (control ``anchors [..., A, 2]``), ``r_j`` the file's
    variances (control ``range_var [..., A]``), ``b_j`` the range bias (``bias="anchor"``: one per
    slot, ``"shared"``: one for all, ``None``: none) and ``s_j`` ``noise_scale`` (per slot or
    shared, as ``bias``; fixed at 1 with ``noise=None``).  ``f_j`` is the :class:`RobustGate`
    inflation of the residual of the observed range (control ``z_obs [..., A]``) against the prior
    prediction (``gate=None``: no gate).

    Learnable: ``range_bias`` (``Bounded(-max_bias, max_bias)``, m), ``noise_scale``
    (``Positive(1e-4)``), and ``gate.*`` of a smooth learnable gate.
    """

    def __init__(
        self,
        *,
        num_anchors: int,
        bias: str | None = "anchor",
        noise: str | None = "anchor",
        gate: RobustGate | None = None,
        max_bias: float = 10.0,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if int(num_anchors) < 1:
            raise ValueError(f"num_anchors must be >= 1, got {num_anchors}")
        for arg, val in (("bias", bias), ("noise", noise)):
            if val not in ("anchor", "shared", None):
                raise ValueError(f"{arg} must be 'anchor', 'shared' or None, got {val!r}")
        self.measurement_dim = int(num_anchors)
        self.bias_mode, self.noise_mode = bias, noise
        size = {"anchor": (int(num_anchors),), "shared": (1,)}
        if bias is not None:
            register_constrained(self, "range_bias", torch.zeros(size[bias], dtype=dtype), Bounded(-float(max_bias), float(max_bias)))
        if noise is not None:
            register_constrained(self, "noise_scale", torch.ones(size[noise], dtype=dtype), Positive(1e-4))
        self.gate = gate

    def _geometry(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor]:
        d = x[..., None, :2] - control(u, "anchors").to(x.dtype)
        return d, torch.sqrt((d * d).sum(-1) + 1e-12)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        _, r = self._geometry(x, u)
        return r + self.range_bias if self.bias_mode is not None else r

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        d, r = self._geometry(x, u)
        unit = d / r[..., None]
        return torch.cat([unit, torch.zeros_like(unit[..., :1])], -1)

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        var = control(u, "range_var").to(x.dtype)
        if self.noise_mode is not None:
            var = var * self.noise_scale
        r = torch.diag_embed(var.expand(*x.shape[:-1], self.measurement_dim) if var.dim() < x.dim() else var)
        if self.gate is None:
            return r
        return self.gate.inflate(r, control(u, "z_obs").to(x.dtype) - self(x, u))


def range_gate(gate: str | None, *, threshold: float, floor: float, softness: float, dtype: torch.dtype) -> RobustGate | None:
    """The range models' gate: ``"soft"`` a smooth reject gate whose threshold, floor and softness
    learn, ``"hard"`` a fixed reject gate at ``threshold``, ``None`` none (ValueError otherwise)."""
    if gate not in ("soft", "hard", None):
        raise ValueError(f"gate must be 'soft', 'hard' or None, got {gate!r}")
    if gate == "soft":
        return RobustGate(kind="reject", threshold=threshold, floor=floor, softness=softness, learnable=True, dtype=dtype)
    if gate == "hard":
        return RobustGate(kind="reject", threshold=threshold, floor=floor)
    return None


def make_ranging_model(
    *,
    num_anchors: int,
    bias: str | None = "anchor",
    noise: str | None = "anchor",
    gate: str | None = "soft",
    gate_threshold: float = 3.0,
    gate_floor: float = 0.5,
    gate_softness: float = 0.5,
    odom_scale: float = 1.0,
    process_psd: tuple[float, float, float] = (1e-4, 1e-4, 1e-6),
    dtype: torch.dtype = torch.float64,
) -> StateSpaceModel:
    """The odometry + range model: ``gate="soft"`` a smooth learnable reject gate (threshold,
    floor, softness learnable), ``"hard"`` a fixed chi-square gate at ``gate_threshold``, ``None``
    no gate.  The model carries ``defaults`` (:func:`~difffilter.models.layout.describe`): the
    state's layout ``[x, y, theta]`` (``defaults.layout.position`` = ``(0, 1)``) and every
    parameter as ``learn``."""
    robust = range_gate(gate, threshold=gate_threshold, floor=gate_floor, softness=gate_softness, dtype=dtype)
    dyn = OdometryDynamics2D(odom_scale=odom_scale, process_psd=process_psd, dtype=dtype)
    meas = RangeMeasurement2D(num_anchors=num_anchors, bias=bias, noise=noise, gate=robust, dtype=dtype)
    model = StateSpaceModel(dyn, meas)
    return describe(model, layout=_LAYOUT, learn=list(parameter_owners(model)), name="ranging2d")  # type: ignore[return-value]


def multilateration(ranges: Tensor, var: Tensor, mask: Tensor, anchors: Tensor, *, iterations: int = 15) -> Tensor:
    """Per-step weighted least-squares position ``[T, d]`` from ranges ``[T, A]`` to anchors
    ``[T, A, d]`` (``d`` = 2 or 3; Gauss-Newton from the anchors' centroid, weights ``1 / var``);
    NaN where fewer than ``d + 1`` ranges."""
    dim = anchors.shape[-1]
    w = mask.to(ranges.dtype) / var
    p = (anchors * mask[..., None]).sum(-2) / mask.sum(-1, keepdim=True).clamp(min=1)
    p = p + 1e-3  # off the centroid exactly, where a symmetric layout gives a zero gradient
    for _ in range(iterations):
        d = p[..., None, :] - anchors
        r = d.norm(dim=-1).clamp(min=1e-9)
        jac = d / r[..., None]
        res = torch.where(mask, ranges - r, torch.zeros_like(r))
        jtj = (jac[..., :, None] * jac[..., None, :] * w[..., None, None]).sum(-3) + 1e-9 * torch.eye(dim, dtype=ranges.dtype)
        jtr = (jac * (w * res)[..., None]).sum(-2)
        p = p + torch.linalg.solve(jtj, jtr)
    return torch.where((mask.sum(-1) >= dim + 1)[..., None], p, torch.full_like(p, math.nan))
