"""State-space model interfaces.

A model describes

.. math::
    x_{k} = f(x_{k-1}, u_k) + w_k,\\quad w_k \\sim N(0, Q) \\qquad
    z_k = h(x_k, u_k) + v_k,\\quad v_k \\sim N(0, R)

with states ``[..., n]`` and measurements ``[..., m]``.  ``u`` are per-step exogenous inputs
(controls, time steps, satellite positions...): a tensor or a ``dict`` of tensors whose leading
dimensions broadcast against ``x`` (filters pass ``u`` with a singleton sigma-point dimension,
e.g. ``x [B, S, n]`` with ``u [B, 1, k]``).  Models are written for arbitrary leading
dimensions with ``...`` indexing, which is all the filters and ``torch.func`` need.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from ..params import check_covariance, register_covariance

__all__ = [
    "Controls",
    "DynamicsModel",
    "FunctionalModel",
    "LinearModel",
    "MeasurementModel",
    "StateSpaceModel",
    "wrap_angle",
    "wrap_components",
]

Controls = Tensor | dict[str, Tensor] | None


def wrap_angle(angle: Tensor) -> Tensor:
    """Angle reduced to ``(-pi, pi]`` (gradient 1 almost everywhere)."""
    two_pi = 2.0 * math.pi
    return angle - two_pi * torch.ceil((angle - math.pi) / two_pi)


def wrap_components(x: Tensor, indices: tuple[int, ...]) -> Tensor:
    """``x [..., d]`` with the components ``indices`` reduced to ``(-pi, pi]`` (out of place)."""
    if not indices:
        return x
    sel = torch.zeros(x.shape[-1], dtype=torch.bool, device=x.device)
    sel[list(indices)] = True
    return torch.where(sel, wrap_angle(x), x)


class DynamicsModel(nn.Module):
    """Transition ``f`` with process noise ``Q``.

    Subclasses implement :meth:`forward` (``f``); they may override :meth:`jacobian` (analytic
    ``df/dx``, else filters use autodiff), :meth:`process_noise` (state-dependent Q) and
    :meth:`matrix` (return ``F`` when ``f(x) = F x + c(u)`` is linear, enabling the Kalman filter
    and the simplified UKF).  ``self.Q`` is the (constrained) process-noise covariance.

    ``angular`` lists the state components that are angles (radians, ``2 pi``-periodic): the
    filters then take differences with :meth:`residual` and add corrections with :meth:`add`,
    both wrapped to ``(-pi, pi]``, and the unscented filters average them around a reference
    point (a circular mean).
    """

    state_dim: int
    angular: tuple[int, ...] = ()
    #: False for dynamics that ignore the per-step inputs (a ``LinearModel`` without ``B``, a
    #: ``FunctionalModel(controls=False)``): controls given to a model whose parts all ignore
    #: them are refused instead of silently dropped.
    uses_controls: bool = True

    def residual(self, x: Tensor, x_ref: Tensor) -> Tensor:
        """State difference ``x - x_ref`` ``[..., n]``, angular components wrapped."""
        return wrap_components(x - x_ref, self.angular)

    def add(self, x: Tensor, dx: Tensor) -> Tensor:
        """State ``x + dx`` ``[..., n]``, angular components wrapped."""
        return wrap_components(x + dx, self.angular)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        """Analytic ``df/dx [..., n, n]``, or ``None`` to let the filter differentiate ``f``."""
        return None

    def matrix(self, u: Controls = None) -> Tensor | None:
        """``F [..., n, n]`` if the dynamics are linear (affine in ``u``), else ``None``."""
        return None

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        """Process-noise covariance ``[n, n]`` or ``[..., n, n]`` for prior mean ``x``."""
        return self.Q

    def validate_controls(self, controls: Controls) -> None:
        """Check the whole run's inputs ``[B, T, ...]`` before filtering; raise ``ValueError``
        naming the input and the batch element(s) that are invalid (default: nothing to check)."""

    def precompute_controls(self, controls: Controls) -> Controls:
        """Whole-run inputs ``[B, T, ...]`` with entries derived from them added, computed once
        for every step before the time loop (default: ``controls`` unchanged).

        For a model whose per-step matrices depend on the inputs only (not on the state or on
        parameters), e.g. a transition matrix ``Phi = expm(F(u) dt)``, one batched call over
        ``[B, T]`` replaces ``T`` per-step calls.  The filters call it in ``forward`` after
        validating the inputs; a model reads a derived entry in :meth:`matrix` etc. when present
        and computes it itself otherwise (a single :meth:`~difffilter.filters.RecursiveFilter.step`
        call, a model used on its own), with equal results.  Derived entries are named so that
        two models that compute different values never share a key; a model whose key is
        already present (another mode of an IMM with the same configuration) leaves it as is.
        """
        return controls

    #: ``False`` when the model declares non-additive process noise ``x_k = f(x, w, u)``: it then
    #: implements :meth:`with_noise`, and ``forward(x, u)`` is ``f(x, 0, u)``.
    additive_noise: bool = True

    def with_noise(self, x: Tensor, w: Tensor, u: Controls = None) -> Tensor:
        """``f(x, w, u)`` for noise samples ``w [..., q]`` (``Q`` is ``[q, q]``); additive models
        return ``f(x, u) + w``."""
        return self(x, u) + w

    def noise_jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        """Analytic ``df/dw [..., n, q]`` at ``w = 0``, or ``None`` (identity for additive noise,
        else the filter differentiates :meth:`with_noise`)."""
        return None


class MeasurementModel(nn.Module):
    """Measurement ``h`` with noise ``R``; the counterpart of :class:`DynamicsModel`.

    ``angular`` lists the measurement components that are angles (a bearing, a heading): the
    default :meth:`residual` wraps them and the unscented filters compute their predicted
    measurement as a circular mean (around a reference sigma point), so that points on both
    sides of ``+-pi`` average to an angle near ``pi``, not near 0.
    """

    measurement_dim: int
    angular: tuple[int, ...] = ()
    #: As :attr:`DynamicsModel.uses_controls`.
    uses_controls: bool = True

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        """Analytic ``dh/dx [..., m, n]``, or ``None`` to let the filter differentiate ``h``."""
        return None

    def matrix(self, u: Controls = None) -> Tensor | None:
        """``H [..., m, n]`` if ``h(x) = H x`` is linear, else ``None``."""
        return None

    def measurement_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        """Measurement-noise covariance ``[m, m]`` or ``[..., m, m]``."""
        return self.R

    def residual(self, z: Tensor, z_ref: Tensor) -> Tensor:
        """Difference ``z - z_ref`` of measurements ``[..., m]``, the :attr:`angular` components
        wrapped to ``(-pi, pi]``."""
        return wrap_components(z - z_ref, self.angular)

    def validate_controls(self, controls: Controls) -> None:
        """As :meth:`DynamicsModel.validate_controls`."""

    def precompute_controls(self, controls: Controls) -> Controls:
        """As :meth:`DynamicsModel.precompute_controls` (default: ``controls`` unchanged)."""
        return controls

    #: ``False`` when the model declares non-additive measurement noise ``z = h(x, v, u)``: it
    #: then implements :meth:`with_noise`, and ``forward(x, u)`` is ``h(x, 0, u)``.
    additive_noise: bool = True

    def with_noise(self, x: Tensor, v: Tensor, u: Controls = None) -> Tensor:
        """``h(x, v, u)`` for noise samples ``v [..., r]`` (``R`` is ``[r, r]``); additive models
        return ``h(x, u) + v``."""
        return self(x, u) + v

    def noise_jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        """Analytic ``dh/dv [..., m, r]`` at ``v = 0``, or ``None`` (see :meth:`DynamicsModel.noise_jacobian`)."""
        return None


class StateSpaceModel(nn.Module):
    """A dynamics model and a measurement model: what every filter consumes."""

    def __init__(self, dynamics: DynamicsModel, measurement: MeasurementModel) -> None:
        super().__init__()
        self.dynamics = dynamics
        self.measurement = measurement

    @property
    def state_dim(self) -> int:
        return int(self.dynamics.state_dim)

    @property
    def measurement_dim(self) -> int:
        return int(self.measurement.measurement_dim)

    # Convenience accessors so that ``model.Q``/``model.R`` read and write the constrained values.
    @property
    def Q(self) -> Tensor:  # noqa: N802 - field notation
        return self.dynamics.Q

    @Q.setter
    def Q(self, value: Tensor) -> None:  # noqa: N802
        self.dynamics.Q = value

    @property
    def R(self) -> Tensor:  # noqa: N802
        return self.measurement.R

    @R.setter
    def R(self, value: Tensor) -> None:  # noqa: N802
        self.measurement.R = value

    def f(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.dynamics(x, u)

    def h(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.measurement(x, u)


def _check_matrix(name: str, value: Tensor | None, dtype: torch.dtype | None) -> None:
    """A model matrix: a finite floating-point tensor of the model's dtype (``dtype``: that of
    the first matrix given)."""
    if value is None:
        return
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if not value.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {value.dtype}")
    if dtype is not None and value.dtype != dtype:
        raise TypeError(f"{name} has dtype {value.dtype} but the model's other matrices are {dtype}: give all of F, H, Q, R, B one dtype")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must be finite, got non-finite entries")


class _FunctionalDynamics(DynamicsModel):
    def __init__(self, f: Callable[..., Tensor], Q: Tensor, jacobian: Callable[..., Tensor] | None, structure: str, takes_u: bool) -> None:  # noqa: N803
        super().__init__()
        check_covariance("Q", Q, semidefinite=True)
        self.state_dim = Q.shape[-1]
        self._f, self._jac, self._takes_u = f, jacobian, takes_u
        self.uses_controls = bool(takes_u)
        register_covariance(self, "Q", Q, structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return self._f(x, u) if self._takes_u else self._f(x)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        if self._jac is None:
            return None
        return self._jac(x, u) if self._takes_u else self._jac(x)


class _FunctionalMeasurement(MeasurementModel):
    def __init__(self, h: Callable[..., Tensor], R: Tensor, jacobian: Callable[..., Tensor] | None, structure: str, takes_u: bool) -> None:  # noqa: N803
        super().__init__()
        check_covariance("R", R, semidefinite=True)
        self.measurement_dim = R.shape[-1]
        self._h, self._jac, self._takes_u = h, jacobian, takes_u
        self.uses_controls = bool(takes_u)
        register_covariance(self, "R", R, structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return self._h(x, u) if self._takes_u else self._h(x)

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor | None:
        if self._jac is None:
            return None
        return self._jac(x, u) if self._takes_u else self._jac(x)


class FunctionalModel(StateSpaceModel):
    """A model from plain callables.

    ``angular_states`` / ``angular_measurements`` declare angle components (see
    :attr:`DynamicsModel.angular`, :attr:`MeasurementModel.angular`).

    Args:
        f: transition ``f(x [..., n]) -> [..., n]`` (or ``f(x, u)`` with ``controls=True``).
        h: measurement ``h(x [..., n]) -> [..., m]`` (or ``h(x, u)``).
        Q: process-noise covariance ``[n, n]`` (positive semi-definite); learnable with structure
            ``Q_structure``.
        R: measurement-noise covariance ``[m, m]``; learnable with structure ``R_structure``.
        f_jacobian, h_jacobian: optional analytic Jacobians ``[..., n, n]`` / ``[..., m, n]``.
        controls: whether ``f``/``h`` take the per-step inputs ``u`` as second argument.
        Q_structure, R_structure: ``"auto"`` (default: ``"full"`` when the value is positive
            definite, ``"factor"`` when it is semi-definite, e.g. the white-noise-acceleration
            ``Q``, ``"scalar"`` when a variance is below the dtype's floor, e.g. float32
            ``R = 1e-20 I``), ``"full"``, ``"diagonal"``, ``"scalar"``, ``"factor"`` (a free
            factor of the value's rank: learnable semi-definite covariances) or ``"fixed"``
            (:func:`~difffilter.params.register_covariance`).
        angular_states, angular_measurements: indices of angle components (radians).
    """

    def __init__(
        self,
        *,
        f: Callable[..., Tensor],
        h: Callable[..., Tensor],
        Q: Tensor,  # noqa: N803
        R: Tensor,  # noqa: N803
        f_jacobian: Callable[..., Tensor] | None = None,
        h_jacobian: Callable[..., Tensor] | None = None,
        controls: bool = False,
        Q_structure: str = "auto",  # noqa: N803
        R_structure: str = "auto",  # noqa: N803
        angular_states: tuple[int, ...] = (),
        angular_measurements: tuple[int, ...] = (),
    ) -> None:
        if isinstance(Q, Tensor) and isinstance(R, Tensor) and Q.dtype != R.dtype:
            raise TypeError(f"Q and R must have one dtype, got Q {Q.dtype} and R {R.dtype}")
        super().__init__(
            _FunctionalDynamics(f, Q, f_jacobian, Q_structure, controls),
            _FunctionalMeasurement(h, R, h_jacobian, R_structure, controls),
        )
        self.dynamics.angular = _indices("angular_states", angular_states, self.state_dim)
        self.measurement.angular = _indices("angular_measurements", angular_measurements, self.measurement_dim)


def _indices(name: str, indices: tuple[int, ...], dim: int) -> tuple[int, ...]:
    out = tuple(int(i) for i in indices)
    if len(set(out)) != len(out) or not all(0 <= i < dim for i in out):
        raise ValueError(f"{name} must be distinct component indices in [0, {dim}), got {list(indices)}")
    return out


class _LinearDynamics(DynamicsModel):
    def __init__(self, F: Tensor, Q: Tensor, B: Tensor | None, structure: str) -> None:  # noqa: N803
        super().__init__()
        if F.ndim != 2 or F.shape[0] != F.shape[1]:
            raise ValueError(f"F must be a square matrix [n, n], got shape {tuple(F.shape)}")
        n = F.shape[0]
        check_covariance("Q", Q, n, semidefinite=True)
        if B is not None and (B.ndim != 2 or B.shape[0] != n):
            raise ValueError(f"B must have shape [{n}, k], got {tuple(B.shape)}")
        self.state_dim = n
        self.register_buffer("F", F.detach().clone())
        self.register_buffer("B", None if B is None else B.detach().clone())
        self.uses_controls = B is not None
        register_covariance(self, "Q", Q, structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        out = x @ self.F.mT
        if self.B is not None and u is not None:
            if not isinstance(u, Tensor):
                raise TypeError("controls for a LinearModel with B must be a tensor [B, T, k]")
            out = out + u @ self.B.mT
        return out

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.F.expand(*x.shape[:-1], *self.F.shape)

    def matrix(self, u: Controls = None) -> Tensor:
        return self.F


class _LinearMeasurement(MeasurementModel):
    def __init__(self, H: Tensor, R: Tensor, structure: str) -> None:  # noqa: N803
        super().__init__()
        if H.ndim != 2:
            raise ValueError(f"H must be a matrix [m, n], got shape {tuple(H.shape)}")
        check_covariance("R", R, H.shape[0], semidefinite=True)
        self.measurement_dim = H.shape[0]
        self.register_buffer("H", H.detach().clone())
        self.uses_controls = False
        register_covariance(self, "R", R, structure)

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        return x @ self.H.mT

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        return self.H.expand(*x.shape[:-1], *self.H.shape)

    def matrix(self, u: Controls = None) -> Tensor:
        return self.H


class LinearModel(StateSpaceModel):
    """Linear-Gaussian model ``x_k = F x_{k-1} + B u_k + w_k``, ``z_k = H x_k + v_k``.

    ``F [n, n]``, ``H [m, n]``, ``Q [n, n]`` (positive semi-definite), ``R [m, m]``, optional
    ``B [n, k]`` (then ``controls`` are ``[B, T, k]``), all finite and of one dtype.  ``Q`` and
    ``R`` are learnable (see ``*_structure``, as for :class:`FunctionalModel`).
    """

    def __init__(
        self,
        *,
        F: Tensor,  # noqa: N803
        H: Tensor,  # noqa: N803
        Q: Tensor,  # noqa: N803
        R: Tensor,  # noqa: N803
        B: Tensor | None = None,  # noqa: N803
        Q_structure: str = "auto",  # noqa: N803
        R_structure: str = "auto",  # noqa: N803
    ) -> None:
        _check_matrix("F", F, None)
        for name, value in (("H", H), ("Q", Q), ("R", R), ("B", B)):
            _check_matrix(name, value, F.dtype)
        if H.ndim == 2 and F.ndim == 2 and H.shape[1] != F.shape[0]:
            raise ValueError(f"H must have shape [m, {F.shape[0]}], got {tuple(H.shape)}")
        super().__init__(_LinearDynamics(F, Q, B, Q_structure), _LinearMeasurement(H, R, R_structure))
