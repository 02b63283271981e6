"""Constrained learnable parameters.

Every learnable quantity in difffilter is an unconstrained ``nn.Parameter`` (the *raw* value)
mapped to its constrained value by a parametrization registered with
:mod:`torch.nn.utils.parametrize`.  Users read and write constrained values
(``model.R = torch.eye(2)``); the optimiser sees only the raw tensor
(``model.parametrizations.R.original``).

The constraint maps live in :mod:`difffilter.constraints` (re-exported here); this module
registers them, validates covariances and builds the noise-covariance structures.  Design
rules shared by all constraints:

* ``forward(raw)`` is finite with finite gradients, and inside its documented set (open
  intervals strictly inside, positive-definite matrices with a bounded condition number), for
  every raw entry in ``[-50, 50]`` in float32 and float64.
* ``right_inverse(value)`` is the exact inverse on the constraint set, so ``set -> get``
  round-trips to rounding error (1e-12 in float64); a value outside the set, non-finite, of
  another shape or dtype is refused with an error naming the parameter.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from .constraints import (
    Bounded,
    Constraint,
    FactorCovariance,
    Interval,
    Positive,
    PositiveDefinite,
    RowStochastic,
    pd_nugget,
    softplus,
    softplus_inverse,
)

__all__ = [
    "Bounded",
    "Constraint",
    "FactorCovariance",
    "Interval",
    "Positive",
    "PositiveDefinite",
    "RowStochastic",
    "register_constrained",
    "remove_constrained",
    "softplus",
    "softplus_inverse",
    "ScaledMatrix",
    "GroupScaledCovariance",
    "check_covariance",
    "numerical_rank",
    "auto_structure",
    "register_covariance",
    "constrained_values",
]


Structure = Literal["full", "diagonal", "scalar", "factor", "fixed"]


def register_constrained(module: nn.Module, name: str, value: Tensor, constraint: nn.Module | None) -> None:
    """Register ``module.<name>`` as a constrained learnable parameter with initial ``value``.

    ``constraint=None`` registers a fixed buffer instead (not learnable).

    ``copy.deepcopy`` shares a parametrized module's generated class between the module and its
    copies; registering (and re-registering, via :func:`remove_constrained`) gives ``module`` a
    private class first, so deep copies (e.g. the hand-tuned filter a learner's copy was made
    from) neither lose nor gain properties.
    """
    remove_constrained(module, name)
    if hasattr(module, name):
        delattr(module, name)
    if constraint is None:
        module.register_buffer(name, value.detach().clone())
        return
    if isinstance(constraint, Constraint):
        constraint.name = name
        constraint.check(value)
        constraint.value_shape = tuple(value.shape) if constraint.value_shape is None else constraint.value_shape
        constraint.value_dtype = value.dtype
    module.register_parameter(name, nn.Parameter(value.detach().clone()))
    _own_class(module)  # the new property must not appear on deep copies that share the class
    parametrize.register_parametrization(module, name, constraint, unsafe=True)


def remove_constrained(module: nn.Module, name: str) -> None:
    """Remove the parametrization of ``module.<name>`` and the attribute, if there is one.

    ``module`` first gets a private copy of its generated class: ``copy.deepcopy`` shares that
    class between a module and its copies, and ``remove_parametrizations`` deletes the property
    from the class, which would break the copies that still have the parametrization.
    """
    if not parametrize.is_parametrized(module, name):
        return
    _own_class(module)
    parametrize.remove_parametrizations(module, name, leave_parametrized=False)
    delattr(module, name)  # the raw value that remove_parametrizations leaves behind


def _own_class(module: nn.Module) -> None:
    """Give a parametrized ``module`` a private copy of its generated class (same bases, same
    properties), so that adding or removing a parametrization's property touches it alone."""
    if parametrize.is_parametrized(module):
        cls = type(module)
        module.__class__ = type(cls.__name__, cls.__bases__, dict(cls.__dict__))


def constrained_values(module: nn.Module, prefix: str = "") -> dict[str, Tensor]:
    """All constrained parameters below ``module``: ``{dotted.name: constrained value}``."""
    out: dict[str, Tensor] = {}
    for mod_name, mod in module.named_modules(prefix=prefix):
        if parametrize.is_parametrized(mod):
            for pname in mod.parametrizations.keys():
                full = f"{mod_name}.{pname}" if mod_name else pname
                out[full] = getattr(mod, pname).detach()
    return out


class ScaledMatrix(Constraint):
    """``value = scale * base`` with a learnable positive scalar ``scale`` and fixed ``base``.

    Used for noise covariances whose shape is known and whose level is tuned (the per-mode Q/R
    scales of p003); ``base`` may be semi-definite.  ``right_inverse`` accepts any positive
    multiple of ``base``, or the scale itself (a scalar).
    """

    accepts_scalar = True
    base: Tensor
    _scale: Positive

    def __init__(self, base: Tensor, floor: float = 0.0) -> None:
        super().__init__()
        self.register_buffer("base", base.detach().clone())
        self._scale = Positive(floor)
        self.value_shape = tuple(base.shape)

    def forward(self, raw: Tensor) -> Tensor:
        scale: Tensor = self._scale(raw)
        return scale * self.base

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        self._scale.name = f"{self.name}'s scale"
        if value.ndim == 0:
            return self._scale.right_inverse(value)
        idx = self.base.abs().argmax()
        scale = value.flatten()[idx] / self.base.flatten()[idx]
        if not torch.allclose(value, scale * self.base, rtol=1e-6, atol=0.0):
            raise ValueError(f"{self.name} must be a positive multiple of its base matrix (structure 'scalar')")
        return self._scale.right_inverse(scale)


class GroupScaledCovariance(Constraint):
    """``value = D base D`` with ``D = diag(sqrt(exp(raw) @ groups))``: one positive scale per
    group of state components, learned in log space (a constraint for ``register_constrained``).

    ``groups [G, n]`` is a 0/1 partition of the ``n`` components; ``raw [G]`` are the log scales
    relative to ``base`` (``raw = 0``: ``value = base``).  Log space matters for scales that
    must move by orders of magnitude: Adam moves a raw value by about ``lr`` per step, which in
    softplus space (``Positive``) changes a scale of ``1e4`` by ``lr`` and in log space by a
    factor ``exp(lr)``.  ``right_inverse`` takes a scalar (every group) or a matrix of this form.
    """

    accepts_scalar = True
    base: Tensor
    groups: Tensor

    def __init__(self, base: Tensor, groups: Tensor) -> None:
        super().__init__()
        n = base.shape[-1]
        g = torch.as_tensor(groups, dtype=base.dtype)
        if g.ndim != 2 or g.shape[1] != n:
            raise ValueError(f"groups must be [G, {n}] (one 0/1 row per group), got {tuple(g.shape)}")
        if not bool(((g == 0) | (g == 1)).all()) or not bool((g.sum(0) == 1).all()):
            raise ValueError("groups must put every component in exactly one group (0/1 rows summing to 1 per column)")
        self.register_buffer("base", base.detach().clone())
        self.register_buffer("groups", g)
        self.value_shape = tuple(base.shape)

    def forward(self, raw: Tensor) -> Tensor:
        d = torch.sqrt(torch.exp(raw) @ self.groups)
        return d[:, None] * self.base * d[None, :]

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(torch.as_tensor(value, dtype=self.base.dtype))
        if value.ndim == 0:
            if not float(value) > 0.0:
                raise ValueError(f"{self.name}: a group scale must be positive, got {float(value)}")
            return torch.full((self.groups.shape[0],), float(torch.log(value)), dtype=self.base.dtype)
        ratio = torch.diagonal(value) / torch.diagonal(self.base)
        scales = (self.groups * ratio).sum(1) / self.groups.sum(1)
        raw = torch.log(scales)
        if not torch.allclose(self.forward(raw), value, rtol=1e-6, atol=0.0):
            raise ValueError(f"{self.name} must be the base covariance with one positive scale per group")
        return raw


def numerical_rank(value: Tensor) -> int:
    """Rank of a symmetric ``[n, n]`` matrix: eigenvalues above ``64 n eps`` times the largest."""
    lam = torch.linalg.eigvalsh(0.5 * (value + value.mT))
    tol = 64 * value.shape[-1] * torch.finfo(value.dtype).eps * lam.abs().amax()
    return int((lam > tol).sum())


def check_covariance(name: str, value: Tensor, n: int | None = None, *, batch_ok: bool = False, semidefinite: bool = False) -> Tensor:
    """Validate a user-given covariance: square ``[n, n]`` (or ``[..., n, n]`` if ``batch_ok``),
    finite, symmetric and positive definite (``semidefinite``: positive semi-definite, to a
    relative tolerance of ``64 n eps`` on the eigenvalues).  Raises ``TypeError``/``ValueError``
    naming ``name`` (and, for a batch, the failing batch elements)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if not value.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {value.dtype}")
    shape = tuple(value.shape)
    want = f"[{n}, {n}]" if n is not None else "[n, n]"
    if value.ndim < 2 or (value.ndim != 2 and not batch_ok) or shape[-1] != shape[-2]:
        raise ValueError(f"{name} must be a square matrix {want}{' (or batched)' if batch_ok else ''}, got shape {shape}")
    if n is not None and shape[-1] != n:
        raise ValueError(f"{name} must have shape {want}, got {shape}")

    def where(bad: Tensor) -> str:
        return f" (batch elements {bad.nonzero().flatten().tolist()[:10]})" if bad.ndim > 0 else ""

    flat = value.flatten(-2)
    bad = ~torch.isfinite(flat).all(-1)
    if bool(bad.any()):
        raise ValueError(f"{name} contains non-finite entries{where(bad)}")
    scale = flat.abs().amax(-1).clamp_min(torch.finfo(value.dtype).tiny)
    bad = ~((value - value.mT).abs().flatten(-2) <= 1e-6 * scale[..., None]).all(-1)
    if bool(bad.any()):
        raise ValueError(f"{name} must be symmetric{where(bad)}")
    sym = 0.5 * (value + value.mT)
    if semidefinite:
        lam = torch.linalg.eigvalsh(sym)
        bad = (lam < -64 * shape[-1] * torch.finfo(value.dtype).eps * lam.abs().amax(-1, keepdim=True)).any(-1)
        if bool(bad.any()):
            raise ValueError(f"{name} must be positive semi-definite{where(bad)}, got eigenvalues down to {float(lam.min()):.3g}")
        return value
    bad = torch.linalg.cholesky_ex(sym)[1] != 0
    if bool(bad.any()):
        raise ValueError(f"{name} must be positive definite{where(bad)}")
    return value


def auto_structure(value: Tensor, *, floor: float = 0.0) -> str:
    """The structure ``"auto"`` gives a covariance ``value [n, n]``: ``"full"`` when the
    log-Cholesky parametrisation holds it; else ``"scalar"`` when a variance lies at or below the
    variance floor of the learnable structures (``sqrt(tiny)`` of the dtype, 1.1e-19 in float32,
    1.5e-154 in float64), which a learnable multiple of the matrix still represents exactly; else
    ``"factor"`` (a semi-definite matrix, held exactly as ``L L^T`` of its numerical rank)."""
    try:
        PositiveDefinite(floor=floor).right_inverse(value)
        return "full"
    except ValueError:
        pass
    tiny = pd_nugget(value.shape[-1], value.dtype)[1]
    diag = torch.diagonal(value, dim1=-2, dim2=-1)
    return "scalar" if bool(((diag > 0) & (diag <= 2 * tiny)).any()) else "factor"


def register_covariance(
    module: nn.Module, name: str, value: Tensor, structure: str = "full", *, floor: float = 0.0, rank: int | None = None
) -> None:
    """Register a noise covariance ``module.<name>`` with a learnable structure.

    ``structure``: ``"full"`` (log-Cholesky :class:`PositiveDefinite`, bounded condition
    number), ``"diagonal"``, ``"scalar"`` (learnable positive multiple of the given matrix, which
    may be semi-definite), ``"factor"`` (:class:`FactorCovariance`, ``value = L L^T`` with a free
    ``L [n, rank]``, for semi-definite covariances; ``rank`` defaults to the value's numerical
    rank), ``"fixed"`` (buffer, semi-definite allowed) or ``"auto"`` (:func:`auto_structure`:
    ``"full"`` where it can hold the value, else ``"factor"`` for a semi-definite one, such as
    the textbook white-noise-acceleration ``Q``, or ``"scalar"`` for variances below the
    dtype's variance floor, such as ``R = 1e-20 I`` in float32).
    """
    if structure == "auto":
        structure = auto_structure(value, floor=floor)
    if structure == "full":
        constraint: nn.Module | None = PositiveDefinite(floor=floor)
    elif structure == "diagonal":
        constraint = PositiveDefinite(diagonal=True, floor=floor)
    elif structure == "scalar":
        constraint = ScaledMatrix(value, floor=floor)
        value = torch.ones((), dtype=value.dtype, device=value.device)
    elif structure == "factor":
        constraint = FactorCovariance(max(1, numerical_rank(value)) if rank is None else rank)
    elif structure == "fixed":
        constraint = None
    else:
        raise ValueError(f"{name}_structure must be 'auto', 'full', 'diagonal', 'scalar', 'factor' or 'fixed', got {structure!r}")
    register_constrained(module, name, value, constraint)
