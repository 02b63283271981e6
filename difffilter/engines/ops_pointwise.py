"""ATen element-wise, comparison, conversion and creation operations on object arrays of scalar nodes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import fx

from .graph import CMP_OPS, UnsupportedOp
from .ops import Lowering, filled

__all__ = ["MISSING", "lower_pointwise"]

#: returned when the operation is not one of this module's
MISSING = object()

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


def lower_pointwise(L: Lowering, name: str, args: tuple, kw: dict[str, Any], node: fx.Node) -> Any:  # noqa: C901 - one table of cases
    """``aten.<name>(*args, **kw)`` if element-wise or a creation op, else :data:`MISSING`."""
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
    if name == "nextafter":  # constants only (a constraint's open bounds), in the kernel's dtype
        a, b = np.broadcast_arrays(L.fl(a0), L.fl(args[1]))
        if not all(g.is_const(int(x)) for x in (*a.reshape(-1), *b.reshape(-1))):
            raise UnsupportedOp("nextafter of values that are not constants")

        def after(x: int, y: int) -> int:
            towards = torch.nextafter(torch.tensor(g.value[x], dtype=L.dtype), torch.tensor(g.value[y], dtype=L.dtype))
            return g.const(towards.item())

        return np.asarray(np.frompyfunc(after, 2, 1)(a, b), dtype=object)
    if name == "hypot":  # sqrt(a^2 + b^2): its reverse derivative comes from the scalar graph
        return L.unary("sqrt", L.binary("add", L.binary("mul", a0, a0), L.binary("mul", args[1], args[1])))
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
    if name == "fill":
        return filled(L, L.arr(a0).shape, args[1], node.meta["val"].dtype)
    if name == "_efficientzerotensor":
        return filled(L, a0, 0.0, kw.get("dtype"))
    if name in ("zeros", "ones", "full", "empty", "new_zeros", "new_ones", "new_full", "new_empty", "scalar_tensor"):
        if name == "scalar_tensor":
            return L.fl(a0) if kw.get("dtype") != torch.bool else L.bo(a0)
        shape = args[1] if name.startswith("new_") else a0
        value = {"zeros": 0.0, "ones": 1.0, "empty": 0.0, "new_zeros": 0.0, "new_ones": 1.0, "new_empty": 0.0}.get(name)
        if value is None:
            value = args[2] if name == "new_full" else args[1]
        return filled(L, shape, value, kw.get("dtype"))
    if name in ("zeros_like", "ones_like", "full_like", "empty_like"):
        shape = L.arr(a0).shape
        value = {"zeros_like": 0.0, "ones_like": 1.0, "empty_like": 0.0}.get(name, args[1] if len(args) > 1 else None)
        dtype = kw.get("dtype") or node.meta["val"].dtype
        return filled(L, shape, value, dtype)
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
    return MISSING
