"""C++ source of the sequence kernels: a filter run over ``T`` steps, forward and reverse.

One kernel call processes a range of *tiles*; a tile is one SIMD vector of trajectories (8
doubles or 16 floats).  Inside a tile the whole step is straight-line vector code, the belief
stays in registers from one step to the next, and nothing but the recorded outputs touches
memory.  Tiles are independent, so callers split them over threads.

Memory layout (``Bp`` = batch padded to whole vectors; element ``k`` of trajectory ``b``):

* ``state0 [S, Bp]`` - the belief before the first step, flattened;
* ``step_in [T, I, Bp]`` - per-step inputs (measurement, mask, controls);
* ``shared [T, J]`` - per-step inputs that are the same for every trajectory (e.g. a Kalman
  gain computed once for the batch), read once per step and broadcast;
* ``params [P]`` - the model parameters that train (the same for every trajectory);
* ``outs[g] [T, K_g, Bp]`` - recorded output groups (posterior, prior, log-likelihood...),
  which include the next belief so that the reverse kernel can restart every step from memory.

A filter whose belief gains entries in its first step (e.g. a residual statistic) has a
separate *first* step body from the initial layout to the steady one.

The reverse kernel walks the steps backwards, recomputes each step from the stored belief and
accumulates adjoints: ``g_outs[j]`` (gradients of the groups that have one) in, ``g_state0
[S, Bp]``, ``g_step [T, I, Bp]`` (optional) and ``g_params [tiles, P]`` (per-tile partial
sums) out, and ``g_shared [tiles, T, J]`` (per-tile sums over the lanes) when asked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .adjoint import ancestors, backprop, total
from .emit import Emitter, ctypes_of, prelude, split_levels, store
from .graph import LANE, UNIFORM, ScalarGraph

__all__ = ["BackwardSpec", "SequenceSpec", "StepBody", "backward_source", "forward_source"]


@dataclass
class StepBody:
    """One step as nodes: ``state_in[k]`` (belief element ``k`` before the step), ``step_in``,
    ``groups[g]`` (nodes of output group ``g``) and ``state_slot[k] = (g, i)`` (where the belief
    element ``k`` after the step is stored)."""

    state_in: list[int]
    step_in: list[int]
    groups: list[list[int]]
    state_slot: list[tuple[int, int]]
    shared_in: list[int] = field(default_factory=list)

    def state_out(self) -> list[int]:
        return [self.groups[g][i] for g, i in self.state_slot]


@dataclass
class SequenceSpec:
    """The steady step, an optional first step (same output groups, its own input layout) and
    the uniform ``params`` input nodes, all in ``graph``."""

    graph: ScalarGraph
    dtype: torch.dtype
    params: list[int]
    steady: StepBody
    first: StepBody | None = None

    @property
    def group_sizes(self) -> list[int]:
        return [len(g) for g in self.steady.groups]

    @property
    def initial(self) -> StepBody:
        """The body of step 0."""
        return self.first if self.first is not None else self.steady


def _bind_state(e: Emitter, body: StepBody, names: list[str]) -> list[str]:
    """Map the state input nodes to the state variables (stored as floats; booleans are read as
    ``!= 0``)."""
    out: list[str] = []
    for k, n in enumerate(body.state_in):
        if e.g.kind[n] == "b":
            out.append(f"const M v{n} = {names[k]} != bc(T(0));")
            e.vector[n] = f"v{n}"
        else:
            e.vector[n] = names[k]
    return out


def _bind_inputs(e: Emitter, body: StepBody, t: str) -> list[str]:
    """Load step ``t``'s per-trajectory inputs (vectors) and shared inputs (broadcast scalars)."""
    out = []
    for i, n in enumerate(body.step_in):
        out.append(f"const V v{n} = vload(step_in + ({t} * {len(body.step_in)} + {i}) * Bp + b0);")
        e.vector[n] = f"v{n}"
    for i, n in enumerate(body.shared_in):
        out.append(f"const V v{n} = bc(shared[{t} * {len(body.shared_in)} + {i}]);")
        e.vector[n] = f"v{n}"
    return out


def _as_float(e: Emitter, n: int, pre: list[str]) -> str:
    ref = e.vector_ref(n, pre)
    return f"({ref} ? bc(T(1)) : bc(T(0)))" if e.g.kind[n] == "b" else ref


def _body_forward(e: Emitter, body: StepBody, state_in: list[str], state_out: list[str], pre: list[str], t: str) -> list[str]:
    """Statements of one forward step reading the variables ``state_in`` and writing the next
    belief into ``state_out``."""
    g = e.g
    out = _bind_state(e, body, state_in)
    out += _bind_inputs(e, body, t)
    _, lane = split_levels(g, ancestors(g, [n for grp in body.groups for n in grp]))
    e.emit_vector(lane, out, pre)
    for gi, grp in enumerate(body.groups):
        out.append(f"{{ T* o = outs[{gi}] + {t} * {len(grp)} * Bp + b0;")
        out += [store(e, n, f"o + {j} * Bp", pre) for j, n in enumerate(grp)]
        out.append("}")
    nxt = [_as_float(e, n, pre) for n in body.state_out()]
    out += [f"V next{k} = {v};" for k, v in enumerate(nxt)]
    out += [f"{v} = next{k};" for k, v in enumerate(state_out)]
    return out


def forward_source(spec: SequenceSpec) -> str:
    """``extern "C" void forward(tile0, tile1, T, Bp, state0, step_in, shared, params, outs)``."""
    g = spec.graph
    e = Emitter(g, ctypes_of(spec.dtype)[0])
    for i, n in enumerate(spec.params):
        e.scalar[n] = f"params[{i}]"
    bodies = [b for b in (spec.first, spec.steady) if b is not None]
    uni, _ = split_levels(g, ancestors(g, [n for b in bodies for grp in b.groups for n in grp]))
    prologue: list[str] = []
    e.emit_scalar(uni, prologue)
    pre: list[str] = []
    init = spec.initial
    steady_state = [f"s{k}" for k in range(len(spec.steady.state_in))]
    lines = [f"V s{k};" for k in range(len(spec.steady.state_in))]
    if spec.first is not None:
        first_state = [f"f{k}" for k in range(len(init.state_in))]
        lines += ["{", *[f"const V f{k} = vload(state0 + {k} * Bp + b0);" for k in range(len(init.state_in))]]
        lines += [*_body_forward(e, spec.first, first_state, steady_state, pre, "0"), "}"]
        start = "1"
    else:
        lines += [f"s{k} = vload(state0 + {k} * Bp + b0);" for k in range(len(init.state_in))]
        start = "0"
    lines += [f"for (int64_t t = {start}; t < T_; ++t) {{", *_body_forward(e, spec.steady, steady_state, steady_state, pre, "t"), "}"]
    src = [
        prelude(spec.dtype),
        'extern "C" void forward(int64_t tile0, int64_t tile1, int64_t T_, int64_t Bp, const T* state0, const T* step_in, '
        "const T* shared, const T* params, T* const* outs) {",
        *prologue,
        *pre,
        "for (int64_t tile = tile0; tile < tile1; ++tile) {",
        "const int64_t b0 = tile * L;",
        *lines,
        "}",
        "}",
    ]
    return "\n".join(src) + "\n"


@dataclass(frozen=True)
class BackwardSpec:
    """Which gradients one reverse kernel takes and returns."""

    grad_groups: tuple[int, ...]  # output groups that receive a gradient, in the order of g_outs
    step_grad: bool  # whether the gradient w.r.t. every step input is wanted
    shared_grad: bool = False  # whether the gradient w.r.t. every shared input is wanted


@dataclass
class _Reverse:
    """One body's reverse step as nodes: adjoints of its state and step inputs, and the
    per-step contributions to uniform nodes."""

    gout: list[list[int]]
    gstate: list[int]
    prev_state: list[int]
    step_adj: list[int]
    boundary: dict[int, int]
    shared_adj: list[int]


def _reverse(g: ScalarGraph, body: StepBody, which: BackwardSpec) -> _Reverse:
    seeds: dict[int, list[int]] = {}
    gout: list[list[int]] = []
    for gi in which.grad_groups:
        nodes = [g.input(f"g_out{gi}", j) for j in range(len(body.groups[gi]))]
        gout.append(nodes)
        for n, node in zip(body.groups[gi], nodes, strict=True):
            seeds.setdefault(n, []).append(node)
    gstate = [g.input("g_state", k) for k in range(len(body.state_slot))]
    for n, node in zip(body.state_out(), gstate, strict=True):
        seeds.setdefault(n, []).append(node)
    adj, boundary = backprop(g, {n: total(g, ts) for n, ts in seeds.items()}, LANE)
    zero = g.const(0.0)
    prev = [adj.get(n, zero) for n in body.state_in]
    step_adj = [adj.get(n, zero) for n in body.step_in] if which.step_grad else []
    shared_adj = [adj.get(n, zero) for n in body.shared_in] if which.shared_grad else []
    return _Reverse(gout, gstate, prev, step_adj, boundary, shared_adj)


def _body_backward(e: Emitter, body: StepBody, rev: _Reverse, acc: dict[int, str], pre: list[str], t: str, carried: list[str]) -> list[str]:
    """Statements of one reverse step: reads the state variables ``s*`` and the carried adjoint
    ``carried``, leaves the adjoint of the step's input belief in ``gn*``."""
    g = e.g
    out = _bind_state(e, body, [f"s{k}" for k in range(len(body.state_in))])
    out += _bind_inputs(e, body, t)
    for j, nodes in enumerate(rev.gout):
        for i, n in enumerate(nodes):
            out.append(f"const V v{n} = vload(g_outs[{j}] + ({t} * {len(nodes)} + {i}) * Bp + b0);")
            e.vector[n] = f"v{n}"
    for k, n in enumerate(rev.gstate):
        e.vector[n] = carried[k]
    targets = rev.prev_state + rev.step_adj + rev.shared_adj + list(rev.boundary.values())
    _, lane = split_levels(g, ancestors(g, targets))
    e.emit_vector(lane, out, pre)
    out += [f"gn{k} = {e.vector_ref(n, pre)};" for k, n in enumerate(rev.prev_state)]
    out += [f"vstore(g_step + ({t} * {len(body.step_in)} + {i}) * Bp + b0, {e.vector_ref(n, pre)});" for i, n in enumerate(rev.step_adj)]
    ns = len(body.shared_in)
    out += [f"g_shared[(tile * T_ + {t}) * {ns} + {i}] = hsum({e.vector_ref(n, pre)});" for i, n in enumerate(rev.shared_adj)]
    out += [f"{acc[b]} += {e.vector_ref(v, pre)};" for b, v in rev.boundary.items()]
    return out


def backward_source(spec: SequenceSpec, which: BackwardSpec) -> str:
    """``extern "C" void backward(tile0, tile1, T, Bp, state0, step_in, shared, params, outs, g_outs,
    g_state0, g_step, g_shared, g_params)``."""
    g = spec.graph
    steady = _reverse(g, spec.steady, which)
    first = _reverse(g, spec.first, which) if spec.first is not None else None
    bnodes = sorted(set(steady.boundary) | set(first.boundary if first else ()))
    acc_in = [g.input("g_acc", i, level=UNIFORM) for i in range(len(bnodes))]
    # the uniform part's reverse sweep, seeded with the boundary adjoints summed over lanes and steps
    uadj, _ = backprop(g, dict(zip(bnodes, acc_in, strict=True)), UNIFORM)
    param_adj = [uadj.get(n, g.const(0.0)) for n in spec.params]

    e = Emitter(g, ctypes_of(spec.dtype)[0])
    for i, n in enumerate(spec.params):
        e.scalar[n] = f"params[{i}]"
    revs = [(spec.steady, steady)] + ([(spec.first, first)] if spec.first is not None and first is not None else [])
    targets = [n for _, r in revs for n in r.prev_state + r.step_adj + r.shared_adj + list(r.boundary.values())]
    uni, _ = split_levels(g, ancestors(g, targets))
    prologue: list[str] = []
    e.emit_scalar(uni, prologue)
    pre: list[str] = []
    acc = {b: f"acc{i}" for i, b in enumerate(bnodes)}
    ns = len(spec.steady.state_in)
    lines = [f"V s{k}, gs{k} = bc(T(0)), gn{k};" for k in range(ns)]
    lines += [f"V acc{i} = bc(T(0));" for i in range(len(bnodes))]
    stop = "1" if spec.first is not None else "0"
    load = []
    for k, (gi, i) in enumerate(spec.steady.state_slot):
        size = len(spec.steady.groups[gi])
        prev = f"vload(outs[{gi}] + ((t - 1) * {size} + {i}) * Bp + b0)"
        load.append(f"s{k} = {prev};" if spec.first is not None else f"s{k} = t > 0 ? {prev} : vload(state0 + {k} * Bp + b0);")
    carried = [f"gs{k}" for k in range(ns)]
    lines += [f"for (int64_t t = T_ - 1; t >= {stop}; --t) {{", *load, *_body_backward(e, spec.steady, steady, acc, pre, "t", carried)]
    lines += [f"gs{k} = gn{k};" for k in range(ns)] + ["}"]
    if spec.first is not None and first is not None:
        nf = len(spec.first.state_in)
        lines += ["{", *[f"V s{k} = vload(state0 + {k} * Bp + b0), gn{k};" for k in range(nf)]]
        lines += _body_backward(e, spec.first, first, acc, pre, "0", carried)
        lines += [f"vstore(g_state0 + {k} * Bp + b0, gn{k});" for k in range(nf)] + ["}"]
    else:
        lines += [f"vstore(g_state0 + {k} * Bp + b0, gs{k});" for k in range(ns)]
    epi_uni = sorted(n for n in ancestors(g, param_adj) if g.level[n] == UNIFORM and g.op[n] != "input")
    epilogue = [f"const T u{n} = hsum(acc{i});" for i, n in enumerate(acc_in)]
    for n in acc_in:
        e.scalar[n] = f"u{n}"
    e.emit_scalar(epi_uni, epilogue)
    epilogue += [f"g_params[tile * {len(spec.params)} + {i}] = {e.scalar_ref(n)};" for i, n in enumerate(param_adj)]
    src = [
        prelude(spec.dtype),
        'extern "C" void backward(int64_t tile0, int64_t tile1, int64_t T_, int64_t Bp, const T* state0, const T* step_in, '
        "const T* shared, const T* params, T* const* outs, T* const* g_outs, T* g_state0, T* g_step, T* g_shared, T* g_params) {",
        *prologue,
        *pre,
        "for (int64_t tile = tile0; tile < tile1; ++tile) {",
        "const int64_t b0 = tile * L;",
        *lines,
        *epilogue,
        "}",
        "}",
    ]
    return "\n".join(src) + "\n"
