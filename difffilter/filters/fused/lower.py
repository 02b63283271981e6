"""ATen graph -> scalar graph: run a traced step on arrays of scalar nodes.

:func:`lower` interprets an FX graph of ATen operations (from ``make_fx``) where every tensor is
a NumPy object array of :class:`~.graph.ScalarGraph` node ids, one per element.  Shapes are
static and the batch dimension of the trace has size one, so each element is one scalar of one
trajectory.  Views, broadcasting and concatenation are index bookkeeping; element-wise
operations create one node per element; reductions and small matrix products become chains of
additions; ``linalg.cholesky_ex`` and the triangular solves are written out as the textbook
algorithms (Cholesky with pivots clamped to ``n * eps * max|diag| + tiny``).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import fx

from .graph import CMP_OPS, UNARY, UNIFORM, ScalarGraph, UnsupportedOp

__all__ = ["lower", "Lowering"]

aten = torch.ops.aten
Arr = np.ndarray


def _dim(d: int, ndim: int) -> int:
    return d + ndim if d < 0 else d


class Lowering:
    """Interpreter state: the scalar graph, the kernel dtype and the op table."""

    def __init__(self, graph: ScalarGraph, dtype: torch.dtype) -> None:
        self.g = graph
        self.dtype = dtype
        g = graph
        self._un = {op: np.frompyfunc(lambda a, op=op: g.unary(op, a), 1, 1) for op in UNARY}
        self._bin = {op: np.frompyfunc(lambda a, b, op=op: g.binary(op, a, b), 2, 1) for op in ("add", "sub", "mul", "div", "pow", "atan2", "max", "min", "fmod")}
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
        dims = sorted({_dim(d, a.ndim) for d in dims}) if a.ndim else []
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
                [[a[idx][i, j] if i == j else g.binary("mul", half, g.binary("add", a[idx][i, j], a[idx][j, i])) for j in range(n)] for i in range(n)],
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
            return np.swapaxes(self.solve_triangular(np.swapaxes(a, -1, -2), np.swapaxes(b, -1, -2), upper=not upper, left=True, unit=unit), -1, -2)
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


def _householder_qr(L: Lowering, a: Arr, want_q: bool) -> tuple[Arr, Arr]:
    """QR of every ``[m, k]`` matrix in ``a`` by Householder reflections, LAPACK's sign
    convention (``R_jj = -sign(a_jj) * norm``); reduced ``Q [..., m, min(m, k)]``."""
    g = L.g
    m, k = a.shape[-2:]
    p = min(m, k)
    lead = a.shape[:-2]
    q_out = np.empty(lead + (m, p), dtype=object)
    r_out = np.empty(lead + (p, k), dtype=object)
    zero, one = g.const(0.0), g.const(1.0)
    for idx in np.ndindex(*lead):
        w = [[a[idx][i, j] for j in range(k)] for i in range(m)]
        reflectors = []
        for j in range(p):
            alpha = w[j][j]
            xnorm2 = zero
            for i in range(j + 1, m):
                xnorm2 = g.binary("add", xnorm2, g.binary("mul", w[i][j], w[i][j]))
            norm = g.unary("sqrt", g.binary("add", g.binary("mul", alpha, alpha), xnorm2))
            neg = g.compare("lt", alpha, zero)
            beta = g.where(neg, norm, g.unary("neg", norm))
            trivial = g.compare("eq", xnorm2, zero)  # nothing below the diagonal: H = I
            safe = g.where(trivial, one, g.binary("sub", alpha, beta))
            tau = g.where(trivial, zero, g.binary("div", g.binary("sub", beta, alpha), g.where(trivial, one, beta)))
            v = [one] + [g.binary("div", w[i][j], safe) for i in range(j + 1, m)]
            w[j][j] = g.where(trivial, alpha, beta)
            for i in range(j + 1, m):
                w[i][j] = zero
            for c in range(j + 1, k):  # w[j:, c] -= tau v (v^T w[j:, c])
                dot = w[j][c]
                for i in range(j + 1, m):
                    dot = g.binary("add", dot, g.binary("mul", v[i - j], w[i][c]))
                s = g.binary("mul", tau, dot)
                for i in range(j, m):
                    w[i][c] = g.binary("sub", w[i][c], g.binary("mul", s, v[i - j]))
            reflectors.append((j, v, tau))
        r_out[idx] = np.array([[w[i][j] if j >= i else zero for j in range(k)] for i in range(p)], dtype=object)
        if want_q:
            qm = [[one if i == c else zero for c in range(p)] for i in range(m)]
            for j, v, tau in reversed(reflectors):
                for c in range(p):
                    dot = zero
                    for i in range(j, m):
                        dot = g.binary("add", dot, g.binary("mul", v[i - j], qm[i][c]))
                    s = g.binary("mul", tau, dot)
                    for i in range(j, m):
                        qm[i][c] = g.binary("sub", qm[i][c], g.binary("mul", s, v[i - j]))
            q_out[idx] = np.array(qm, dtype=object)
    return q_out, r_out


_UNARY_ATEN = {
    "neg": "neg",
    "sqrt": "sqrt",
    "exp": "exp",
    "log": "log",
    "log1p": "log1p",
    "expm1": "expm1",
    "sin": "sin",
    "cos": "cos",
    "tan": "tan",
    "atan": "atan",
    "asin": "asin",
    "acos": "acos",
    "tanh": "tanh",
    "sinh": "sinh",
    "cosh": "cosh",
    "sigmoid": "sigmoid",
    "abs": "abs",
    "floor": "floor",
    "ceil": "ceil",
    "round": "round",
    "sign": "sign",
    "sgn": "sign",
    "trunc": "round",
}


def _lower_op(L: Lowering, name: str, args: tuple, kw: dict[str, Any], node: fx.Node) -> Any:  # noqa: C901 - one table of cases
    g = L.g
    a0 = args[0] if args else None
    if name in _UNARY_ATEN:
        return L.unary(_UNARY_ATEN[name], a0)
    if name in ("add", "sub"):
        b = args[1]
        alpha = kw.get("alpha", 1)
        if alpha != 1:
            b = L.binary("mul", b, alpha)
        return L.binary(name, a0, b)
    if name == "rsub":
        b = args[1]
        alpha = kw.get("alpha", 1)
        return L.binary("sub", b, a0 if alpha == 1 else L.binary("mul", a0, alpha))
    if name in ("mul", "div", "atan2", "fmod", "remainder"):
        mode = kw.get("rounding_mode")
        if name == "remainder":
            q = L.unary("floor", L.binary("div", a0, args[1]))
            return L.binary("sub", a0, L.binary("mul", q, args[1]))
        out = L.binary({"atan2": "atan2", "fmod": "fmod"}.get(name, name), a0, args[1])
        if mode == "floor":
            out = L.unary("floor", out)
        elif mode == "trunc":
            raise UnsupportedOp("div with rounding_mode='trunc'")
        return out
    if name in ("pow",):
        return L.binary("pow", a0, args[1])
    if name == "square":
        return L.binary("mul", a0, a0)
    if name == "reciprocal":
        return L.binary("div", 1.0, a0)
    if name == "rsqrt":
        return L.binary("div", 1.0, L.unary("sqrt", a0))
    if name in ("maximum", "max") and len(args) == 2 and not isinstance(args[1], int):
        return L.binary("max", a0, args[1])
    if name in ("minimum", "min") and len(args) == 2 and not isinstance(args[1], int):
        return L.binary("min", a0, args[1])
    if name in ("clamp", "clamp_min", "clamp_max"):
        lo = args[1] if len(args) > 1 and name != "clamp_max" else kw.get("min")
        hi = (args[2] if len(args) > 2 else kw.get("max")) if name == "clamp" else (args[1] if name == "clamp_max" else None)
        out = L.fl(a0)
        if lo is not None:
            out = L.binary("max", out, lo)
        if hi is not None:
            out = L.binary("min", out, hi)
        return out
    if name == "softplus":
        beta = args[1] if len(args) > 1 else kw.get("beta", 1.0)
        threshold = args[2] if len(args) > 2 else kw.get("threshold", 20.0)
        x = L.binary("mul", a0, beta)
        soft = L.binary("div", L.unary("softplus", x), beta)
        return L.where(L.cmp("gt", x, threshold), L.fl(a0), soft)
    if name in CMP_OPS:
        return L.cmp(name, a0, args[1])
    if name in ("logical_and", "bitwise_and"):
        return np.asarray(L._and(L.arr(a0), L.arr(args[1])), dtype=object)
    if name in ("logical_or", "bitwise_or"):
        return np.asarray(L._or(L.arr(a0), L.arr(args[1])), dtype=object)
    if name in ("logical_xor", "bitwise_xor"):
        return np.asarray(L._xor(L.arr(a0), L.arr(args[1])), dtype=object)
    if name in ("logical_not", "bitwise_not"):
        return np.asarray(L._not(L.arr(a0)), dtype=object)
    if name == "isnan":
        return L.cmp("ne", a0, a0)
    if name == "isinf":
        return L.cmp("eq", L.unary("abs", a0), math.inf)
    if name == "isfinite":
        return L.cmp("lt", L.unary("abs", a0), math.inf)
    if name == "where":
        return L.where(L.bo(a0), L.arr(args[1]), L.arr(args[2]))
    if name == "logaddexp":
        hi, lo = L.binary("max", a0, args[1]), L.binary("min", a0, args[1])
        out = L.binary("add", hi, L.unary("log1p", L.unary("exp", L.binary("sub", lo, hi))))
        return L.where(L.cmp("eq", hi, -math.inf), hi, out)
    if name in ("_has_same_storage_numel", "_assert_tensor_metadata", "_assert_scalar", "sym_constrain_range_for_size"):
        return True  # metadata checks of the trace, already true for the traced shapes
    if name == "is_same_size":
        return L.arr(a0).shape == L.arr(args[1]).shape
    if name in ("masked_fill",):
        return L.where(L.bo(args[1]), L.arr(args[2]) if not isinstance(args[2], np.ndarray) else args[2], L.arr(a0))
    if name in ("_to_copy", "to", "clone", "lift_fresh_copy", "alias", "detach", "contiguous", "_conj", "resolve_conj", "resolve_neg"):
        dtype = kw.get("dtype")
        if dtype is None and name == "to" and len(args) > 1 and isinstance(args[1], torch.dtype):
            dtype = args[1]
        x = L.arr(a0)
        if dtype is None:
            return x
        return L.bo(x) if dtype == torch.bool else L.fl(x)
    if name == "copy":
        return np.broadcast_to(L.arr(args[1]), L.arr(a0).shape).copy()
    if name in ("view", "_unsafe_view", "reshape", "view_copy"):
        return L.arr(a0).reshape(args[1])
    if name == "expand":
        shape = [s if s != -1 else L.arr(a0).shape[i - (len(args[1]) - L.arr(a0).ndim)] for i, s in enumerate(args[1])]
        return np.broadcast_to(L.arr(a0), shape)
    if name in ("permute",):
        return np.transpose(L.arr(a0), args[1])
    if name == "transpose":
        return np.swapaxes(L.arr(a0), args[1], args[2])
    if name in ("t", "numpy_T"):
        return L.arr(a0).T
    if name == "unsqueeze":
        x = L.arr(a0)
        return np.expand_dims(x, _dim(args[1], x.ndim + 1))
    if name == "squeeze":
        x = L.arr(a0)
        dims = args[1] if len(args) > 1 else [i for i, s in enumerate(x.shape) if s == 1]
        dims = [dims] if isinstance(dims, int) else list(dims)
        dims = tuple(_dim(d, x.ndim) for d in dims if x.shape[_dim(d, x.ndim)] == 1) if x.ndim else ()
        return np.squeeze(x, axis=dims) if dims else x
    if name == "select":
        x = L.arr(a0)
        return np.take(x, args[2], axis=_dim(args[1], x.ndim))
    if name == "slice":
        x = L.arr(a0)
        d = _dim(args[1] if len(args) > 1 else 0, x.ndim)
        start = args[2] if len(args) > 2 else None
        end = args[3] if len(args) > 3 else None
        step = args[4] if len(args) > 4 else 1
        sl = [slice(None)] * x.ndim
        sl[d] = slice(start, None if end is not None and end >= 2**62 else end, step)
        return x[tuple(sl)]
    if name == "narrow":
        x = L.arr(a0)
        d = _dim(args[1], x.ndim)
        sl = [slice(None)] * x.ndim
        sl[d] = slice(args[2], args[2] + args[3])
        return x[tuple(sl)]
    if name == "unbind":
        x = L.arr(a0)
        d = _dim(args[1] if len(args) > 1 else 0, x.ndim)
        return [np.take(x, i, axis=d) for i in range(x.shape[d])]
    if name in ("split", "split_with_sizes"):
        x = L.arr(a0)
        d = _dim(args[2] if len(args) > 2 else kw.get("dim", 0), x.ndim)
        sizes = args[1]
        if isinstance(sizes, int):
            sizes = [sizes] * (x.shape[d] // sizes) + ([x.shape[d] % sizes] if x.shape[d] % sizes else [])
        cuts = np.cumsum(sizes)[:-1]
        return list(np.split(x, cuts, axis=d))
    if name in ("cat", "concat"):
        tensors = [L.arr(t) for t in a0 if L.arr(t).size or L.arr(t).ndim > 1]
        d = args[1] if len(args) > 1 else kw.get("dim", 0)
        return np.concatenate(tensors, axis=_dim(d, tensors[0].ndim))
    if name == "stack":
        tensors = [L.arr(t) for t in a0]
        d = args[1] if len(args) > 1 else kw.get("dim", 0)
        return np.stack(tensors, axis=_dim(d, tensors[0].ndim + 1))
    if name == "flip":
        return np.flip(L.arr(a0), axis=tuple(args[1]))
    if name == "diagonal":
        x = L.arr(a0)
        off = args[1] if len(args) > 1 else kw.get("offset", 0)
        d1 = _dim(args[2] if len(args) > 2 else kw.get("dim1", 0), x.ndim)
        d2 = _dim(args[3] if len(args) > 3 else kw.get("dim2", 1), x.ndim)
        return np.diagonal(x, offset=off, axis1=d1, axis2=d2)
    if name == "diag_embed":
        x = L.arr(a0)
        off = args[1] if len(args) > 1 else kw.get("offset", 0)
        if off != 0 or (len(args) > 2 and (args[2], args[3]) != (-2, -1)):
            raise UnsupportedOp("diag_embed with an offset or other dims")
        n = x.shape[-1]
        out = np.empty(x.shape + (n,), dtype=object)
        out[...] = g.const(0.0)
        for i in range(n):
            out[..., i, i] = x[..., i]
        return out
    if name in ("tril", "triu"):
        x = L.arr(a0).copy()
        k = args[1] if len(args) > 1 else 0
        n, m = x.shape[-2:]
        keep = np.tril(np.ones((n, m), dtype=bool), k) if name == "tril" else np.triu(np.ones((n, m), dtype=bool), k)
        x[..., ~keep] = g.const(0.0)
        return x
    if name in ("index",):
        return L.arr(a0)[_const_index(g, args[1])]
    if name == "index_put":
        x = L.arr(a0).copy()
        accumulate = args[3] if len(args) > 3 else kw.get("accumulate", False)
        pos = np.arange(x.size).reshape(x.shape)[_const_index(g, args[1])]
        vals = np.broadcast_to(L.arr(args[2]), pos.shape)
        flat = x.reshape(-1)
        for p_, v in zip(pos.reshape(-1).tolist(), vals.reshape(-1).tolist(), strict=True):
            flat[p_] = g.binary("add", flat[p_], v) if accumulate else v
        return flat.reshape(x.shape)
    if name == "index_select":
        x = L.arr(a0)
        ids = [int(g.value[v]) for v in L.arr(args[2]).reshape(-1)]
        return np.take(x, ids, axis=_dim(args[1], x.ndim))
    if name in ("select_scatter", "slice_scatter", "diagonal_scatter"):
        x = L.arr(a0).copy()
        src = L.arr(args[1])
        if name == "select_scatter":
            d = _dim(args[2], x.ndim)
            sl = [slice(None)] * x.ndim
            sl[d] = args[3]
        elif name == "slice_scatter":
            d = _dim(args[2] if len(args) > 2 else kw.get("dim", 0), x.ndim)
            start = args[3] if len(args) > 3 else kw.get("start")
            end = args[4] if len(args) > 4 else kw.get("end")
            step = args[5] if len(args) > 5 else kw.get("step", 1)
            sl = [slice(None)] * x.ndim
            sl[d] = slice(start, None if end is not None and end >= 2**62 else end, step)
        else:
            raise UnsupportedOp("diagonal_scatter")
        x[tuple(sl)] = src
        return x
    if name in ("sum", "mean", "amax", "amin", "prod", "any", "all"):
        x = L.arr(a0)
        dims = args[1] if len(args) > 1 else kw.get("dim")
        keep = args[2] if len(args) > 2 else kw.get("keepdim", False)
        if name in ("any", "all"):
            return L.reduce("or" if name == "any" else "and", x, dims, keep)
        op = {"sum": "add", "mean": "add", "amax": "max", "amin": "min", "prod": "mul"}[name]
        out = L.reduce(op, x, dims, keep)
        if name == "mean":
            count = x.size // max(out.size, 1)
            out = L.binary("div", out, float(count))
        return out
    if name == "linalg_vector_norm":
        order = args[1] if len(args) > 1 else kw.get("ord", 2)
        dims = args[2] if len(args) > 2 else kw.get("dim")
        keep = args[3] if len(args) > 3 else kw.get("keepdim", False)
        if order != 2:
            raise UnsupportedOp(f"vector norm of order {order}")
        x = L.fl(a0)
        return L.unary("sqrt", L.reduce("add", L.binary("mul", x, x), dims, keep))
    if name == "logsumexp":
        x = L.fl(a0)
        dims = args[1]
        keep = args[2] if len(args) > 2 else False
        top = L.reduce("max", x, dims, True)
        safe = L.where(L.cmp("eq", L.unary("abs", top), math.inf), 0.0, top)
        s = L.reduce("add", L.unary("exp", L.binary("sub", x, safe)), dims, True)
        out = L.binary("add", L.unary("log", s), safe)
        if not keep:
            out = np.squeeze(out, axis=tuple(_dim(d, x.ndim) for d in ([dims] if isinstance(dims, int) else dims)))
        return out
    if name in ("_log_softmax", "_softmax", "log_softmax", "softmax"):
        x = L.fl(a0)
        d = args[1]
        top = L.reduce("max", x, [d], True)
        shifted = L.binary("sub", x, top)
        e = L.unary("exp", shifted)
        s = L.reduce("add", e, [d], True)
        return L.binary("sub", shifted, L.unary("log", s)) if "log" in name else L.binary("div", e, s)
    if name in ("mm", "bmm", "matmul"):
        a, b = L.arr(a0), L.arr(args[1])
        if a.ndim == 1:
            return L.matmul(a[None, :], b if b.ndim > 1 else b[:, None])[..., 0, :] if b.ndim > 1 else L.matmul(a[None, :], b[:, None])[0, 0]
        if b.ndim == 1:
            return L.matmul(a, b[:, None])[..., 0]
        return L.matmul(a, b)
    if name == "mv":
        return L.matmul(L.arr(a0), L.arr(args[1])[:, None])[..., 0]
    if name == "dot":
        return L.reduce("add", L.binary("mul", a0, args[1]), None, False)
    if name in ("addmm", "baddbmm"):
        beta, alpha = kw.get("beta", 1), kw.get("alpha", 1)
        prod = L.matmul(L.arr(args[1]), L.arr(args[2]))
        return L.binary("add", L.binary("mul", a0, beta), L.binary("mul", prod, alpha))
    if name == "linalg_qr":
        mode = args[1] if len(args) > 1 else kw.get("mode", "reduced")
        if mode not in ("reduced", "r"):
            raise UnsupportedOp(f"linalg.qr mode={mode!r}")
        q, r = _householder_qr(L, L.fl(a0), mode == "reduced")
        return (q if mode == "reduced" else np.empty((0,), dtype=object)), r
    if name == "linalg_cholesky_ex":
        if (args[1] if len(args) > 1 else kw.get("upper", False)):
            raise UnsupportedOp("upper Cholesky")
        return L.cholesky(L.fl(a0))
    if name == "cholesky":
        low, _ = L.cholesky(L.fl(a0))
        return np.swapaxes(low, -1, -2).copy() if (args[1] if len(args) > 1 else kw.get("upper", False)) else low
    if name == "linalg_solve_triangular":
        upper = args[2] if len(args) > 2 else kw["upper"]
        return L.solve_triangular(L.fl(a0), L.fl(args[1]), upper=upper, left=kw.get("left", True), unit=kw.get("unitriangular", False))
    if name == "triangular_solve":  # (B, A, upper=True, transpose=False, unitriangular=False) -> (X, A)
        upper = args[2] if len(args) > 2 else kw.get("upper", True)
        trans = args[3] if len(args) > 3 else kw.get("transpose", False)
        unit = args[4] if len(args) > 4 else kw.get("unitriangular", False)
        a = L.fl(args[1])
        if trans:
            a, upper = np.swapaxes(a, -1, -2), not upper
        return L.solve_triangular(a, L.fl(a0), upper=upper, left=True, unit=unit), L.arr(args[1])
    if name == "cholesky_solve":  # (B, L, upper=False)
        low = L.fl(args[1])
        if args[2] if len(args) > 2 else kw.get("upper", False):
            low = np.swapaxes(low, -1, -2)
        y = L.solve_triangular(low, L.fl(a0), upper=False, left=True, unit=False)
        return L.solve_triangular(np.swapaxes(low, -1, -2), y, upper=True, left=True, unit=False)
    if name == "fill":
        return _filled(L, L.arr(a0).shape, args[1], node.meta["val"].dtype)
    if name == "_efficientzerotensor":
        return _filled(L, a0, 0.0, kw.get("dtype"))
    if name in ("zeros", "ones", "full", "empty", "new_zeros", "new_ones", "new_full", "new_empty", "scalar_tensor"):
        if name == "scalar_tensor":
            return L.fl(a0) if kw.get("dtype") != torch.bool else L.bo(a0)
        shape = args[1] if name.startswith("new_") else a0
        value = {"zeros": 0.0, "ones": 1.0, "empty": 0.0, "new_zeros": 0.0, "new_ones": 1.0, "new_empty": 0.0}.get(name)
        if value is None:
            value = args[2] if name == "new_full" else args[1]
        return _filled(L, shape, value, kw.get("dtype"))
    if name in ("zeros_like", "ones_like", "full_like", "empty_like"):
        shape = L.arr(a0).shape
        value = {"zeros_like": 0.0, "ones_like": 1.0, "empty_like": 0.0}.get(name, args[1] if len(args) > 1 else None)
        dtype = kw.get("dtype") or node.meta["val"].dtype
        return _filled(L, shape, value, dtype)
    if name == "arange":
        vals = torch.arange(*args, dtype=torch.float64)
        return np.array([g.const(float(v)) for v in vals.tolist()], dtype=object)
    if name == "eye":
        n = a0
        m = args[1] if len(args) > 1 and isinstance(args[1], int) else n
        out = np.empty((n, m), dtype=object)
        for i in range(n):
            for j in range(m):
                out[i, j] = g.const(1.0 if i == j else 0.0)
        return out
    raise UnsupportedOp(f"aten.{name}")


def _const_index(g: ScalarGraph, indices: Any) -> tuple[Any, ...]:
    """A NumPy index from ATen's list of optional index tensors (constants only)."""
    idx: list[Any] = []
    for i in indices:
        if i is None:
            idx.append(slice(None))
            continue
        if not isinstance(i, np.ndarray) or any(g.level[v] != 0 for v in i.reshape(-1)):
            raise UnsupportedOp("indexing with a data-dependent index")
        arr = np.array([g.value[v] for v in i.reshape(-1)]).reshape(i.shape)
        idx.append(arr.astype(bool) if arr.dtype == bool else arr.astype(np.int64))
    return tuple(idx)


def _filled(L: Lowering, shape: Any, value: Any, dtype: torch.dtype | None) -> Arr:
    shape = tuple(int(s) for s in shape)
    v = L.arr(value)
    if dtype == torch.bool:
        v = L.bo(v)
    return np.broadcast_to(v, shape).copy()


def _cmp(self: Lowering, op: str, a: Any, b: Any) -> Arr:
    return np.asarray(self._cmp[op](self.arr(a), self.arr(b)), dtype=object)


Lowering.cmp = _cmp  # type: ignore[attr-defined]


def _op_name(target: Any) -> str:
    if isinstance(target, torch._ops.OpOverload):
        return target.overloadpacket.__name__.rstrip("_") if target.overloadpacket.__name__ not in ("__and__", "__or__") else target.overloadpacket.__name__
    if isinstance(target, torch._ops.OpOverloadPacket):
        return target.__name__
    raise UnsupportedOp(f"call to {target}")


def lower(gm: fx.GraphModule, graph: ScalarGraph, dtype: torch.dtype, inputs: list[Any]) -> Any:
    """Run ``gm`` on ``inputs`` (object arrays, one per placeholder); return its outputs (same pytree)."""
    L = Lowering(graph, dtype)
    env: dict[fx.Node, Any] = {}
    it = iter(inputs)

    def load(a: Any) -> Any:
        return fx.node.map_arg(a, lambda n: env[n])

    for node in gm.graph.nodes:
        if node.op == "placeholder":
            env[node] = next(it)
        elif node.op == "get_attr":
            val = getattr(gm, node.target)
            env[node] = L.const_array(val) if isinstance(val, torch.Tensor) else val
        elif node.op == "call_function":
            args, kw = load(node.args), load(node.kwargs)
            if node.target is operator.getitem:
                env[node] = _as_arrays(args[0][args[1]], node.meta.get("val"))
                continue
            if node.target in _PY_OPS:
                env[node] = _PY_OPS[node.target](*args)
                continue
            env[node] = _as_arrays(_lower_op(L, _op_name(node.target), tuple(args), dict(kw), node), node.meta.get("val"))
        elif node.op == "output":
            return load(node.args[0])
        else:
            raise UnsupportedOp(f"FX node {node.op}")
    raise UnsupportedOp("graph without output")


def _as_arrays(value: Any, meta: Any) -> Any:
    """Tensors are always object arrays: indexing one element out of an array returns a bare node
    id, which must not be mistaken for a Python number later."""
    if isinstance(meta, torch.Tensor):
        return np.asarray(value, dtype=object) if not isinstance(value, np.ndarray) else value
    if isinstance(meta, (list, tuple)) and isinstance(value, (list, tuple)):
        return type(value)(_as_arrays(v, m) for v, m in zip(value, meta, strict=False))
    return value


_PY_OPS: dict[Callable[..., Any], Callable[..., Any]] = {
    operator.add: operator.add,
    operator.sub: operator.sub,
    operator.mul: operator.mul,
    operator.floordiv: operator.floordiv,
    operator.truediv: operator.truediv,
    operator.neg: operator.neg,
}

__all__ += ["UNIFORM"]
