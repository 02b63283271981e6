"""C++ source of the sequence kernels: a filter run over ``T`` steps, forward and reverse.

One kernel call processes a range of *tiles*; a tile is one SIMD vector of trajectories (``L``
lanes: 8 doubles or 16 floats in 64 bytes).  Inside a tile the whole step is straight-line
vector code, the belief stays in registers from one step to the next, and nothing but the
recorded outputs touches memory.  Tiles are independent, so callers split them over threads.

Memory layout (``Bp`` = batch padded to a multiple of ``L``; element ``k`` of trajectory ``b``):

* ``state0 [S, Bp]`` - the belief before the first step, flattened;
* ``step_in [T, I, Bp]`` - per-step inputs (measurement, mask, controls);
* ``params [P]`` - model parameters and buffers (the same for every trajectory);
* ``out [T, O, Bp]`` - recorded outputs (posterior, prior, log-likelihood...), which include
  the next belief so that the reverse kernel can restart every step from memory.

The reverse kernel walks the steps backwards, recomputes each step from the stored belief and
accumulates adjoints: ``g_out [T, G, Bp]`` (gradients of the outputs that have one) in,
``g_state0 [S, Bp]``, ``g_step [T, I', Bp]`` and ``g_params [tiles, P]`` out.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch

from .adjoint import ancestors, backprop, total
from .graph import CONST, LANE, UNIFORM, ScalarGraph, UnsupportedOp

__all__ = ["SequenceSpec", "forward_source", "backward_source", "VECTOR_BYTES"]

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


@dataclass
class SequenceSpec:
    """What one step reads and writes, as nodes of ``graph``.

    ``state_in[k]`` is the belief element ``k`` before the step, ``step_in`` the per-step inputs
    and ``params`` the uniform inputs.  ``groups[g]`` lists the nodes of output group ``g``
    (stored as ``[T, len(groups[g]), Bp]``); ``state_slot[k] = (g, i)`` says where the belief
    element ``k`` after the step is stored.
    """

    graph: ScalarGraph
    dtype: torch.dtype
    state_in: list[int]
    step_in: list[int]
    params: list[int]
    groups: list[list[int]]
    state_slot: list[tuple[int, int]]

    def state_out(self) -> list[int]:
        return [self.groups[g][i] for g, i in self.state_slot]


def _literal(v: float | bool, ctype: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if math.isnan(v):
        return "std::numeric_limits<T>::quiet_NaN()"
    if math.isinf(v):
        return ("-" if v < 0 else "") + "std::numeric_limits<T>::infinity()"
    return f"T({v!r})"


class _Emitter:
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


def _ctypes(dtype: torch.dtype) -> tuple[str, str]:
    if dtype == torch.float64:
        return "double", "int64_t"
    if dtype == torch.float32:
        return "float", "int32_t"
    raise UnsupportedOp(f"dtype {dtype}")


def _prelude(dtype: torch.dtype) -> str:
    ctype, itype = _ctypes(dtype)
    return _PRELUDE.format(ctype=ctype, itype=itype, vbytes=VECTOR_BYTES)


def _split(g: ScalarGraph, nodes: set[int]) -> tuple[list[int], list[int]]:
    uni = sorted(n for n in nodes if g.level[n] == UNIFORM and g.op[n] != "input")
    lane = sorted(n for n in nodes if g.level[n] == LANE and g.op[n] != "input")
    return uni, lane


def _store(e: _Emitter, n: int, ptr: str, pre: list[str]) -> str:
    if e.g.kind[n] == "b":
        return f"vstore({ptr}, {e.vector_ref(n, pre)} ? bc(T(1)) : bc(T(0)));"
    return f"vstore({ptr}, {e.vector_ref(n, pre)});"


def forward_source(spec: SequenceSpec) -> str:
    """``extern "C" void forward(tile0, tile1, T, Bp, state0, step_in, params, outs)``; ``outs[g]``
    points to output group ``g``."""
    g = spec.graph
    ctype, _ = _ctypes(spec.dtype)
    e = _Emitter(g, ctype)
    need = ancestors(g, [n for grp in spec.groups for n in grp])
    uni, lane = _split(g, need)
    for i, n in enumerate(spec.params):
        e.scalar[n] = f"params[{i}]"
    prologue: list[str] = []
    e.emit_scalar(uni, prologue)
    pre: list[str] = []
    loop: list[str] = []
    for k, n in enumerate(spec.state_in):
        e.vector[n] = f"s{k}"
    for i, n in enumerate(spec.step_in):
        loop.append(f"const V v{n} = vload(xin + {i} * Bp);")
        e.vector[n] = f"v{n}"
    e.emit_vector(lane, loop, pre)
    for gi, grp in enumerate(spec.groups):
        loop.append(f"T* o{gi} = outs[{gi}] + t * {len(grp)} * Bp + b0;")
        loop += [_store(e, n, f"o{gi} + {j} * Bp", pre) for j, n in enumerate(grp)]
    nxt = [f"s{k} = {e.vector_ref(n, pre)};" for k, n in enumerate(spec.state_out())]
    body = [
        _prelude(spec.dtype),
        'extern "C" void forward(int64_t tile0, int64_t tile1, int64_t T_, int64_t Bp, const T* state0, const T* step_in, '
        "const T* params, T* const* outs) {",
        *prologue,
        *pre,
        "for (int64_t tile = tile0; tile < tile1; ++tile) {",
        "const int64_t b0 = tile * L;",
        *[f"V s{k} = vload(state0 + {k} * Bp + b0);" for k in range(len(spec.state_in))],
        "for (int64_t t = 0; t < T_; ++t) {",
        f"const T* xin = step_in + t * {len(spec.step_in)} * Bp + b0;",
        *loop,
        *nxt,
        "}",
        "}",
        "}",
    ]
    return "\n".join(body) + "\n"


@dataclass(frozen=True)
class BackwardSpec:
    """Which gradients one reverse kernel takes and returns."""

    grad_groups: tuple[int, ...]  # output groups that receive a gradient, in the order of g_outs
    step_grad: bool  # whether the gradient w.r.t. every step input is wanted


def backward_source(spec: SequenceSpec, which: BackwardSpec) -> str:
    """``extern "C" void backward(tile0, tile1, T, Bp, state0, step_in, params, outs, g_outs,
    g_state0, g_step, g_params)``; ``g_params [tiles, P]`` holds each tile's partial sum and
    ``g_step [T, I, Bp]`` is written only if ``which.step_grad``."""
    g = spec.graph
    ctype, _ = _ctypes(spec.dtype)
    # seeds: output gradients and the adjoint of the next belief (carried from step t + 1)
    seeds: dict[int, list[int]] = {}
    gout: list[list[int]] = []
    for gi in which.grad_groups:
        nodes = [g.input(f"g_out{gi}", j) for j in range(len(spec.groups[gi]))]
        gout.append(nodes)
        for n, node in zip(spec.groups[gi], nodes, strict=True):
            seeds.setdefault(n, []).append(node)
    gstate = [g.input("g_state", k) for k in range(len(spec.state_in))]
    for n, node in zip(spec.state_out(), gstate, strict=True):
        seeds.setdefault(n, []).append(node)
    adj, boundary = backprop(g, {n: total(g, ts) for n, ts in seeds.items()}, LANE)
    prev_state = [adj.get(n, g.const(0.0)) for n in spec.state_in]
    step_adj = [adj.get(n, g.const(0.0)) for n in spec.step_in] if which.step_grad else []
    bnodes = sorted(boundary)
    acc = [g.input("g_acc", i, level=UNIFORM) for i in range(len(bnodes))]
    # seeds of the uniform part: boundary adjoints summed over lanes and steps
    uadj, _ = backprop(g, dict(zip(bnodes, acc, strict=True)), UNIFORM)
    param_adj = [uadj.get(n, g.const(0.0)) for n in spec.params]

    e = _Emitter(g, ctype)
    for i, n in enumerate(spec.params):
        e.scalar[n] = f"params[{i}]"
    need = ancestors(g, prev_state + step_adj + [boundary[b] for b in bnodes])
    uni, lane = _split(g, need)
    prologue: list[str] = []
    e.emit_scalar(uni, prologue)
    pre: list[str] = []
    loop: list[str] = []
    for k, n in enumerate(spec.state_in):
        e.vector[n] = f"s{k}"
    for i, n in enumerate(spec.step_in):
        loop.append(f"const V v{n} = vload(xin + {i} * Bp);")
        e.vector[n] = f"v{n}"
    for j, nodes in enumerate(gout):
        loop.append(f"const T* gin{j} = g_outs[{j}] + t * {len(nodes)} * Bp + b0;")
        for i, n in enumerate(nodes):
            loop.append(f"const V v{n} = vload(gin{j} + {i} * Bp);")
            e.vector[n] = f"v{n}"
    for k, n in enumerate(gstate):
        e.vector[n] = f"gs{k}"
    e.emit_vector(lane, loop, pre)
    loop += [f"gs_next{k} = {e.vector_ref(n, pre)};" for k, n in enumerate(prev_state)]
    loop += [f"vstore(gx + {i} * Bp, {e.vector_ref(n, pre)});" for i, n in enumerate(step_adj)]
    loop += [f"acc{i} += {e.vector_ref(boundary[b], pre)};" for i, b in enumerate(bnodes)]
    loop += [f"gs{k} = gs_next{k};" for k in range(len(spec.state_in))]
    # epilogue: the uniform part's reverse sweep, on this tile's accumulated adjoints
    epi_uni = sorted(n for n in ancestors(g, param_adj) if g.level[n] == UNIFORM and g.op[n] != "input")
    epilogue = [f"const T u{n} = hsum(acc{i});" for i, n in enumerate(acc)]
    for n in acc:
        e.scalar[n] = f"u{n}"
    e.emit_scalar(epi_uni, epilogue)
    epilogue += [f"g_params[tile * {len(spec.params)} + {i}] = {e.scalar_ref(n)};" for i, n in enumerate(param_adj)]
    nin = len(spec.step_in)
    load_state = []
    for k, (gi, i) in enumerate(spec.state_slot):
        size = len(spec.groups[gi])
        load_state.append(f"s{k} = t > 0 ? vload(outs[{gi}] + ((t - 1) * {size} + {i}) * Bp + b0) : vload(state0 + {k} * Bp + b0);")
    src = [
        _prelude(spec.dtype),
        'extern "C" void backward(int64_t tile0, int64_t tile1, int64_t T_, int64_t Bp, const T* state0, const T* step_in, '
        "const T* params, T* const* outs, T* const* g_outs, T* g_state0, T* g_step, T* g_params) {",
        *prologue,
        *pre,
        "for (int64_t tile = tile0; tile < tile1; ++tile) {",
        "const int64_t b0 = tile * L;",
        *[f"V s{k}, gs{k} = bc(T(0)), gs_next{k};" for k in range(len(spec.state_in))],
        *[f"V acc{i} = bc(T(0));" for i in range(len(bnodes))],
        "for (int64_t t = T_ - 1; t >= 0; --t) {",
        *load_state,
        f"const T* xin = step_in + t * {nin} * Bp + b0;",
        f"T* gx = g_step + t * {nin} * Bp + b0;" if which.step_grad else "",
        *loop,
        "}",
        *[f"vstore(g_state0 + {k} * Bp + b0, gs{k});" for k in range(len(spec.state_in))],
        *epilogue,
        "}",
        "}",
    ]
    return "\n".join(src) + "\n"


def count_statements(source: str) -> int:
    return source.count(";")


__all__ += ["BackwardSpec", "count_statements"]
