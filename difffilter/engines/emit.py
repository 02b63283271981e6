"""C++ building blocks of the generated kernels: the vector prelude and the statement emitter.

Values of one trajectory are lanes of a GCC vector (``V``: ``VECTOR_BYTES`` bytes, 8 doubles or
16 floats); booleans are integer masks (``M``).  Values the same for every trajectory are plain
scalars, broadcast once where vector code reads them.  Functions without a vector instruction
(``exp``, ``atan2``...) run lane by lane.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

from .graph import CONST, LANE, UNIFORM, ScalarGraph, UnsupportedOp

__all__ = ["VECTOR_BYTES", "Emitter", "ctypes_of", "prelude", "split_levels", "store"]

VECTOR_BYTES = 64

_PRELUDE = r"""
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
typedef {ctype} T;
typedef T V __attribute__((vector_size({vbytes})));
typedef {itype} M __attribute__((vector_size({vbytes})));
enum {{ L = {vbytes} / sizeof(T) }};
static inline V vload(const T* p) {{ V v; std::memcpy(&v, p, sizeof(V)); return v; }}
static inline void vstore(T* p, V v) {{ std::memcpy(p, &v, sizeof(V)); }}
static inline V bc(T x) {{ V v; for (int i = 0; i < L; ++i) v[i] = x; return v; }}
static inline M bcm(bool x) {{ M v; for (int i = 0; i < L; ++i) v[i] = x ? -1 : 0; return v; }}
static inline T hsum(V a) {{ T s = 0; for (int i = 0; i < L; ++i) s += a[i]; return s; }}
static inline T s_sigmoid(T x) {{ return x >= 0 ? T(1) / (T(1) + std::exp(-x)) : std::exp(x) / (T(1) + std::exp(x)); }}
static inline T s_softplus(T x) {{ return x > 0 ? x + std::log1p(std::exp(-x)) : std::log1p(std::exp(x)); }}
static inline T s_sign(T x) {{ return T((x > 0) - (x < 0)); }}
static inline T s_abs(T x) {{ return std::fabs(x); }}
#define VF1(name, fn) static inline V v_##name(V a) {{ V r; for (int i = 0; i < L; ++i) r[i] = fn(a[i]); return r; }}
#define VF2(name, fn) static inline V v_##name(V a, V b) {{ V r; for (int i = 0; i < L; ++i) r[i] = fn(a[i], b[i]); return r; }}
VF1(sqrt, std::sqrt) VF1(exp, std::exp) VF1(log, std::log) VF1(log1p, std::log1p) VF1(expm1, std::expm1)
VF1(sin, std::sin) VF1(cos, std::cos) VF1(tan, std::tan) VF1(atan, std::atan) VF1(asin, std::asin)
VF1(acos, std::acos) VF1(tanh, std::tanh) VF1(sinh, std::sinh) VF1(cosh, std::cosh) VF1(sigmoid, s_sigmoid)
VF1(softplus, s_softplus) VF1(abs, s_abs) VF1(floor, std::floor) VF1(ceil, std::ceil) VF1(round, std::nearbyint)
VF1(sign, s_sign) VF2(pow, std::pow) VF2(atan2, std::atan2) VF2(fmod, std::fmod)
"""

_INFIX = {"add": "+", "sub": "-", "mul": "*", "div": "/"}
_CMP = {"gt": ">", "ge": ">=", "lt": "<", "le": "<=", "eq": "==", "ne": "!="}
_SCALAR_FN = {
    "sqrt": "std::sqrt", "exp": "std::exp", "log": "std::log", "log1p": "std::log1p", "expm1": "std::expm1",
    "sin": "std::sin", "cos": "std::cos", "tan": "std::tan", "atan": "std::atan", "asin": "std::asin",
    "acos": "std::acos", "tanh": "std::tanh", "sinh": "std::sinh", "cosh": "std::cosh", "sigmoid": "s_sigmoid",
    "softplus": "s_softplus", "abs": "s_abs", "floor": "std::floor", "ceil": "std::ceil", "round": "std::nearbyint",
    "sign": "s_sign", "pow": "std::pow", "atan2": "std::atan2", "fmod": "std::fmod",
}  # fmt: skip


def _literal(v: float | bool, ctype: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if math.isnan(v):
        return "std::numeric_limits<T>::quiet_NaN()"
    if math.isinf(v):
        return ("-" if v < 0 else "") + "std::numeric_limits<T>::infinity()"
    return f"T({v!r})"


class Emitter:
    """Names and statements for the nodes of one kernel."""

    def __init__(self, g: ScalarGraph, ctype: str) -> None:
        self.g = g
        self.ctype = ctype
        self.scalar: dict[int, str] = {}  # node -> scalar (uniform) variable
        self.vector: dict[int, str] = {}  # node -> vector variable
        self.lines: list[str] = []

    def scalar_ref(self, n: int) -> str:
        g = self.g
        if g.level[n] == CONST:
            return _literal(g.value[n], self.ctype)  # type: ignore[arg-type]
        return self.scalar[n]

    def vector_ref(self, n: int, pre: list[str]) -> str:
        """Vector name of node ``n``; constants and uniform values are broadcast once, in ``pre``."""
        name = self.vector.get(n)
        if name is not None:
            return name
        g = self.g
        if g.level[n] == LANE:
            raise UnsupportedOp(f"internal: lane node {n} used before it is computed")
        name = f"b{n}"
        fn = "bcm" if g.kind[n] == "b" else "bc"
        pre.append(f"const {'M' if g.kind[n] == 'b' else 'V'} {name} = {fn}({self.scalar_ref(n)});")
        self.vector[n] = name
        return name

    def expr(self, n: int, ref) -> str:  # type: ignore[no-untyped-def]
        g = self.g
        op, args = g.op[n], [ref(a) for a in g.args[n]]
        vec = ref.__name__ == "vref"
        if op in _INFIX:
            return f"{args[0]} {_INFIX[op]} {args[1]}"
        if op == "neg":
            return f"-{args[0]}"
        if op in _CMP:
            return f"{args[0]} {_CMP[op]} {args[1]}"
        if op in ("max", "min"):
            cmp = ">=" if op == "max" else "<="
            return f"{args[0]} {cmp} {args[1]} ? {args[0]} : {args[1]}"
        if op == "where":
            return f"{args[0]} ? {args[1]} : {args[2]}"
        if op == "and":
            return f"{args[0]} {'&' if vec else '&&'} {args[1]}"
        if op == "or":
            return f"{args[0]} {'|' if vec else '||'} {args[1]}"
        if op == "xor":
            return f"{args[0]} {'^' if vec else '!='} {args[1]}"
        if op == "not":
            return f"{'~' if vec else '!'}{args[0]}"
        if op in _SCALAR_FN:
            fn = f"v_{op}" if vec else _SCALAR_FN[op]
            return f"{fn}({', '.join(args)})"
        raise UnsupportedOp(f"no C++ for scalar op {op}")

    def emit_scalar(self, nodes: Iterable[int], out: list[str]) -> None:
        g = self.g

        def sref(a: int) -> str:
            return self.scalar_ref(a)

        for n in nodes:
            if n in self.scalar or g.level[n] == CONST:
                continue
            name = f"u{n}"
            out.append(f"const {'bool' if g.kind[n] == 'b' else 'T'} {name} = {self.expr(n, sref)};")
            self.scalar[n] = name

    def emit_vector(self, nodes: Iterable[int], out: list[str], pre: list[str]) -> None:
        g = self.g

        def vref(a: int) -> str:
            return self.vector_ref(a, pre)

        for n in nodes:
            if n in self.vector:
                continue
            name = f"v{n}"
            out.append(f"const {'M' if g.kind[n] == 'b' else 'V'} {name} = {self.expr(n, vref)};")
            self.vector[n] = name


def ctypes_of(dtype: torch.dtype) -> tuple[str, str]:
    if dtype == torch.float64:
        return "double", "int64_t"
    if dtype == torch.float32:
        return "float", "int32_t"
    raise UnsupportedOp(f"dtype {dtype}")


def prelude(dtype: torch.dtype) -> str:
    ctype, itype = ctypes_of(dtype)
    return _PRELUDE.format(ctype=ctype, itype=itype, vbytes=VECTOR_BYTES)


def split_levels(g: ScalarGraph, nodes: set[int]) -> tuple[list[int], list[int]]:
    uni = sorted(n for n in nodes if g.level[n] == UNIFORM and g.op[n] != "input")
    lane = sorted(n for n in nodes if g.level[n] == LANE and g.op[n] != "input")
    return uni, lane


def store(e: Emitter, n: int, ptr: str, pre: list[str]) -> str:
    if e.g.kind[n] == "b":
        return f"vstore({ptr}, {e.vector_ref(n, pre)} ? bc(T(1)) : bc(T(0)));"
    return f"vstore({ptr}, {e.vector_ref(n, pre)});"
