"""Constraint maps from unconstrained raw tensors to constrained values (and back).

Each constraint is an ``nn.Module`` with ``forward(raw) -> value`` and
``right_inverse(value) -> raw``, registered on a module by
:func:`difffilter.params.register_constrained` (which also tells it the attribute's name, shape
and dtype, so that a bad assignment ``model.Q = ...`` is refused in the user's terms).

Contracts, for every raw entry in ``[-50, 50]`` in float32 and float64:

* ``forward`` is finite with finite gradients and lies in the documented set: open intervals
  stay strictly inside their bounds (the value is clamped to the neighbouring representable
  numbers), positive-definite matrices have a bounded condition number of their correlation
  matrix (a relative nugget ``16 n eps`` on the diagonal, :class:`PositiveDefinite`), so that
  their Cholesky factorisation succeeds;
* ``right_inverse`` is the exact inverse on the constraint set (``set -> get`` round-trips to
  rounding), validates the value first (finite, shape, dtype, in the set) and raises
  ``ValueError``/``TypeError`` naming the parameter.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

__all__ = [
    "Bounded",
    "Constraint",
    "FactorCovariance",
    "Interval",
    "Positive",
    "PositiveDefinite",
    "RowStochastic",
    "pd_nugget",
    "softplus",
    "softplus_inverse",
]


def softplus(x: Tensor) -> Tensor:
    """``log(1 + exp(x))``; exact to rounding up to ``x = 40`` (``nn.functional.softplus`` turns
    linear at 20, an error of 2e-9 that breaks exact set/get round trips), linear beyond."""
    return nn.functional.softplus(x, beta=1.0, threshold=40.0)


def softplus_inverse(y: Tensor) -> Tensor:
    """Inverse of ``softplus`` for ``y > 0``: ``log(expm1(y))`` written to avoid overflow."""
    return y + torch.log(-torch.expm1(-y))


#: Relative size of the nugget that bounds the condition number of :class:`PositiveDefinite`.
_NUGGET = 16.0


def pd_nugget(n: int, dtype: torch.dtype) -> tuple[float, float]:
    """``(delta, floor)`` of :class:`PositiveDefinite`: ``value = A + delta diag(A) + floor I`` with
    ``delta = 16 n eps`` (the correlation matrix's smallest eigenvalue is then at least
    ``delta / (1 + delta)``, its condition number at most ``n (1 + delta) / delta``, far inside
    what Cholesky factorises: ``1.6e4`` in float32 and ``3e12`` in float64 for ``n = 4``,
    whatever the units of the components) and ``floor = sqrt(tiny)`` against underflow.  An
    ordinary covariance moves by ``delta`` relative: ``7e-14`` in float64 for ``n = 20``."""
    fi = torch.finfo(dtype)
    return _NUGGET * n * fi.eps, fi.tiny**0.5


class Constraint(nn.Module):
    """Base class: the parameter's name, value shape and dtype for clear errors on assignment.

    :func:`~difffilter.params.register_constrained` sets ``name``, ``value_shape`` and
    ``value_dtype``; :meth:`check` validates a value against them (finite, floating point, same
    dtype, same shape, or a scalar where :attr:`accepts_scalar`).
    """

    accepts_scalar = False

    def __init__(self) -> None:
        super().__init__()
        self.name = "parameter"
        self.value_shape: tuple[int, ...] | None = None
        self.value_dtype: torch.dtype | None = None

    def check(self, value: Tensor) -> Tensor:
        if not isinstance(value, Tensor):
            raise TypeError(f"{self.name} must be a torch.Tensor, got {type(value).__name__}")
        if not value.is_floating_point():
            raise TypeError(f"{self.name} must be a floating-point tensor, got {value.dtype}")
        if self.value_dtype is not None and value.dtype != self.value_dtype:
            raise TypeError(f"{self.name} must have dtype {self.value_dtype} like the parameter it replaces, got {value.dtype}")
        shape = tuple(value.shape)
        if self.value_shape is not None and shape != self.value_shape and not (self.accepts_scalar and value.ndim == 0):
            raise ValueError(f"{self.name} must have shape {list(self.value_shape)}, got {list(shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{self.name} must be finite, got {_show(value)}")
        return value


def _floor_hint(name: str, dtype: torch.dtype, tiny: float) -> str:
    """Why a tiny variance is refused and what holds it instead."""
    return (
        f": {tiny:.3g} is the variance floor of a learnable covariance in {dtype} (sqrt of its smallest normal number, added "
        f"so that every learned value factorises); pass {name}_structure='scalar' (a learnable multiple of the given matrix, "
        f"what 'auto' picks) or 'fixed', or compute in float64"
    )


def _show(value: Tensor) -> str:
    return str(value.detach().cpu().tolist()) if value.numel() <= 16 else f"a tensor of shape {list(value.shape)}"


class Positive(Constraint):
    """``value = floor + softplus(raw)``: positive scalars or vectors with a lower bound."""

    def __init__(self, floor: float = 0.0) -> None:
        super().__init__()
        if not floor >= 0 or not math.isfinite(floor):
            raise ValueError(f"floor must be finite and >= 0, got {floor}")
        self.floor = float(floor)

    def forward(self, raw: Tensor) -> Tensor:
        return self.floor + softplus(raw)

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        if not bool((value > self.floor).all()):
            raise ValueError(f"{self.name} must exceed {self.floor}, got {_show(value)}")
        return softplus_inverse(value - self.floor)


def _inside(value: Tensor, lower: float, upper: float) -> Tensor:
    """``value`` clamped to the representable numbers strictly between ``lower`` and ``upper``."""
    lo = torch.tensor(lower, dtype=value.dtype, device=value.device)
    hi = torch.tensor(upper, dtype=value.dtype, device=value.device)
    return torch.clamp(value, torch.nextafter(lo, hi), torch.nextafter(hi, lo))


def _logit_inside(u: Tensor, dtype: torch.dtype) -> Tensor:
    """``logit(u)`` for ``u`` in ``[0, 1]`` (float64), the bounds mapped to large finite raw values."""
    tiny = 1e-15 if dtype == torch.float64 else 1e-7
    return torch.logit(u.clamp(tiny, 1.0 - tiny)).to(dtype)


class Bounded(Constraint):
    """``value = lower + (upper - lower) * sigmoid(raw)``, kept strictly inside ``(lower, upper)``.

    Used for AR coefficients ``Psi`` in ``(-1, 1)``, blend weights ``delta`` and forgetting
    factors ``rho``.  ``right_inverse`` accepts the closed interval (``rho = 1``, ``delta = 0``);
    a bound maps to the nearest representable value inside it.
    """

    def __init__(self, lower: float, upper: float) -> None:
        super().__init__()
        if not (math.isfinite(lower) and math.isfinite(upper) and upper > lower):
            raise ValueError(f"Bounded needs finite bounds with upper > lower, got ({lower}, {upper})")
        self.lower, self.upper = float(lower), float(upper)

    def forward(self, raw: Tensor) -> Tensor:
        return _inside(self.lower + (self.upper - self.lower) * torch.sigmoid(raw), self.lower, self.upper)

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        u = (value.double() - self.lower) / (self.upper - self.lower)
        if not bool(((u >= 0) & (u <= 1)).all()):
            raise ValueError(f"{self.name} must lie in [{self.lower}, {self.upper}], got {_show(value)}")
        return _logit_inside(u, value.dtype)


class Interval(Constraint):
    """Scale parameter in ``[lower, upper]``, interpolated in log space by default.

    ``value = exp(log lower + (log upper - log lower) * sigmoid(raw))``, clamped to the bounds:
    suited to time constants spanning decades (the Singer tau in ``[0.1 s, 1e4 s]``).
    ``log_scale=False`` interpolates linearly.  ``right_inverse`` accepts the closed interval,
    its bounds compared in the value's dtype (so ``float32(0.7)``, below ``0.7``, is accepted
    for ``lower = 0.7``).
    """

    def __init__(self, lower: float, upper: float, *, log_scale: bool = True) -> None:
        super().__init__()
        if not (math.isfinite(lower) and math.isfinite(upper) and upper > lower):
            raise ValueError(f"Interval needs finite bounds with upper > lower, got ({lower}, {upper})")
        if log_scale and lower <= 0:
            raise ValueError(f"a log-scale Interval needs lower > 0, got {lower}")
        self.log_scale = log_scale
        self.lower, self.upper = float(lower), float(upper)
        self._a, self._b = (math.log(lower), math.log(upper)) if log_scale else (self.lower, self.upper)

    def forward(self, raw: Tensor) -> Tensor:
        v = self._a + (self._b - self._a) * torch.sigmoid(raw)
        # exp(log(upper)) can round past upper (float32): keep the documented bounds exact
        return torch.clamp(torch.exp(v) if self.log_scale else v, self.lower, self.upper)

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        lo = torch.tensor(self.lower, dtype=value.dtype).double()
        hi = torch.tensor(self.upper, dtype=value.dtype).double()
        v = value.double()
        if not bool(((v >= lo) & (v <= hi)).all()):
            raise ValueError(f"{self.name} must lie in [{self.lower:g}, {self.upper:g}], got {_show(value)}")
        v = v.clamp(self.lower, self.upper)
        u = ((torch.log(v) if self.log_scale else v) - self._a) / (self._b - self._a)
        return _logit_inside(u, value.dtype)


class PositiveDefinite(Constraint):
    """Symmetric positive-definite matrices ``[..., n, n]`` whose Cholesky factorisation succeeds.

    ``raw`` is a square matrix whose strict lower triangle is the off-diagonal of a Cholesky
    factor ``L`` and whose diagonal ``d`` gives ``L``'s diagonal ``floor + softplus(d)`` (a
    "log-Cholesky" variant that cannot overflow); ``value = A + delta diag(A) + t I`` with
    ``A = L L^T``, ``delta = 16 n eps`` and ``t = sqrt(tiny)`` (:func:`pd_nugget`): the
    correlation matrix's condition number stays below ``n (1 + delta) / delta``, so every raw
    value gives a matrix that factorises, in any units.  ``diagonal=True`` takes a raw vector
    ``[..., n]`` and returns ``diag((floor + softplus(raw))**2 + t)`` (a diagonal factorises
    whenever its entries are positive and normal).  ``right_inverse`` removes the nugget exactly
    and refuses matrices outside this set.
    """

    def __init__(self, *, diagonal: bool = False, floor: float = 0.0) -> None:
        super().__init__()
        if not floor >= 0 or not math.isfinite(floor):
            raise ValueError(f"floor must be finite and >= 0, got {floor}")
        self.diagonal = diagonal
        self.floor = float(floor)

    def forward(self, raw: Tensor) -> Tensor:
        tiny = pd_nugget(1, raw.dtype)[1]
        if self.diagonal:
            d = self.floor + softplus(raw)
            return torch.diag_embed(d * d + tiny)
        d = self.floor + softplus(torch.diagonal(raw, dim1=-2, dim2=-1))
        chol = torch.tril(raw, -1) + torch.diag_embed(d)
        a = chol @ chol.mT
        delta = pd_nugget(a.shape[-1], a.dtype)[0]
        return a + torch.diag_embed(delta * torch.diagonal(a, dim1=-2, dim2=-1) + tiny)

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        if value.ndim < 2 or value.shape[-1] != value.shape[-2]:
            raise ValueError(f"{self.name} must be a square matrix [..., n, n], got shape {list(value.shape)}")
        n = value.shape[-1]
        delta, tiny = pd_nugget(n, value.dtype)
        diag = torch.diagonal(value, dim1=-2, dim2=-1)
        if self.diagonal:
            off = value - torch.diag_embed(diag)
            if bool((off != 0).any()):
                raise ValueError(f"{self.name} must be a diagonal matrix (its structure is diagonal)")
            a = diag - tiny
            if not bool((a > self.floor**2).all()):
                raise ValueError(
                    f"{self.name} must have diagonal entries above {max(self.floor**2, tiny):.3g} for a learnable diagonal "
                    f"covariance, got {_show(diag)}{_floor_hint(self.name, value.dtype, tiny)}"
                )
            return softplus_inverse(torch.sqrt(a) - self.floor)
        scale = value.abs().amax((-2, -1), keepdim=True).clamp_min(torch.finfo(value.dtype).tiny)
        if not bool(((value - value.mT).abs() <= 1e-6 * scale).all()):
            raise ValueError(f"{self.name} must be symmetric")
        # V's off-diagonal entries are A's; its diagonal is (1 + delta) diag(A) + t
        a = 0.5 * (value + value.mT) + torch.diag_embed((diag - tiny) / (1.0 + delta) - diag)
        if not bool((diag > tiny).all()):
            raise ValueError(f"{self.name} has variances {_show(diag)} at or below {tiny:.3g}{_floor_hint(self.name, value.dtype, tiny)}")
        chol, info = torch.linalg.cholesky_ex(a)
        if bool((info != 0).any()) or not bool(torch.isfinite(chol).all()):
            raise ValueError(
                f"{self.name} must be positive definite for {self.name}_structure='full' (log-Cholesky), with correlations away "
                f"from +-1 by more than the nugget 16 n eps; a semi-definite covariance (such as the white-noise-acceleration Q) "
                f"needs {self.name}_structure='factor' (learnable L L^T of its rank, what 'auto' picks), 'scalar' or 'fixed'"
            )
        d = torch.diagonal(chol, dim1=-2, dim2=-1)
        if not bool((d > self.floor).all()):
            raise ValueError(f"{self.name}'s Cholesky diagonal must exceed the floor {self.floor}")
        return torch.tril(chol, -1) + torch.diag_embed(softplus_inverse(d - self.floor))


class FactorCovariance(Constraint):
    """Positive *semi*-definite matrices of rank at most ``rank``: ``value = L L^T`` with a free
    factor ``L [..., n, rank]`` (the raw tensor).

    Represents rank-deficient process noise (a white-noise-acceleration ``Q = q G G^T``) and
    learns it without leaving that set; ``L`` is defined up to an orthogonal factor on the
    right, which does not matter to the value or its gradients.  ``right_inverse`` takes the
    leading ``rank`` eigenpairs and refuses a value of higher numerical rank.
    """

    def __init__(self, rank: int) -> None:
        super().__init__()
        if int(rank) < 1:
            raise ValueError(f"rank must be >= 1, got {rank}")
        self.rank = int(rank)

    def forward(self, raw: Tensor) -> Tensor:
        return raw @ raw.mT

    def right_inverse(self, value: Tensor) -> Tensor:
        value = self.check(value)
        if value.ndim < 2 or value.shape[-1] != value.shape[-2] or value.shape[-1] < self.rank:
            raise ValueError(f"{self.name} must be a square matrix [..., n, n] with n >= rank = {self.rank}, got {list(value.shape)}")
        scale = value.abs().amax().clamp_min(torch.finfo(value.dtype).tiny)
        if not bool(((value - value.mT).abs() <= 1e-6 * scale).all()):
            raise ValueError(f"{self.name} must be symmetric")
        lam, vecs = torch.linalg.eigh(0.5 * (value + value.mT))
        n = value.shape[-1]
        tol = 64 * n * torch.finfo(value.dtype).eps * lam.abs().amax(-1, keepdim=True)
        if bool((lam < -tol).any()):
            raise ValueError(f"{self.name} must be positive semi-definite, got eigenvalues {_show(lam)}")
        if bool((lam[..., : n - self.rank] > tol).any()):
            raise ValueError(f"{self.name} must have rank <= {self.rank}, got eigenvalues {_show(lam)}")
        top = lam[..., n - self.rank :].clamp_min(0.0)
        factor: Tensor = vecs[..., :, n - self.rank :] * torch.sqrt(top)[..., None, :]
        return factor


class RowStochastic(Constraint):
    """Row-stochastic matrices ``[..., M, M]`` (or probability vectors ``[..., M]``).

    ``value = floor + (1 - M * floor) * softmax(raw, -1)``: every entry is at least ``floor``
    and rows sum to one.  Transition matrices follow ``Pi[i, j] = P(j | i)``.
    """

    def __init__(self, floor: float = 1e-6) -> None:
        super().__init__()
        if not floor >= 0 or not math.isfinite(floor):
            raise ValueError(f"floor must be finite and >= 0, got {floor}")
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
        value = self.check(value)
        m = value.shape[-1]
        if m * self.floor >= 1:
            raise ValueError(f"{self.name}: floor {self.floor} too large for {m} categories")
        if not torch.allclose(value.sum(-1), torch.ones((), dtype=value.dtype), atol=1e-6):
            raise ValueError(f"{self.name} rows must sum to 1, got sums {_show(value.sum(-1))}")
        if not bool((value >= self.floor).all()):
            raise ValueError(f"{self.name} entries must be >= the floor {self.floor}, got {_show(value)}")
        p = (value - self.floor) / (1.0 - m * self.floor)
        logp = torch.log(p.clamp_min(torch.finfo(value.dtype).tiny))
        return logp - logp.mean(-1, keepdim=True)
