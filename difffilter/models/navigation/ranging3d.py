"""3-D ranging to fixed anchors (the libRSF ``range3`` data sets, :mod:`difffilter.datasets.ranging`):
with ``odom3`` odometry or without any.

* With odometry, state ``x = [p_x, p_y, p_z, psi]`` (m; heading about the vertical, rad):
  :class:`OdometryDynamics3D`, driven by the body-frame velocity and the yaw rate of the record.
* Without odometry, the library's constant-velocity model
  :class:`~difffilter.models.motion.ConstantVelocity` ``(axes=3)`` (white-noise acceleration),
  state axis by axis ``x = [p_x, v_x, p_y, v_y, p_z, v_z]``.

The measurement is :class:`~difffilter.models.navigation.ranging2d.RangeMeasurement2D`'s range
model on the three state components named by ``position`` (:class:`RangeMeasurement3D`: per
anchor range bias, noise scale on the file's variances, robust gate), so it serves either state.
:func:`make_ranging3d_model` builds both and records the state's layout as
``model.defaults.layout`` (:class:`~difffilter.models.layout.StateLayout`: ``position`` gives the
position indices, ``(0, 1, 2)`` with odometry, ``(0, 2, 4)`` without).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..._util import control
from ...constraints import Positive
from ...params import register_constrained
from ...selection import parameter_owners
from ..base import Controls, DynamicsModel, StateSpaceModel
from ..layout import StateLayout, describe
from ..motion import ConstantVelocity
from .ranging2d import RangeMeasurement2D, heading_jacobian, range_gate

__all__ = ["OdometryDynamics3D", "RangeMeasurement3D", "make_ranging3d_model"]

# The state of OdometryDynamics3D: the position first, the heading last.
_ODOMETRY_LAYOUT = StateLayout(names=("x", "y", "z", "psi"), units=("m", "m", "m", "rad"), position=(0, 1, 2), angles=(3,))


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


class RangeMeasurement3D(RangeMeasurement2D):
    """:class:`~difffilter.models.navigation.ranging2d.RangeMeasurement2D` with 3-D anchors
    (control ``anchors [..., A, 3]``) and the position at the state indices ``position`` (three
    distinct indices in ``[0, state_dim)``: ``(0, 1, 2)`` for :class:`OdometryDynamics3D`,
    ``(0, 2, 4)`` for :class:`~difffilter.models.motion.ConstantVelocity` ``(axes=3)``; a
    model's ``defaults.layout.position``).  Other keyword arguments as the 2-D model."""

    def __init__(self, *, state_dim: int, position: Sequence[int], **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        n = int(state_dim)
        if n < 3:
            raise ValueError(f"state_dim must be >= 3 (three position components), got {state_dim}")
        pos = tuple(int(i) for i in position)
        if len(pos) != 3 or len(set(pos)) != 3 or not all(0 <= i < n for i in pos):
            raise ValueError(f"position must be three distinct state indices in [0, {n}), got {list(position)}")
        self.state_dim = n
        self.position = pos

    def _geometry(self, x: Tensor, u: Controls) -> tuple[Tensor, Tensor]:
        d = x[..., None, list(self.position)] - control(u, "anchors").to(x.dtype)
        return d, torch.sqrt((d * d).sum(-1) + 1e-12)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        d, r = self._geometry(x, u)
        jac = d.new_zeros(*d.shape[:-1], self.state_dim)
        jac[..., list(self.position)] = d / r[..., None]
        return jac


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
    ``process_psd`` ``(1e-4, 1e-4, 1e-4, 1e-6)``) or
    :class:`~difffilter.models.motion.ConstantVelocity` ``(axes=3)`` (``process_psd`` is its
    per-axis acceleration density ``q``, default ``(1, 1, 1)`` m^2/s^3; the sample interval is
    the control ``dt``); ``gate`` as :func:`~difffilter.models.navigation.ranging2d.make_ranging_model`.
    The model carries ``defaults`` (:func:`~difffilter.models.layout.describe`): the state's
    layout (``defaults.layout.position``: where the position sits) and every parameter as
    ``learn``."""
    robust = range_gate(gate, threshold=gate_threshold, floor=gate_floor, softness=gate_softness, dtype=dtype)
    dyn: DynamicsModel
    if odometry:
        dyn = OdometryDynamics3D(odom_scale=odom_scale, process_psd=tuple(process_psd or (1e-4, 1e-4, 1e-4, 1e-6)), dtype=dtype)  # type: ignore[arg-type]
        layout = _ODOMETRY_LAYOUT
    else:
        q = tuple(process_psd or (1.0, 1.0, 1.0))
        if len(q) != 3 or min(q) <= 0:
            raise ValueError(f"process_psd must be three positive numbers without odometry, got {q}")
        dyn = ConstantVelocity(axes=3, q=torch.tensor(q, dtype=dtype), dtype=dtype)
        layout = StateLayout.kinematic(axes=3, order=2)
    meas = RangeMeasurement3D(
        state_dim=dyn.state_dim, position=layout.position, num_anchors=num_anchors, bias=bias, noise=noise, gate=robust, dtype=dtype
    )
    model = StateSpaceModel(dyn, meas)
    return describe(model, layout=layout, learn=list(parameter_owners(model)), name="ranging3d")  # type: ignore[return-value]
