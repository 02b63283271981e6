"""Models with non-additive noise: ``x_k = f(x_{k-1}, w_k, u_k)`` and ``z_k = h(x_k, v_k, u_k)``.

The filters read a model's noise structure from ``dynamics.additive_noise`` /
``measurement.additive_noise`` (see :class:`~difffilter.models.base.DynamicsModel`): an additive
model (the default, and the fast path) adds ``w ~ N(0, Q)`` and ``v ~ N(0, R)`` to ``f`` and
``h``; a non-additive one passes the noise through :meth:`with_noise`.  The EKF then propagates
``F_w Q F_w^T`` and uses ``H_v R H_v^T`` (Jacobians w.r.t. the noise at zero), and the UKF with
``noise="augmented"`` draws sigma points of ``[x; w]`` (``[x; v]``) and passes them through the
functions.  ``Q [q, q]`` and ``R [r, r]`` are the covariances of the noise inputs, whose
dimensions need not equal the state's or the measurement's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from torch import Tensor

from .base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel, _FunctionalDynamics, _FunctionalMeasurement

__all__ = ["NonAdditiveModel"]


def _zeros(x: Tensor, dim: int) -> Tensor:
    return x.new_zeros(*x.shape[:-1], dim)


class _NoisyDynamics(_FunctionalDynamics):
    """``f(x, w[, u])``: the functional dynamics with the noise as an input (``Q`` is ``w``'s)."""

    additive_noise = False

    def __init__(self, f: Callable[..., Tensor], Q: Tensor, state_dim: int, takes_u: bool, structure: str) -> None:  # noqa: N803
        super().__init__(f, Q, None, structure, takes_u)
        self.state_dim = int(state_dim)

    def with_noise(self, x: Tensor, w: Tensor, u: Controls = None) -> Tensor:
        return self._f(x, w, u) if self._takes_u else self._f(x, w)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.with_noise(x, _zeros(x, self.Q.shape[-1]), u)


class _NoisyMeasurement(_FunctionalMeasurement):
    """``h(x, v[, u])``: the functional measurement with the noise as an input (``R`` is ``v``'s)."""

    additive_noise = False

    def __init__(self, h: Callable[..., Tensor], R: Tensor, measurement_dim: int, takes_u: bool, structure: str) -> None:  # noqa: N803
        super().__init__(h, R, None, structure, takes_u)
        self.measurement_dim = int(measurement_dim)

    def with_noise(self, x: Tensor, v: Tensor, u: Controls = None) -> Tensor:
        return self._h(x, v, u) if self._takes_u else self._h(x, v)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.with_noise(x, _zeros(x, self.R.shape[-1]), u)


class NonAdditiveModel(StateSpaceModel):
    """A model from callables whose noise enters non-additively.

    ``x_k = f(x_{k-1}, w_k[, u_k])``, ``w ~ N(0, Q)``; ``z_k = h(x_k, v_k[, u_k])``,
    ``v ~ N(0, R)`` for the functions named in ``nonadditive``; the others keep the additive form
    ``f(x[, u]) + w`` / ``h(x[, u]) + v``.  Example, a unicycle whose speed and turn rate are
    perturbed (``w = [dv, domega]``, two noise inputs for a three-dimensional state)::

        def f(x, w):
            v, om = 1.0 + w[..., 0], 0.1 + w[..., 1]
            return torch.stack([x[..., 0] + v * x[..., 2].cos(), x[..., 1] + v * x[..., 2].sin(), x[..., 2] + om], -1)

        model = NonAdditiveModel(f=f, h=lambda x: x[..., :2], Q=torch.diag(torch.tensor([0.01, 1e-4])),
                                 R=0.25 * torch.eye(2), state_dim=3, nonadditive="f")

    Args:
        f, h: the transition and measurement functions (any leading dimensions).
        Q: ``[q, q]`` covariance of ``w`` (``q = n`` when ``f`` is additive); learnable.
        R: ``[r, r]`` covariance of ``v`` (``r = m`` when ``h`` is additive); learnable.
        state_dim: ``n``.
        measurement_dim: ``m``; required when ``h`` is non-additive (else ``R``'s size).
        nonadditive: ``"f"``, ``"h"`` or both (``("f", "h")``, the default).
        controls: whether ``f`` and ``h`` take the per-step inputs ``u`` as their last argument.
        Q_structure, R_structure: ``"full"``, ``"diagonal"``, ``"scalar"`` or ``"fixed"``.

    Filters: :class:`~difffilter.filters.EKF` (and :class:`~difffilter.filters.IteratedEKF`) and
    :class:`~difffilter.filters.UKF` with ``noise="augmented"``.
    """

    def __init__(
        self,
        *,
        f: Callable[..., Tensor],
        h: Callable[..., Tensor],
        Q: Tensor,  # noqa: N803
        R: Tensor,  # noqa: N803
        state_dim: int,
        measurement_dim: int | None = None,
        nonadditive: str | Sequence[str] = ("f", "h"),
        controls: bool = False,
        Q_structure: str = "full",  # noqa: N803
        R_structure: str = "full",  # noqa: N803
    ) -> None:
        which = {nonadditive} if isinstance(nonadditive, str) else set(nonadditive)
        if not which or not which <= {"f", "h"}:
            raise ValueError(f"nonadditive must be 'f', 'h' or both, got {nonadditive!r}")
        if not isinstance(state_dim, int) or state_dim < 1:
            raise ValueError(f"state_dim must be a positive int, got {state_dim!r}")
        if not isinstance(Q, Tensor) or not isinstance(R, Tensor):
            raise TypeError("Q and R must be torch tensors [q, q], [r, r]")
        if "f" not in which and Q.shape[-1] != state_dim:
            raise ValueError(f"additive process noise needs Q [{state_dim}, {state_dim}], got {tuple(Q.shape)}")
        if "h" in which:
            if measurement_dim is None or int(measurement_dim) < 1:
                raise ValueError("measurement_dim (a positive int) is required when h is non-additive")
            meas: MeasurementModel = _NoisyMeasurement(h, R, int(measurement_dim), controls, R_structure)
        else:
            if measurement_dim is not None and int(measurement_dim) != R.shape[-1]:
                raise ValueError(f"additive measurement noise needs R [{measurement_dim}, {measurement_dim}], got {tuple(R.shape)}")
            meas = _FunctionalMeasurement(h, R, None, R_structure, controls)
        dyn: DynamicsModel = (
            _NoisyDynamics(f, Q, state_dim, controls, Q_structure)
            if "f" in which
            else _FunctionalDynamics(f, Q, None, Q_structure, controls)
        )
        super().__init__(dyn, meas)
