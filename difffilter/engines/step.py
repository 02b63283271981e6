"""Element-wise small linear algebra for the inductor engine, and the mode that swaps it in.

The inductor engine runs a filter's own ``predict``/``update`` (the code the eager filters run).
What it changes is the primitives underneath: inside :class:`SmallLinalg`, the LAPACK/BLAS calls
of the step (``cholesky_ex``, triangular solves, ``cholesky_solve``, Householder ``qr`` and
products of small matrices) become straight-line element-wise arithmetic over the batch, with
no data-dependent branch.  ``torch.compile`` then fuses a whole step into a few loops over the
batch (on any device inductor supports) instead of calling batched LAPACK kernels on ``n x n``
matrices; the same code runs uncompiled for debugging (the ``"eager"`` engine).  Combined with
:func:`~.branchfree.branch_free` (the helpers that branch on data), a step is one graph.

Layout is batch-first, the reference filters' own: every ``[..., n, n]`` operand is read
element by element (``unbind``), so each primitive is ``O(n^3)`` tensor operations of shape
``[...]``.  The Cholesky factor clamps a pivot that is not above ``n * eps * max|diag| + tiny``
to that floor (the reference retries with jitter) and reports the number of clamps in ``info``
(read by ``safe_cholesky``'s branch-free stand-in as its ``jitter``, so the step flags itself).
"""

from __future__ import annotations

import operator
from typing import Any

import torch
from torch import Tensor

from .householder import Arithmetic, householder

__all__ = ["MAX_CONTRACTION", "SmallLinalg", "cholesky_lower", "householder_qr", "small_matmul", "solve_triangular"]

#: products whose contraction is at most this long become multiply-and-sum
MAX_CONTRACTION = 64


def _elements(a: Tensor) -> list[list[Tensor]]:
    """``a [..., p, q]`` as ``p x q`` tensors ``[...]`` (two ``unbind``: one backward node each)."""
    return [list(row.unbind(-1)) for row in a.unbind(-2)]


def _stack(rows: list[list[Tensor]]) -> Tensor:
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def cholesky_lower(a: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of the symmetric part of ``a [..., n, n]`` and the number of
    clamped pivots ``[...]`` (``int32``).

    Branch-free: a pivot that is not above ``n * eps * max_j |a_jj| + tiny`` (rounding, a
    semi-definite, indefinite or non-finite matrix) is replaced by that floor, so one bad batch
    element never changes the others.  Off-diagonal entries are read as ``(a_ij + a_ji) / 2``, so
    the gradient is symmetric, as torch's.
    """
    n = a.shape[-1]
    eps, tiny = torch.finfo(a.dtype).eps, torch.finfo(a.dtype).tiny
    el = _elements(a)
    sym = [[el[i][j] if i == j else 0.5 * (el[i][j] + el[j][i]) for j in range(n)] for i in range(n)]
    big = torch.stack([sym[j][j] for j in range(n)], -1).abs().amax(-1)
    floor = (n * eps) * big + tiny
    zero = torch.zeros_like(floor)
    low: list[list[Tensor]] = [[zero] * n for _ in range(n)]
    clamps = torch.zeros_like(floor, dtype=torch.int32)
    for j in range(n):
        s = sym[j][j]
        for k in range(j):
            s = s - low[j][k] * low[j][k]
        ok = s > floor
        clamps = clamps + (~ok).to(torch.int32)
        d = torch.sqrt(torch.where(ok, s, floor))
        low[j][j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = sym[i][j]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i][j] = s * inv
    return _stack(low), clamps


def solve_triangular(a: Tensor, b: Tensor, *, upper: bool, left: bool = True, unitriangular: bool = False) -> Tensor:
    """``X`` with ``A X = B`` (``left``) or ``X A = B`` for triangular ``A [..., n, n]`` (only its
    ``upper``/lower triangle read), by substitution; leading dims broadcast."""
    if not left:  # X A = B  <=>  A^T X^T = B^T
        return solve_triangular(a.mT, b.mT, upper=not upper, unitriangular=unitriangular).mT
    n = a.shape[-1]
    el = _elements(a)
    rhs = b.unbind(-2)  # rows [..., k]
    xs: list[Tensor | None] = [None] * n
    for i in range(n - 1, -1, -1) if upper else range(n):
        s = rhs[i]
        for j in range(i + 1, n) if upper else range(i):
            s = s - el[i][j][..., None] * xs[j]  # type: ignore[operator]
        xs[i] = s if unitriangular else s / el[i][i][..., None]
    shape = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    return torch.stack([x.expand(*shape, b.shape[-1]) for x in xs], -2)  # type: ignore[union-attr]


def householder_qr(a: Tensor, mode: str = "reduced") -> tuple[Tensor, Tensor]:
    """QR of ``a [..., m, k]`` by Householder reflections with LAPACK's sign convention
    (``R_jj = -sign(a_jj) ||a_j:||``); ``mode`` ``"reduced"`` or ``"r"`` (empty ``Q``).

    A column with nothing below its diagonal is left as it is (no reflection), selected with
    ``where``, so no batch element divides by zero.
    """
    if mode not in ("reduced", "r"):
        raise ValueError(f"householder_qr: mode must be 'reduced' or 'r', got {mode!r}")
    w = _elements(a)
    zero, one = torch.zeros_like(w[0][0]), torch.ones_like(w[0][0])
    q, r = householder(w, _tensor_arithmetic(zero, one), want_q=mode == "reduced", guard_sqrt=True)
    return (a.new_zeros(0) if q is None else _stack(q)), _stack(r)


def _tensor_arithmetic(zero: Tensor, one: Tensor) -> Arithmetic:
    return Arithmetic(
        add=operator.add,
        sub=operator.sub,
        mul=operator.mul,
        div=operator.truediv,
        neg=operator.neg,
        sqrt=torch.sqrt,
        lt=operator.lt,
        eq=operator.eq,
        where=torch.where,
        zero=zero,
        one=one,
    )


def small_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a [..., i, k] @ b [..., k, j]`` as broadcast multiply-and-sum (fuses with its neighbours)."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


_MATMULS = (torch.matmul, torch.Tensor.matmul, torch.Tensor.__matmul__, torch.bmm, torch.mm)


def _cholesky_ex(a: Tensor, *, upper: bool = False, check_errors: bool = False, out: Any = None) -> Any:
    if upper or check_errors or out is not None:
        return NotImplemented
    return torch.return_types.linalg_cholesky_ex(cholesky_lower(a))


def _cholesky(a: Tensor, *, upper: bool = False, out: Any = None) -> Any:
    if upper or out is not None:
        return NotImplemented
    return cholesky_lower(a)[0]


def _solve_triangular(a: Tensor, b: Tensor, *, upper: bool, left: bool = True, unitriangular: bool = False, out: Any = None) -> Any:
    if out is not None:
        return NotImplemented
    return solve_triangular(a, b, upper=upper, left=left, unitriangular=unitriangular)


def _cholesky_solve(b: Tensor, low: Tensor, upper: bool = False, *, out: Any = None) -> Any:
    if out is not None:
        return NotImplemented
    if upper:
        low = low.mT
    return solve_triangular(low.mT, solve_triangular(low, b, upper=False), upper=True)


def _qr(a: Tensor, mode: str = "reduced", *, out: Any = None) -> Any:
    if out is not None or mode not in ("reduced", "r"):
        return NotImplemented
    return torch.return_types.linalg_qr(householder_qr(a, mode))


def _unflatten(a: Tensor, dim: int, sizes: Any) -> Tensor:
    # Tensor.unflatten is a Python method that dynamo cannot follow into (a super() call)
    d = dim % a.ndim
    return a.reshape(*a.shape[:d], *sizes, *a.shape[d + 1 :])


_REPLACED = {
    torch.linalg.cholesky_ex: _cholesky_ex,
    torch.linalg.cholesky: _cholesky,
    torch.linalg.solve_triangular: _solve_triangular,
    torch.cholesky_solve: _cholesky_solve,
    torch.Tensor.cholesky_solve: _cholesky_solve,
    torch.linalg.qr: _qr,
}


class SmallLinalg(torch.overrides.TorchFunctionMode):
    """Inside the block, the small dense linear algebra of a filter step is element-wise:
    ``cholesky_ex``/``cholesky`` (:func:`cholesky_lower`; ``info`` = clamped pivots),
    ``solve_triangular``, ``cholesky_solve``, ``qr`` and matrix products whose contraction is at
    most :data:`MAX_CONTRACTION` long; ``Tensor.unflatten`` becomes ``reshape`` (which dynamo
    traces).  Other calls (and unsupported arguments) run unchanged."""

    def __torch_function__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        kwargs = kwargs or {}
        if func in _MATMULS and not kwargs and len(args) == 2:
            a, b = args
            if isinstance(a, Tensor) and isinstance(b, Tensor) and a.ndim >= 2 and b.ndim >= 2 and a.shape[-1] <= MAX_CONTRACTION:
                return small_matmul(a, b)
        if func is torch.Tensor.unflatten:  # a Python function: dynamo does not look it up in a dict
            return _unflatten(*args, **kwargs)
        replacement = _REPLACED.get(func)
        if replacement is not None:
            out = replacement(*args, **kwargs)
            if out is not NotImplemented:
                return out
        return func(*args, **kwargs)
