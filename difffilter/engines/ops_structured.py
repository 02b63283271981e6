"""ATen view, indexing, concatenation, reduction and linear-algebra operations on object arrays of scalar nodes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import fx

from .graph import ScalarGraph, UnsupportedOp
from .ops import Lowering, dim_index

__all__ = ["const_index", "data_index", "lower_structured"]


def lower_structured(L: Lowering, name: str, args: tuple, kw: dict[str, Any], node: fx.Node) -> Any:  # noqa: C901 - one table of cases
    """``aten.<name>(*args, **kw)`` for views, indexing, reductions and linear algebra."""
    g = L.g
    a0 = args[0] if args else None
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
        return np.expand_dims(x, dim_index(args[1], x.ndim + 1))
    if name == "squeeze":
        x = L.arr(a0)
        dims = args[1] if len(args) > 1 else [i for i, s in enumerate(x.shape) if s == 1]
        dims = [dims] if isinstance(dims, int) else list(dims)
        dims = tuple(dim_index(d, x.ndim) for d in dims if x.shape[dim_index(d, x.ndim)] == 1) if x.ndim else ()
        return np.squeeze(x, axis=dims) if dims else x
    if name == "select":
        x = L.arr(a0)
        return np.take(x, args[2], axis=dim_index(args[1], x.ndim))
    if name == "slice":
        x = L.arr(a0)
        d = dim_index(args[1] if len(args) > 1 else 0, x.ndim)
        start = args[2] if len(args) > 2 else None
        end = args[3] if len(args) > 3 else None
        step = args[4] if len(args) > 4 else 1
        sl = [slice(None)] * x.ndim
        sl[d] = slice(start, None if end is not None and end >= 2**62 else end, step)
        return x[tuple(sl)]
    if name == "narrow":
        x = L.arr(a0)
        d = dim_index(args[1], x.ndim)
        sl = [slice(None)] * x.ndim
        sl[d] = slice(args[2], args[2] + args[3])
        return x[tuple(sl)]
    if name == "unbind":
        x = L.arr(a0)
        d = dim_index(args[1] if len(args) > 1 else 0, x.ndim)
        return [np.take(x, i, axis=d) for i in range(x.shape[d])]
    if name in ("split", "split_with_sizes"):
        x = L.arr(a0)
        d = dim_index(args[2] if len(args) > 2 else kw.get("dim", 0), x.ndim)
        sizes = args[1]
        if isinstance(sizes, int):
            sizes = [sizes] * (x.shape[d] // sizes) + ([x.shape[d] % sizes] if x.shape[d] % sizes else [])
        cuts = np.cumsum(sizes)[:-1]
        return list(np.split(x, cuts, axis=d))
    if name in ("cat", "concat"):
        tensors = [L.arr(t) for t in a0 if L.arr(t).size or L.arr(t).ndim > 1]
        d = args[1] if len(args) > 1 else kw.get("dim", 0)
        return np.concatenate(tensors, axis=dim_index(d, tensors[0].ndim))
    if name == "stack":
        tensors = [L.arr(t) for t in a0]
        d = args[1] if len(args) > 1 else kw.get("dim", 0)
        return np.stack(tensors, axis=dim_index(d, tensors[0].ndim + 1))
    if name == "flip":
        return np.flip(L.arr(a0), axis=tuple(args[1]))
    if name == "diagonal":
        x = L.arr(a0)
        off = args[1] if len(args) > 1 else kw.get("offset", 0)
        d1 = dim_index(args[2] if len(args) > 2 else kw.get("dim1", 0), x.ndim)
        d2 = dim_index(args[3] if len(args) > 3 else kw.get("dim2", 1), x.ndim)
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
        try:
            return L.arr(a0)[const_index(g, args[1])]
        except UnsupportedOp:
            return data_index(L, L.arr(a0), args[1], node)
    if name == "index_put":
        x = L.arr(a0).copy()
        accumulate = args[3] if len(args) > 3 else kw.get("accumulate", False)
        pos = np.arange(x.size).reshape(x.shape)[const_index(g, args[1])]
        vals = np.broadcast_to(L.arr(args[2]), pos.shape)
        flat = x.reshape(-1)
        for p_, v in zip(pos.reshape(-1).tolist(), vals.reshape(-1).tolist(), strict=True):
            flat[p_] = g.binary("add", flat[p_], v) if accumulate else v
        return flat.reshape(x.shape)
    if name == "index_select":
        x = L.arr(a0)
        ids = [int(g.value[v]) for v in L.arr(args[2]).reshape(-1)]
        return np.take(x, ids, axis=dim_index(args[1], x.ndim))
    if name in ("select_scatter", "slice_scatter", "diagonal_scatter"):
        x = L.arr(a0).copy()
        src = L.arr(args[1])
        if name == "select_scatter":
            d = dim_index(args[2], x.ndim)
            sl = [slice(None)] * x.ndim
            # a length-one slice, not the integer: assigned to a single element of an object
            # array, a 0-d source array would be stored as the element itself (not its node)
            k = args[3] % x.shape[d]
            sl[d] = slice(k, k + 1)
            src = np.expand_dims(src, d)
        elif name == "slice_scatter":
            d = dim_index(args[2] if len(args) > 2 else kw.get("dim", 0), x.ndim)
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
            out = np.squeeze(out, axis=tuple(dim_index(d, x.ndim) for d in ([dims] if isinstance(dims, int) else dims)))
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
            return (
                L.matmul(a[None, :], b if b.ndim > 1 else b[:, None])[..., 0, :] if b.ndim > 1 else L.matmul(a[None, :], b[:, None])[0, 0]
            )
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
        q, r = L.qr(L.fl(a0), mode == "reduced")
        return (q if mode == "reduced" else np.empty((0,), dtype=object)), r
    if name == "linalg_cholesky_ex":
        if args[1] if len(args) > 1 else kw.get("upper", False):
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
    raise UnsupportedOp(f"aten.{name}")


def const_index(g: ScalarGraph, indices: Any) -> tuple[Any, ...]:
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


def data_index(L: Lowering, x: Any, indices: Any, node: fx.Node) -> Any:
    """``x[..., idx, ...]`` with one integer index ``idx`` whose values are data (e.g. a group
    label among the controls picking one of a few learned scales): per element, a chain of
    selections over the indexed dimension's ``size`` entries (negative indices as torch reads
    them).  Boolean or several data-dependent indices are refused (their result's shape or
    pairing depends on the data)."""
    g = L.g
    dims = [i for i, v in enumerate(indices) if v is not None]
    if len(dims) != 1:
        raise UnsupportedOp("indexing with several data-dependent indices")
    d = dims[0]
    meta = node.args[1][d].meta.get("val") if isinstance(node.args[1][d], fx.Node) else None
    if meta is None or meta.dtype == torch.bool or meta.dtype.is_floating_point:
        raise UnsupportedOp("indexing with a data-dependent boolean index")
    idx = L.fl(indices[d])
    size = x.shape[d]
    if size == 0:
        raise UnsupportedOp("indexing an empty dimension")
    lead, rest = x.shape[:d], x.shape[d + 1 :]
    hits = {}
    for ii in np.ndindex(*idx.shape):
        iv = idx[ii]
        hits[ii] = [
            g.logical("or", g.compare("eq", iv, g.const(float(k))), g.compare("eq", iv, g.const(float(k - size)))) for k in range(size)
        ]
    out = np.empty(lead + idx.shape + rest, dtype=object)
    for li in np.ndindex(*lead):
        for ii in np.ndindex(*idx.shape):
            for ri in np.ndindex(*rest):
                val = x[li + (size - 1,) + ri]
                for k in range(size - 2, -1, -1):
                    val = g.where(hits[ii][k], x[li + (k,) + ri], val)
                out[li + ii + ri] = val
    return out
