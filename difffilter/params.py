"""Constrained learnable parameters.

Every learnable quantity in difffilter is an unconstrained ``nn.Parameter`` (the *raw* value)
mapped to its constrained value by a parametrization registered with
:mod:`torch.nn.utils.parametrize`.  Users read and write constrained values
(``model.R = torch.eye(2)``); the optimiser sees only the raw tensor
(``model.parametrizations.R.original``).

Design rules shared by all constraints:

* ``forward(raw)`` is finite with finite gradients for every raw entry in ``[-50, 50]`` in
  float32 and float64 (softplus/sigmoid rather than ``exp`` where overflow could occur).
* ``right_inverse(value)`` is the exact inverse on the constraint set, so ``set -> get``
  round-trips to rounding error (1e-12 in float64).
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

__all__ = [
    "Bounded",
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
    "register_covariance",
    "constrained_values",
]


def softplus(x: Tensor) -> Tensor:
    """``log(1 + exp(x))``; exact to rounding up to ``x = 40`` (``nn.functional.softplus`` turns
    linear at 20, an error of 2e-9 that breaks exact set/get round trips), linear beyond."""
    return nn.functional.softplus(x, beta=1.0, threshold=40.0)


def softplus_inverse(y: Tensor) -> Tensor:
    """Inverse of ``softplus`` for ``y > 0``: ``log(expm1(y))`` written to avoid overflow."""
    return y + torch.log(-torch.expm1(-y))


class Positive(nn.Module):
    """``value = floor + softplus(raw)``: positive scalars or vectors with a lower bound."""

    def __init__(self, floor: float = 0.0) -> None:
        super().__init__()
        if floor < 0:
            raise ValueError(f"floor must be >= 0, got {floor}")
        self.floor = float(floor)

    def forward(self, raw: Tensor) -> Tensor:
        return self.floor + softplus(raw)

    def right_inverse(self, value: Tensor) -> Tensor:
        if not bool((value > self.floor).all()):
            raise ValueError(f"Positive parameter must exceed its floor {self.floor}, got {value}")
        return softplus_inverse(value - self.floor)


class Bounded(nn.Module):
    """``value = lower + (upper - lower) * sigmoid(raw)``: an open interval ``(lower, upper)``.

    Used for AR coefficients ``Psi`` in ``(-1, 1)``, blend weights ``delta`` in ``[0, 1]`` and
    forgetting factors ``rho`` in ``(0, 1]``.
    """

    def __init__(self, lower: float, upper: float) -> None:
        super().__init__()
        if not upper > lower:
            raise ValueError(f"upper must exceed lower, got ({lower}, {upper})")
        self.lower, self.upper = float(lower), float(upper)

    def forward(self, raw: Tensor) -> Tensor:
        return self.lower + (self.upper - self.lower) * torch.sigmoid(raw)

    def right_inverse(self, value: Tensor) -> Tensor:
        u = (value - self.lower) / (self.upper - self.lower)
        if not bool(((u >= 0) & (u <= 1)).all()):
            raise ValueError(f"Bounded parameter must lie in [{self.lower}, {self.upper}], got {value}")
        # Values on the boundary map to a large but finite raw value.
        u = u.clamp(1e-15, 1 - 1e-15) if value.dtype == torch.float64 else u.clamp(1e-7, 1 - 1e-7)
        return torch.logit(u)


class Interval(nn.Module):
    """Scale parameter in ``[lower, upper]``, interpolated in log space by default.

    ``value = exp(log lower + (log upper - log lower) * sigmoid(raw))``: suited to time constants
    spanning decades (the Singer tau in ``[0.1 s, 1e4 s]``).  ``log_scale=False`` gives a linear
    interval (same as :class:`Bounded`).
    """

    def __init__(self, lower: float, upper: float, *, log_scale: bool = True) -> None:
        super().__init__()
        if not upper > lower:
            raise ValueError(f"upper must exceed lower, got ({lower}, {upper})")
        if log_scale and lower <= 0:
            raise ValueError("a log-scale Interval needs lower > 0")
        self.log_scale = log_scale
        self.lower, self.upper = float(lower), float(upper)
        if log_scale:
            self._inner = Bounded(math.log(lower), math.log(upper))
        else:
            self._inner = Bounded(lower, upper)

    def forward(self, raw: Tensor) -> Tensor:
        v = self._inner(raw)
        if not self.log_scale:
            return v
        # exp(log(upper)) can round past upper (float32): keep the documented bounds exact
        return torch.clamp(torch.exp(v), self.lower, self.upper)

    def right_inverse(self, value: Tensor) -> Tensor:
        if not bool(((value >= self.lower) & (value <= self.upper)).all()):
            raise ValueError(f"Interval parameter must lie in [{self.lower}, {self.upper}], got {value}")
        return self._inner.right_inverse(torch.log(value) if self.log_scale else value)


class PositiveDefinite(nn.Module):
    """Symmetric positive-definite matrices ``[..., n, n]`` through a Cholesky factor.

    ``raw`` is a square matrix whose strict lower triangle is the factor's off-diagonal and
    whose diagonal ``d`` gives the factor's diagonal ``floor + softplus(d)`` (a "log-Cholesky"
    variant that cannot overflow).  ``diagonal=True`` takes a raw vector ``[..., n]`` and returns
    ``diag((floor + softplus(raw))**2)``.
    """

    def __init__(self, *, diagonal: bool = False, floor: float = 0.0) -> None:
        super().__init__()
        self.diagonal = diagonal
        self.floor = float(floor)

    def forward(self, raw: Tensor) -> Tensor:
        if self.diagonal:
            d = self.floor + softplus(raw)
            return torch.diag_embed(d * d)
        d = self.floor + softplus(torch.diagonal(raw, dim1=-2, dim2=-1))
        chol = torch.tril(raw, -1) + torch.diag_embed(d)
        return chol @ chol.mT

    def right_inverse(self, value: Tensor) -> Tensor:
        if value.ndim < 2 or value.shape[-1] != value.shape[-2]:
            raise ValueError(f"PositiveDefinite value must be [..., n, n], got {tuple(value.shape)}")
        if self.diagonal:
            off = value - torch.diag_embed(torch.diagonal(value, dim1=-2, dim2=-1))
            if bool((off != 0).any()):
                raise ValueError("a diagonal PositiveDefinite parameter needs a diagonal matrix")
            sd = torch.sqrt(torch.diagonal(value, dim1=-2, dim2=-1))
            if not bool((sd > self.floor).all()):
                raise ValueError(f"diagonal entries must exceed floor**2 = {self.floor**2}")
            return softplus_inverse(sd - self.floor)
        chol, info = torch.linalg.cholesky_ex(0.5 * (value + value.mT))
        if bool((info != 0).any()) or not bool(torch.isfinite(chol).all()):
            raise ValueError("PositiveDefinite value is not symmetric positive definite")
        d = torch.diagonal(chol, dim1=-2, dim2=-1)
        if not bool((d > self.floor).all()):
            raise ValueError(f"Cholesky diagonal must exceed floor {self.floor}")
        return torch.tril(chol, -1) + torch.diag_embed(softplus_inverse(d - self.floor))


class RowStochastic(nn.Module):
    """Row-stochastic matrices ``[..., M, M]`` (or probability vectors ``[..., M]``).

    ``value = floor + (1 - M * floor) * softmax(raw, -1)``: every entry is at least ``floor``
    and rows sum to one.  Transition matrices follow ``Pi[i, j] = P(j | i)``.
    """

    def __init__(self, floor: float = 1e-6) -> None:
        super().__init__()
        if floor < 0:
            raise ValueError(f"floor must be >= 0, got {floor}")
        self.floor = float(floor)

    def forward(self, raw: Tensor) -> Tensor:
        m = raw.shape[-1]
        return self.floor + (1.0 - m * self.floor) * torch.softmax(raw, dim=-1)

    def log_value(self, raw: Tensor) -> Tensor:
        """``log(forward(raw))`` computed stably (used by the IMM's log-space recursion)."""
        m = raw.shape[-1]
        logp = torch.log_softmax(raw, dim=-1) + math.log1p(-m * self.floor)
        if self.floor == 0:
            return logp
        return torch.logaddexp(logp, torch.full_like(logp, math.log(self.floor)))

    def right_inverse(self, value: Tensor) -> Tensor:
        m = value.shape[-1]
        if m * self.floor >= 1:
            raise ValueError(f"floor {self.floor} too large for {m} categories")
        if not torch.allclose(value.sum(-1), torch.ones((), dtype=value.dtype), atol=1e-6):
            raise ValueError("RowStochastic rows must sum to 1")
        if not bool((value >= self.floor).all()):
            raise ValueError(f"RowStochastic entries must be >= floor {self.floor}")
        p = (value - self.floor) / (1.0 - m * self.floor)
        logp = torch.log(p.clamp_min(torch.finfo(value.dtype).tiny))
        return logp - logp.mean(-1, keepdim=True)


Structure = Literal["full", "diagonal", "scalar", "fixed"]


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
            for pname in mod.parametrizations.keys():  # type: ignore[union-attr]
                full = f"{mod_name}.{pname}" if mod_name else pname
                out[full] = getattr(mod, pname).detach()
    return out


class ScaledMatrix(nn.Module):
    """``value = scale * base`` with a learnable positive scalar ``scale`` and fixed ``base``.

    Used for noise covariances whose shape is known and whose level is tuned (the per-mode Q/R
    scales of p003).  ``right_inverse`` accepts any positive multiple of ``base``.
    """

    def __init__(self, base: Tensor, floor: float = 0.0) -> None:
        super().__init__()
        self.register_buffer("base", base.detach().clone())
        self._scale = Positive(floor)

    def forward(self, raw: Tensor) -> Tensor:
        return self._scale(raw) * self.base

    def right_inverse(self, value: Tensor) -> Tensor:
        if value.ndim == 0:
            return self._scale.right_inverse(value)
        idx = self.base.abs().argmax()
        scale = value.flatten()[idx] / self.base.flatten()[idx]
        if not torch.allclose(value, scale * self.base, rtol=1e-6, atol=0.0):
            raise ValueError("ScaledMatrix value must be a positive multiple of its base matrix")
        return self._scale.right_inverse(scale)


class GroupScaledCovariance(nn.Module):
    """``value = D base D`` with ``D = diag(sqrt(exp(raw) @ groups))``: one positive scale per
    group of state components, learned in log space (a constraint for ``register_constrained``).

    ``groups [G, n]`` is a 0/1 partition of the ``n`` components; ``raw [G]`` are the log scales
    relative to ``base`` (``raw = 0``: ``value = base``).  Log space matters for scales that
    must move by orders of magnitude: Adam moves a raw value by about ``lr`` per step, which in
    softplus space (``Positive``) changes a scale of ``1e4`` by ``lr`` and in log space by a
    factor ``exp(lr)``.  ``right_inverse`` takes a scalar (every group) or a matrix of this form.
    """

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

    def forward(self, raw: Tensor) -> Tensor:
        d = torch.sqrt(torch.exp(raw) @ self.groups)
        return d[:, None] * self.base * d[None, :]

    def right_inverse(self, value: Tensor) -> Tensor:
        value = torch.as_tensor(value, dtype=self.base.dtype)
        if value.ndim == 0:
            if not float(value) > 0.0:
                raise ValueError(f"a group scale must be positive, got {float(value)}")
            return torch.full((self.groups.shape[0],), math.log(float(value)), dtype=self.base.dtype)
        ratio = torch.diagonal(value) / torch.diagonal(self.base)
        scales = (self.groups * ratio).sum(1) / self.groups.sum(1)
        raw = torch.log(scales)
        if not torch.allclose(self.forward(raw), value, rtol=1e-6, atol=0.0):
            raise ValueError("value must be the base covariance with one positive scale per group")
        return raw


def check_covariance(name: str, value: Tensor, n: int | None = None, *, batch_ok: bool = False) -> Tensor:
    """Validate a user-given covariance: square ``[n, n]`` (or ``[..., n, n]`` if ``batch_ok``),
    finite, symmetric and positive definite.  Raises ``ValueError`` naming ``name``."""
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
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains non-finite entries")
    scale = value.abs().amax().clamp_min(torch.finfo(value.dtype).tiny)
    if not bool(((value - value.mT).abs() <= 1e-6 * scale).all()):
        raise ValueError(f"{name} must be symmetric")
    _, info = torch.linalg.cholesky_ex(0.5 * (value + value.mT))
    if bool((info != 0).any()):
        raise ValueError(f"{name} must be positive definite")
    return value


def register_covariance(module: nn.Module, name: str, value: Tensor, structure: str = "full", *, floor: float = 0.0) -> None:
    """Register a noise covariance ``module.<name>`` with a learnable structure.

    ``structure``: ``"full"`` (log-Cholesky :class:`PositiveDefinite`), ``"diagonal"``,
    ``"scalar"`` (learnable positive multiple of the given matrix) or ``"fixed"`` (buffer).
    """
    if structure == "full":
        constraint: nn.Module | None = PositiveDefinite(floor=floor)
    elif structure == "diagonal":
        constraint = PositiveDefinite(diagonal=True, floor=floor)
    elif structure == "scalar":
        constraint = ScaledMatrix(value, floor=floor)
        value = torch.ones((), dtype=value.dtype, device=value.device)
    elif structure == "fixed":
        constraint = None
    else:
        raise ValueError(f"structure must be 'full', 'diagonal', 'scalar' or 'fixed', got {structure!r}")
    try:
        register_constrained(module, name, value, constraint)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from exc
