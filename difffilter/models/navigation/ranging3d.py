"""3-D ranging to fixed anchors (the libRSF ``range3`` data sets, :mod:`difffilter.datasets.ranging`):
with ``odom3`` odometry or without any.

* With odometry, state ``x = [p_x, p_y, p_z, psi]`` (m; heading about the vertical, rad):
  :class:`OdometryDynamics3D`, driven by the body-frame velocity and the yaw rate of the record.
* Without odometry, state ``x = [p_x, p_y, p_z, v_x, v_y, v_z]``: :class:`ConstantVelocity3D`
  (white-noise acceleration).

The measurement is :class:`~difffilter.models.navigation.ranging2d.RangeMeasurement2D`'s range
model on the first three state components (:class:`RangeMeasurement3D`: per anchor range bias,
noise scale on the file's variances, robust gate).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..._util import control
from ...constraints import Positive
from ...params import register_constrained
from ..base import Controls, DynamicsModel, StateSpaceModel
from .ranging2d import RangeMeasurement2D, heading_jacobian, range_gate

__all__ = ["ConstantVelocity3D", "OdometryDynamics3D", "RangeMeasurement3D", "make_ranging3d_model"]


class OdometryDynamics3D(DynamicsModel):
    """Dead reckoning with body-frame odometry ``u = (v_x, v_y, v_z, w_z)`` over ``dt``:

    .. math::
        p_k = p_{k-1} + \\mathrm{blockdiag}(R(\\psi_{k-1}), 1) [v_x, v_y, v_z]^T dt, \\qquad
        \\psi_k = \\psi_{k-1} + w_z\\, dt

    (a level vehicle: the heading turns the horizontal velocity), ``Q = s G Sigma_u G^T + diag(q) dt``
    with ``G = d f / d u``, ``Sigma_u`` the record's covariance (control ``odom_cov [..., 4, 4]``),
    ``s`` = ``odom_scale`` and ``q`` = ``process_psd`` ``[4]``.

    Controls: ``odom [..., 4]``, ``odom_cov [..., 4, 4]``, ``dt [..., 1]``.
    Learnable: ``odom_scale`` (``Positive(1e-6)``), ``process_psd`` (``Positive(1e-12)``).
    """

    state_dim = 4
    angular = (3,)
    odom_scale: Tensor
    process_psd: Tensor

    def __init__(
        self,
        *,
        odom_scale: float = 1.0,
        process_psd: tuple[float, float, float, float] = (1e-4, 1e-4, 1e-4, 1e-6),
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        if not float(odom_scale) > 0 or len(process_psd) != 4 or min(process_psd) <= 0:
            raise ValueError(f"odom_scale must be > 0 and process_psd four positive numbers, got {odom_scale}, {process_psd}")
        register_constrained(self, "odom_scale", torch.tensor(float(odom_scale), dtype=dtype), Positive(1e-6))
        register_constrained(self, "process_psd", torch.tensor([float(q) for q in process_psd], dtype=dtype), Positive(1e-12))

    def _g(self, x: Tensor, dt: Tensor) -> Tensor:
        """``d f / d u`` ``[..., 4, 4]``."""
        c, s = torch.cos(x[..., 3]), torch.sin(x[..., 3])
        z = torch.zeros_like(c * dt)
        rows = [[c * dt, -s * dt, z, z], [s * dt, c * dt, z, z], [z, z, z + dt, z], [z, z, z, z + dt]]
        return torch.stack([torch.stack(r, -1) for r in rows], -2)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        odom, dt = control(u, "odom").to(x.dtype), control(u, "dt").to(x.dtype)[..., 0]
        return x + (self._g(x, dt) @ odom[..., None])[..., 0]

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return heading_jacobian(x, u, heading=3)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        cov, dt = control(u, "odom_cov").to(x.dtype), control(u, "dt").to(x.dtype)[..., 0]
        g = self._g(x, dt)
        q = self.odom_scale * (g @ cov @ g.mT) + torch.diag_embed(self.process_psd * dt[..., None])
        return 0.5 * (q + q.mT)


class ConstantVelocity3D(DynamicsModel):
    """``x = [p, v]`` (3 + 3), ``p_k = p_{k-1} + v_{k-1} dt``, ``v_k = v_{k-1}``, with continuous
    white acceleration of spectral density ``q`` per axis (``process_psd [3]``, m^2/s^3):
    ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis.  Controls: ``dt [..., 1]``.
    Learnable: ``process_psd`` (``Positive(1e-12)``)."""

    state_dim = 6
    process_psd: Tensor

    def __init__(self, *, process_psd: tuple[float, float, float] = (1.0, 1.0, 1.0), dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        if len(process_psd) != 3 or min(process_psd) <= 0:
            raise ValueError(f"process_psd must be three positive numbers, got {process_psd}")
        register_constrained(self, "process_psd", torch.tensor([float(q) for q in process_psd], dtype=dtype), Positive(1e-12))

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = control(u, "dt").to(x.dtype)[..., 0]
        shape = torch.broadcast_shapes(x.shape[:-1], dt.shape)
        f = torch.eye(6, dtype=x.dtype, device=x.device).expand(*shape, 6, 6).clone()
        for i in range(3):
            f[..., i, 3 + i] = dt.expand(shape)
        return f

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = control(u, "dt").to(x.dtype)
        return torch.cat([x[..., :3] + x[..., 3:] * dt, x[..., 3:] + 0.0 * dt], -1)

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        dt = control(u, "dt").to(x.dtype)[..., 0]
        q = torch.diag_embed(self.process_psd.expand(*dt.shape, 3))
        d = dt[..., None, None]
        top = torch.cat([q * d**3 / 3, q * d**2 / 2], -1)
        out = torch.cat([top, torch.cat([q * d**2 / 2, q * d], -1)], -2)
        return 0.5 * (out + out.mT)


class RangeMeasurement3D(RangeMeasurement2D):
    """:class:`~difffilter.models.navigation.ranging2d.RangeMeasurement2D` with 3-D anchors
    (control ``anchors [..., A, 3]``) and the position in the first three state components of a
    ``state_dim``-dimensional state."""

    def __init__(self, *, state_dim: int, **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        if int(state_dim) < 3:
            raise ValueError(f"state_dim must be >= 3 (the position comes first), got {state_dim}")
        self.state_dim = int(state_dim)

    def _geometry(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor]:
        d = x[..., None, :3] - control(u, "anchors").to(x.dtype)
        return d, torch.sqrt((d * d).sum(-1) + 1e-12)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        d, r = self._geometry(x, u)
        unit = d / r[..., None]
        return torch.cat([unit, unit.new_zeros(*unit.shape[:-1], self.state_dim - 3)], -1)


def make_ranging3d_model(
    *,
    num_anchors: int,
    odometry: bool,
    bias: str | None = "anchor",
    noise: str | None = "anchor",
    gate: str | None = "soft",
    gate_threshold: float = 3.0,
    gate_floor: float = 0.5,
    gate_softness: float = 0.5,
    odom_scale: float = 1.0,
    process_psd: tuple[float, ...] | None = None,
    dtype: torch.dtype = torch.float64,
) -> StateSpaceModel:
    """The 3-D range model with :class:`OdometryDynamics3D` (``odometry=True``; default
    ``process_psd`` ``(1e-4, 1e-4, 1e-4, 1e-6)``) or :class:`ConstantVelocity3D` (default
    ``process_psd`` ``(1, 1, 1)`` m^2/s^3); ``gate`` as
    :func:`~difffilter.models.navigation.ranging2d.make_ranging_model`."""
    robust = range_gate(gate, threshold=gate_threshold, floor=gate_floor, softness=gate_softness, dtype=dtype)
    dyn: DynamicsModel
    if odometry:
        dyn = OdometryDynamics3D(odom_scale=odom_scale, process_psd=tuple(process_psd or (1e-4, 1e-4, 1e-4, 1e-6)), dtype=dtype)  # type: ignore[arg-type]
    else:
        dyn = ConstantVelocity3D(process_psd=tuple(process_psd or (1.0, 1.0, 1.0)), dtype=dtype)  # type: ignore[arg-type]
    meas = RangeMeasurement3D(state_dim=dyn.state_dim, num_anchors=num_anchors, bias=bias, noise=noise, gate=robust, dtype=dtype)
    return StateSpaceModel(dyn, meas)
