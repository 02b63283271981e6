"""Model factories for configs: kinematic targets observed in position, linear measurements, and
the time-invariant cache of linear dynamics.

Configs cannot write tensors or dtypes; these functions take lists, floats and dtype names
(``"float64"``) and return modules, so a model config reads like the paper's table::

    _target_: difffilter.models.tracking_model
    dynamics: {_target_: difffilter.models.motion.Singer, axes: 2, dt: 1.0, tau: 20.0, sigma_a: 1.0}
    R: [100.0, 100.0]          # position measurement variances (m^2)
    learn: [tau, sigma_a, R]   # what `learn: null` trains (default: every parameter)
    dtype: float64
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from .._util import as_dtype, covariance
from .base import Controls, DynamicsModel, LinearModel, MeasurementModel, StateSpaceModel
from .layout import StateLayout, describe

__all__ = ["TimeInvariantDynamics", "linear_measurement", "tracking_model"]


class TimeInvariantDynamics(DynamicsModel):
    """Wraps linear, time-invariant dynamics (``F`` and ``Q`` independent of the time step, the
    state and ``u``) so that ``F`` and ``Q`` are computed once per filter run instead of at
    every step.

    A Singer model rebuilds its series-expanded ``Phi(tau)`` and ``Q(tau, sigma)`` at each of
    the ``T`` predictions, which dominates a Kalman filter's cost.  Filters evaluate parameters
    inside ``torch.nn.utils.parametrize.cached()``, where every constrained value is one tensor
    object for the whole run; the cache here is keyed on those very objects (held, not just
    their ids), so it is reused within a run and recomputed as soon as a parameter changes.
    Outside ``cached()`` it never reuses anything.  Parameters keep their names below
    ``inner`` (``dynamics.inner.tau`` still matches ``tau``).
    """

    def __init__(self, inner: DynamicsModel) -> None:
        super().__init__()
        if type(inner).matrix is DynamicsModel.matrix:
            raise TypeError("TimeInvariantDynamics needs linear dynamics that implement matrix()")
        self.inner = inner
        self.state_dim = int(inner.state_dim)
        self._key: tuple[Tensor, ...] | None = None
        self._value: tuple[Tensor, Tensor] | None = None

    def __getstate__(self) -> dict:
        # The cache may hold non-leaf tensors, which cannot be deep-copied; it is only a cache.
        state = super().__getstate__()
        return {**state, "_key": None, "_value": None}

    def _parameter_values(self) -> tuple[Tensor, ...]:
        out = []
        for mod in self.inner.modules():
            if parametrize.is_parametrized(mod):
                out.extend(getattr(mod, name) for name in mod.parametrizations.keys())  # type: ignore[union-attr]
        return tuple(out)

    def _compute(self) -> tuple[Tensor, Tensor]:
        ref = next(iter(self.inner.parameters()), None)
        ref = next(iter(self.inner.buffers()), None) if ref is None else ref
        zero = torch.zeros(self.state_dim, dtype=None if ref is None else ref.dtype, device=None if ref is None else ref.device)
        return self.inner.matrix(None), self.inner.process_noise(zero, None)

    def _matrices(self) -> tuple[Tensor, Tensor]:
        if not parametrize._cache_enabled:  # noqa: SLF001 - only the enabled flag is read
            self._key, self._value = None, None
            return self._compute()
        key = self._parameter_values()
        hit = self._value is not None and self._key is not None and len(key) == len(self._key)
        if not (hit and all(a is b for a, b in zip(key, self._key or (), strict=True))):
            self._key, self._value = key, self._compute()
        assert self._value is not None
        return self._value

    @staticmethod
    def _no_inputs(u: Controls) -> None:
        if u is not None:
            raise ValueError("TimeInvariantDynamics ignores per-step inputs; use the plain dynamics when u (e.g. u['dt']) is given")

    def forward(self, x: Tensor, u: Controls = None) -> Tensor:
        self._no_inputs(u)
        return x @ self._matrices()[0].mT

    def jacobian(self, x: Tensor, u: Controls = None) -> Tensor:
        self._no_inputs(u)
        f = self._matrices()[0]
        return f.expand(*x.shape[:-1], *f.shape[-2:])

    def matrix(self, u: Controls = None) -> Tensor:
        self._no_inputs(u)
        return self._matrices()[0]

    def process_noise(self, x: Tensor, u: Controls = None) -> Tensor:
        self._no_inputs(u)
        return self._matrices()[1]

    @property
    def Q(self) -> Tensor:  # noqa: N802
        return self._matrices()[1]


def linear_measurement(
    *,
    R: float | Sequence[float] | Sequence[Sequence[float]],  # noqa: N803
    H: Sequence[Sequence[float]] | Tensor | None = None,  # noqa: N803
    state_dim: int | None = None,
    observed: Sequence[int] | None = None,
    R_structure: str = "diagonal",  # noqa: N803
    dtype: torch.dtype | str | None = "float64",
) -> MeasurementModel:
    """Linear measurement ``z = H x + v``, ``v ~ N(0, R)`` (``R`` learnable with ``R_structure``).

    Give ``H [m, n]``, or ``state_dim`` and the ``observed`` state indices (``H`` then selects
    them).  ``R``: scalar, variances ``[m]`` or ``[m, m]``.
    """
    dt = as_dtype(dtype)
    if H is None:
        if state_dim is None or observed is None:
            raise ValueError("linear_measurement needs H or both state_dim and observed")
        h = torch.zeros(len(observed), int(state_dim), dtype=dt)
        h[torch.arange(len(observed)), torch.as_tensor(list(observed))] = 1.0
    else:
        h = torch.as_tensor(H, dtype=dt)
    m, n = h.shape
    eye = torch.eye(n, dtype=dt)
    # LinearModel's measurement part is the linear measurement module; its dynamics are unused.
    return LinearModel(F=eye, H=h, Q=eye, R=covariance(R, m, dt), R_structure=R_structure).measurement


def tracking_model(
    *,
    dynamics: DynamicsModel,
    R: float | Sequence[float] | Sequence[Sequence[float]],  # noqa: N803
    observed: Sequence[int] | None = None,
    R_structure: str = "diagonal",  # noqa: N803
    time_invariant: bool = False,
    learn: Sequence[str] | None = None,
    initial_mean: Sequence[float] | None = None,
    initial_var: Sequence[float] | None = None,
    reference: Mapping[str, Any] | None = None,
    name: str | None = None,
    dtype: torch.dtype | str | None = "float64",
) -> StateSpaceModel:
    """A kinematic ``dynamics`` (e.g. :class:`~difffilter.models.motion.Singer`) observed in
    position: ``observed`` defaults to the position index of every axis (``0, order, 2 order...``
    for the axis-by-axis layout of :mod:`difffilter.models.motion`).  The model is converted to
    ``dtype``.  ``time_invariant`` wraps the dynamics in :class:`TimeInvariantDynamics` (only for
    dynamics whose ``F`` and ``Q`` depend on nothing but parameters).

    The model carries :class:`~difffilter.models.layout.ModelDefaults`: the kinematic layout
    (:meth:`StateLayout.kinematic`), ``learn`` (default: the dynamics' constrained parameters in
    registration order, then ``R`` unless it is fixed), the default belief ``initial_mean`` /
    ``initial_var``, the in-family ``reference`` parameter values and the report label ``name``.
    """
    dt = as_dtype(dtype)
    n = int(dynamics.state_dim)
    order = getattr(dynamics, "order", None)
    if observed is None:
        if order is None:
            raise ValueError("observed is required for dynamics without an axis layout (no `order` attribute)")
        observed = list(range(0, n, int(order)))
    meas = linear_measurement(R=R, state_dim=n, observed=observed, R_structure=R_structure, dtype=dt)
    dyn: DynamicsModel = TimeInvariantDynamics(dynamics) if time_invariant else dynamics
    model = StateSpaceModel(dyn, meas).to(dt)
    if order is not None:
        layout = StateLayout.kinematic(axes=n // int(order), order=int(order))
    else:
        layout = StateLayout(names=tuple(f"x{i}" for i in range(n)), units=("",) * n, position=tuple(observed))
    if learn is None:
        own = list(dynamics.parametrizations.keys()) if parametrize.is_parametrized(dynamics) else []  # type: ignore[union-attr]
        learn = own + (["R"] if R_structure != "fixed" else [])
    return describe(model, layout=layout, learn=learn, initial_mean=initial_mean, initial_var=initial_var, reference=reference, name=name)  # type: ignore[return-value]
