"""What a model's state means and what it brings to an experiment that leaves things open.

* :class:`StateLayout` - names and units of the state components, which of them are positions
  (``rmse_pos``, trajectory figures) and which are angles.
* :class:`ModelDefaults` - the layout plus the parameters a model learns by default
  (``learn: null`` in a config), a default belief before the first measurement and, for
  in-family simulation (:class:`~difffilter.sim.ModelSimulator`), reference parameter
  values for the truth and a sampler of the per-step inputs a model needs (IMU readings,
  satellite positions).

Models carry their defaults as the attribute ``defaults`` (set by :func:`describe`: navigation
models as a class attribute, factories such as :func:`~difffilter.models.tracking.tracking_model`
on the instance they build); :func:`model_defaults` finds them on a model or on the model inside
a filter or mixer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from torch import nn

__all__ = ["ModelDefaults", "StateLayout", "describe", "model_defaults"]

_AXES = ("x", "y", "z")
_ORDER_NAMES = ("", "v", "a")
_ORDER_UNITS = ("m", "m/s", "m/s^2")


def _indices(name: str, values: Sequence[int], dim: int) -> tuple[int, ...]:
    out = tuple(int(i) for i in values)
    if len(set(out)) != len(out) or not all(0 <= i < dim for i in out):
        raise ValueError(f"{name} must be distinct state indices in [0, {dim}), got {list(values)}")
    return out


@dataclass(frozen=True, kw_only=True)
class StateLayout:
    """Names and units of the ``n`` state components and which are positions / angles.

    Args:
        names: ``n`` component names (``"x"``, ``"vx"``, ``"psi"``...).
        units: ``n`` unit strings (``"m"``, ``"m/s"``, ``"rad"``...).
        position: indices of the position components (the ``rmse_pos`` metric, figures).
        angles: indices of angle components (radians, defined modulo ``2 pi``).
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    position: tuple[int, ...]
    angles: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        names, units = tuple(str(v) for v in self.names), tuple(str(v) for v in self.units)
        if not names or len(set(names)) != len(names):
            raise ValueError(f"names must be distinct and non-empty, got {list(self.names)}")
        if len(units) != len(names):
            raise ValueError(f"units must give one unit per state component ({len(names)}), got {len(units)}")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "units", units)
        object.__setattr__(self, "position", _indices("position", self.position, len(names)))
        object.__setattr__(self, "angles", _indices("angles", self.angles, len(names)))
        if not self.position:
            raise ValueError("position must name at least one state component")

    @property
    def dim(self) -> int:
        """The state dimension ``n``."""
        return len(self.names)

    def index(self, *names: str) -> list[int]:
        """Indices of the named components (``ValueError`` for an unknown name)."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise ValueError(f"unknown state components {missing}; the layout has {list(self.names)}")
        return [self.names.index(n) for n in names]

    @classmethod
    def kinematic(cls, *, axes: int, order: int) -> StateLayout:
        """Axis-by-axis kinematic states ``[x, vx(, ax), y, vy(, ay)...]`` (the layout of
        :mod:`difffilter.models.motion`): ``order`` components per axis, ``axes`` axes."""
        if not 1 <= axes <= 3 or not 1 <= order <= 3:
            raise ValueError(f"axes and order must lie in [1, 3], got {axes}, {order}")
        names = [f"{_ORDER_NAMES[k]}{_AXES[a]}" for a in range(axes) for k in range(order)]
        units = [_ORDER_UNITS[k] for _ in range(axes) for k in range(order)]
        return cls(names=tuple(names), units=tuple(units), position=tuple(range(0, axes * order, order)))


@dataclass(frozen=True, kw_only=True)
class ModelDefaults:
    """What a model brings to an experiment that leaves it open (module docstring).

    Args:
        layout: the :class:`StateLayout`.
        learn: names of the parameters trained when the config says ``learn: null``.
        initial_mean, initial_var: default belief ``N(mean, diag(var))`` before the first
            measurement (``None``: the scenario must give one).
        reference: constrained parameter values of the in-family truth (names as in
            ``learn``); empty: the truth is the model as configured.
        controls: ``(batch_size, num_steps, generator, dtype) -> controls`` drawing the per-step
            inputs the model needs for in-family simulation (``None``: it needs none).
        name: a label for reports.
    """

    layout: StateLayout
    learn: tuple[str, ...]
    initial_mean: tuple[float, ...] | None = None
    initial_var: tuple[float, ...] | None = None
    reference: Mapping[str, Any] = field(default_factory=dict)
    controls: Callable[..., Any] | None = None
    name: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.layout, StateLayout):
            raise TypeError(f"layout must be a StateLayout, got {type(self.layout).__name__}")
        object.__setattr__(self, "learn", tuple(str(v) for v in self.learn))
        n = self.layout.dim
        for key in ("initial_mean", "initial_var"):
            value = getattr(self, key)
            if value is None:
                continue
            vals = tuple(float(v) for v in value)
            if len(vals) != n or not all(math.isfinite(v) for v in vals):
                raise ValueError(f"{key} must hold {n} finite values (one per state component), got {list(value)}")
            object.__setattr__(self, key, vals)
        if self.initial_var is not None and min(self.initial_var) <= 0:
            raise ValueError(f"initial_var must be positive, got {list(self.initial_var)}")
        if (self.initial_mean is None) != (self.initial_var is None):
            raise ValueError("give both initial_mean and initial_var or neither")
        if self.controls is not None and not callable(self.controls):
            raise TypeError(f"controls must be a callable (batch_size, num_steps, generator, dtype) -> controls, got {type(self.controls)}")
        object.__setattr__(self, "reference", dict(self.reference or {}))


def describe(
    model: nn.Module,
    *,
    layout: StateLayout,
    learn: Sequence[str],
    initial_mean: Sequence[float] | None = None,
    initial_var: Sequence[float] | None = None,
    reference: Mapping[str, Any] | None = None,
    controls: Callable[..., Any] | None = None,
    name: str | None = None,
) -> nn.Module:
    """Attach :class:`ModelDefaults` to ``model`` (as ``model.defaults``) and return it."""
    state_dim = getattr(model, "state_dim", None)
    if state_dim is not None and int(state_dim) != layout.dim:
        raise ValueError(f"the layout has {layout.dim} components but the model's state has {int(state_dim)}")
    model.defaults = ModelDefaults(
        layout=layout,
        learn=tuple(learn),
        initial_mean=None if initial_mean is None else tuple(initial_mean),
        initial_var=None if initial_var is None else tuple(initial_var),
        reference=dict(reference or {}),
        controls=controls,
        name=name,
    )
    return model


def model_defaults(obj: Any) -> ModelDefaults | None:
    """The :class:`ModelDefaults` of a model, or of the model inside a filter (``.model``) or a
    mixer (its first mode, ``.filters[0]``); ``None`` when there are none."""
    seen = 0
    while obj is not None and seen < 8:
        found = getattr(obj, "defaults", None)
        if isinstance(found, ModelDefaults):
            return found
        inner = getattr(obj, "model", None)
        if inner is None:
            modes = getattr(obj, "filters", None)
            inner = modes[0] if modes is not None and len(modes) else None
        obj, seen = inner, seen + 1
    return None
