"""Building blocks of the lowering: tensors as NumPy object arrays of scalar-graph nodes.

:class:`Lowering` holds the scalar graph and the kernel dtype and turns element-wise operations,
reductions, small matrix products and the small dense linear algebra of a filter step
(Cholesky with clamped pivots, triangular solves, Householder QR) into scalar nodes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .graph import CMP_OPS, UNARY, ScalarGraph, UnsupportedOp
from .householder import Arithmetic, householder

__all__ = ["Arr", "Lowering", "dim_index", "filled"]

Arr = np.ndarray


def dim_index(d: int, ndim: int) -> int:
    return d + ndim if d < 0 else d


class Lowering:
    """Interpreter state: the scalar graph, the kernel dtype and the op table."""

    def __init__(self, graph: ScalarGraph, dtype: torch.dtype) -> None:
        self.g = graph
        self.dtype = dtype
        g = graph
        self._un = {op: np.frompyfunc(lambda a, op=op: g.unary(op, a), 1, 1) for op in UNARY}
        self._bin = {
            op: np.frompyfunc(lambda a, b, op=op: g.binary(op, a, b), 2, 1)
            for op in ("add", "sub", "mul", "div", "pow", "atan2", "max", "min", "fmod")
        }
        self._cmp = {op: np.frompyfunc(lambda a, b, op=op: g.compare(op, g.to_float(a), g.to_float(b)), 2, 1) for op in CMP_OPS}
        self._and = np.frompyfunc(lambda a, b: g.logical("and", g.to_bool(a), g.to_bool(b)), 2, 1)
        self._or = np.frompyfunc(lambda a, b: g.logical("or", g.to_bool(a), g.to_bool(b)), 2, 1)
        self._xor = np.frompyfunc(lambda a, b: g.logical("xor", g.to_bool(a), g.to_bool(b)), 2, 1)
        self._not = np.frompyfunc(lambda a: g.logical("not", g.to_bool(a)), 1, 1)
        self._where = np.frompyfunc(lambda c, x, y: g.where(g.to_bool(c), x, y), 3, 1)
        self._to_float = np.frompyfunc(g.to_float, 1, 1)
        self._to_bool = np.frompyfunc(g.to_bool, 1, 1)

    # -- conversions ------------------------------------------------------------------------
    def const_array(self, t: torch.Tensor) -> Arr:
        vals = t.detach().cpu()
        is_bool = vals.dtype == torch.bool
        flat = [self.g.const(bool(v) if is_bool else float(v)) for v in vals.reshape(-1).tolist()]
        return np.array(flat, dtype=object).reshape(tuple(t.shape))

    def arr(self, x: Any) -> Arr:
        """An object array from a lowered tensor or a Python number."""
        if isinstance(x, np.ndarray):
            return x
        if isinstance(x, bool):
            return np.array(self.g.const(x), dtype=object)
        if isinstance(x, (int, float)):
            return np.array(self.g.const(float(x)), dtype=object)
        if isinstance(x, torch.Tensor):
            return self.const_array(x)
        raise UnsupportedOp(f"cannot use {type(x).__name__} as a tensor")

    def fl(self, x: Any) -> Arr:
        a = self.arr(x)
        return np.asarray(self._to_float(a), dtype=object) if a.size else a

    def bo(self, x: Any) -> Arr:
        a = self.arr(x)
        return np.asarray(self._to_bool(a), dtype=object) if a.size else a

    # -- building blocks --------------------------------------------------------------------
    def binary(self, op: str, a: Any, b: Any) -> Arr:
        return np.asarray(self._bin[op](self.fl(a), self.fl(b)), dtype=object)

    def unary(self, op: str, a: Any) -> Arr:
        return np.asarray(self._un[op](self.fl(a)), dtype=object)

    def where(self, c: Any, x: Any, y: Any) -> Arr:
        return np.asarray(self._where(self.arr(c), self.arr(x), self.arr(y)), dtype=object)

    def reduce(self, op: str, a: Arr, dims: Any, keepdim: bool) -> Arr:
        a = self.arr(a)
        if dims is None or (isinstance(dims, (list, tuple)) and len(dims) == 0):
            dims = list(range(a.ndim))
        if isinstance(dims, int):
            dims = [dims]
        dims = sorted({dim_index(d, a.ndim) for d in dims}) if a.ndim else []
        if op in ("and", "or"):
            fn = self._and if op == "and" else self._or
            a = self.bo(a)
        else:
            fn = self._bin[op]
            a = self.fl(a)
        out = a
        for d in reversed(dims):
            if out.shape[d] == 0:
                raise UnsupportedOp("reduction over an empty dimension")
            out = np.asarray(fn.reduce(out, axis=d, keepdims=True), dtype=object)
        if not keepdim and dims:
            out = out.reshape([s for i, s in enumerate(out.shape) if i not in dims])
        return out

    def matmul(self, a: Arr, b: Arr) -> Arr:
        """``a [..., i, k] @ b [..., k, j]`` with broadcasting over the leading dims."""
        prod = self.binary("mul", a[..., :, :, None], b[..., None, :, :])
        return self.reduce("add", prod, [-2], False)

    def cholesky(self, a: Arr) -> tuple[Arr, Arr]:
        """Lower factor of every ``[n, n]`` matrix in ``a [..., n, n]`` and the clamp counts ``[...]``."""
        g = self.g
        n = a.shape[-1]
        eps, tiny = torch.finfo(self.dtype).eps, torch.finfo(self.dtype).tiny
        lead = a.shape[:-2]
        out = np.empty(a.shape, dtype=object)
        info = np.empty(lead, dtype=object)
        zero = g.const(0.0)
        half = g.const(0.5)
        for idx in np.ndindex(*lead):
            # read the symmetric part, as torch's Cholesky gradient does (its gradient is
            # symmetric); equal to the lower triangle for a symmetric input
            m = np.array(
                [
                    [a[idx][i, j] if i == j else g.binary("mul", half, g.binary("add", a[idx][i, j], a[idx][j, i])) for j in range(n)]
                    for i in range(n)
                ],
                dtype=object,
            )
            big = g.unary("abs", m[0, 0])
            for j in range(1, n):
                big = g.binary("max", big, g.unary("abs", m[j, j]))
            floor = g.binary("add", g.binary("mul", g.const(n * eps), big), g.const(tiny))
            low = [[zero] * n for _ in range(n)]
            clamps = zero
            for j in range(n):
                s = m[j, j]
                for k in range(j):
                    s = g.binary("sub", s, g.binary("mul", low[j][k], low[j][k]))
                ok = g.compare("gt", s, floor)
                clamps = g.binary("add", clamps, g.where(ok, zero, g.const(1.0)))
                d = g.unary("sqrt", g.where(ok, s, floor))
                low[j][j] = d
                inv = g.binary("div", g.const(1.0), d)
                for i in range(j + 1, n):
                    s = m[i, j]
                    for k in range(j):
                        s = g.binary("sub", s, g.binary("mul", low[i][k], low[j][k]))
                    low[i][j] = g.binary("mul", s, inv)
            out[idx] = np.array(low, dtype=object)
            info[idx] = clamps
        return out, info

    def solve_triangular(self, a: Arr, b: Arr, *, upper: bool, left: bool, unit: bool) -> Arr:
        """``X`` with ``A X = B`` (``left``) or ``X A = B`` for triangular ``A [..., n, n]``."""
        if not left:  # X A = B  <=>  A^T X^T = B^T
            return np.swapaxes(
                self.solve_triangular(np.swapaxes(a, -1, -2), np.swapaxes(b, -1, -2), upper=not upper, left=True, unit=unit), -1, -2
            )
        g = self.g
        shape = np.broadcast_shapes(a.shape[:-2], b.shape[:-2])
        a = np.broadcast_to(a, shape + a.shape[-2:])
        b = np.broadcast_to(b, shape + b.shape[-2:])
        n, k = b.shape[-2], b.shape[-1]
        out = np.empty(shape + (n, k), dtype=object)
        order = range(n - 1, -1, -1) if upper else range(n)
        for idx in np.ndindex(*shape):
            m, rhs = a[idx], b[idx]
            x = [[0] * k for _ in range(n)]
            inv = [None if unit else g.binary("div", g.const(1.0), m[i, i]) for i in range(n)]
            for i in order:
                deps = range(i + 1, n) if upper else range(i)
                for c in range(k):
                    s = rhs[i, c]
                    for j in deps:
                        s = g.binary("sub", s, g.binary("mul", m[i, j], x[j][c]))
                    x[i][c] = s if unit else g.binary("mul", s, inv[i])
            out[idx] = np.array(x, dtype=object)
        return out

    def cmp(self, op: str, a: Any, b: Any) -> Arr:
        return np.asarray(self._cmp[op](self.arr(a), self.arr(b)), dtype=object)

    def qr(self, a: Arr, want_q: bool) -> tuple[Arr, Arr]:
        return _householder_qr(self, a, want_q)


def _householder_qr(L: Lowering, a: Arr, want_q: bool) -> tuple[Arr, Arr]:
    """QR of every ``[m, k]`` matrix in ``a`` by Householder reflections, LAPACK's sign
    convention (``R_jj = -sign(a_jj) * norm``); reduced ``Q [..., m, min(m, k)]``."""
    g = L.g
    m, k = a.shape[-2:]
    p = min(m, k)
    lead = a.shape[:-2]
    q_out = np.empty(lead + (m, p), dtype=object)
    r_out = np.empty(lead + (p, k), dtype=object)
    ar = Arithmetic(
        add=lambda x, y: g.binary("add", x, y),
        sub=lambda x, y: g.binary("sub", x, y),
        mul=lambda x, y: g.binary("mul", x, y),
        div=lambda x, y: g.binary("div", x, y),
        neg=lambda x: g.unary("neg", x),
        sqrt=lambda x: g.unary("sqrt", x),
        lt=lambda x, y: g.compare("lt", x, y),
        eq=lambda x, y: g.compare("eq", x, y),
        where=g.where,
        zero=g.const(0.0),
        one=g.const(1.0),
    )
    for idx in np.ndindex(*lead):
        qm, r = householder([[a[idx][i, j] for j in range(k)] for i in range(m)], ar, want_q=want_q, guard_sqrt=False)
        r_out[idx] = np.array(r, dtype=object)
        if qm is not None:
            q_out[idx] = np.array(qm, dtype=object)
    return q_out, r_out


def filled(L: Lowering, shape: Any, value: Any, dtype: torch.dtype | None) -> Arr:
    shape = tuple(int(s) for s in shape)
    v = L.arr(value)
    if dtype == torch.bool:
        v = L.bo(v)
    return np.broadcast_to(v, shape).copy()
