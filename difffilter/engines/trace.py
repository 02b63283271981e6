"""Trace one step of a filter (its own ``predict``/``update``) and lower it to a scalar graph.

The step traced is exactly the body of :meth:`RecursiveFilter.forward`'s loop: ``predict``,
``update``, ``finalize_belief`` and ``record``, on a belief of batch size one.  It is traced with
fake tensors (``make_fx``), so any Python decision on the *values* of the belief or the data
fails the trace (and the caller falls back to another engine) instead of being frozen into the
kernel.  The linear-algebra helpers that make such decisions are replaced by branch-free
equivalents while tracing (:func:`_traceable`).

Model parameters that require a gradient become inputs of the kernel; buffers and frozen
parameters are folded in as constants (their values are part of :func:`fingerprint`, so a
changed value means a new kernel).
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.func import functional_call
from torch.fx.experimental.proxy_tensor import make_fx

from ..filters.base import RecursiveFilter
from .branchfree import branch_free as _traceable
from .branchfree import step_flag as _step_flag
from .codegen import SequenceSpec, StepBody
from .graph import LANE, UNIFORM, ScalarGraph, UnsupportedOp
from .lower import lower

__all__ = ["StepLayout", "TracedStep", "eager_steps", "fingerprint", "trace_step"]

_TRACE_LOCK = threading.Lock()
#: largest step (scalar operations of the forward) the generated engine compiles; the code is fully
#: unrolled, and its reverse sweep is ~3x larger (p003's 20-state IMM bank, 8 satellites: 394k
#: operations, a 14 MB forward kernel that took 12 min and 6 GB to build at -O2 on the 2-core machine)
MAX_NODES = 100_000
_RESULT_KEYS = ("prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed", "step_untrusted")


@dataclass(frozen=True)
class StepLayout:
    """Names and per-trajectory shapes of the belief, the step inputs and the controls."""

    belief: tuple[tuple[str, tuple[int, ...], torch.dtype], ...]  # (key, per-trajectory shape, dtype)
    measurement_dim: int
    has_mask: bool
    controls: tuple[tuple[str, tuple[int, ...], torch.dtype], ...] | None  # None: no controls; key "" for a bare tensor
    dtype: torch.dtype
    shared: tuple[str, ...] = ()  # keys of the controls that are the same for every trajectory (kernel input ``shared``)

    @property
    def state_size(self) -> int:
        return sum(math.prod(s) for _, s, _ in self.belief)

    @property
    def step_size(self) -> int:
        ctrl = sum(math.prod(s) for k, s, _ in self.controls if k not in self.shared) if self.controls else 0
        return self.measurement_dim * (2 if self.has_mask else 1) + ctrl

    @property
    def shared_size(self) -> int:
        return sum(math.prod(s) for k, s, _ in self.controls if k in self.shared) if self.controls else 0


@dataclass
class TracedStep:
    """A lowered step: the kernel specification and how outputs map to result fields.

    ``fields[name] = (group, offset, shape)``: where field ``name`` (``mean``, ``cov``,
    ``prior_mean``, ..., every belief key and every recorded key) is stored, and its
    per-trajectory shape.  ``layout.belief`` is the belief before the first step.
    """

    spec: SequenceSpec
    layout: StepLayout
    params: list[tuple[str, Tensor]]
    fields: dict[str, tuple[int, int, tuple[int, ...]]]
    record_keys: tuple[str, ...]
    belief_keys: tuple[str, ...]  # entries of the belief after a step (``final_belief``)
    dtypes: dict[str, torch.dtype]  # of the belief entries and recorded values (others: the kernel's)


def _plain_state(obj: Any, depth: int = 0) -> list[Any]:
    """Scalar configuration reachable from ``obj``'s attributes (flags, sigma-point settings)."""
    out: list[Any] = []
    if depth > 3:
        return out
    items = vars(obj).items() if hasattr(obj, "__dict__") else ()
    for k, v in sorted(items, key=lambda kv: kv[0]):
        if k.startswith("_") and k not in ("_static_q",):
            continue
        if isinstance(v, (bool, int, float, str, type(None))):
            out.append((k, v))
        elif isinstance(v, (tuple, list)) and all(isinstance(x, (bool, int, float, str)) for x in v):
            out.append((k, tuple(v)))
        elif not isinstance(v, (Tensor, nn.Module)) and hasattr(v, "__dict__") and not callable(v):
            out.append((k, type(v).__qualname__, _plain_state(v, depth + 1)))
    return out


def fingerprint(filt: nn.Module) -> str:
    """Hash of what the traced kernel depends on besides its inputs: module types, plain
    attributes, which parameters train, and the values of buffers and frozen parameters."""
    h = hashlib.sha256()
    for name, mod in filt.named_modules():
        h.update(f"{name}:{type(mod).__module__}.{type(mod).__qualname__}:{_plain_state(mod)!r}".encode())
    for name, t in list(filt.named_parameters()) + list(filt.named_buffers()):
        trains = t.requires_grad
        h.update(f"{name}:{tuple(t.shape)}:{t.dtype}:{trains}".encode())
        if not trains:
            h.update(t.detach().cpu().contiguous().numpy().tobytes() if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())
    return h.hexdigest()


def _unflatten_controls(layout: StepLayout, flat: list[Tensor]) -> Any:
    if layout.controls is None:
        return None
    vals = [t.to(dt) if dt != layout.dtype else t for t, (_, _, dt) in zip(flat, layout.controls, strict=True)]
    if len(layout.controls) == 1 and layout.controls[0][0] == "":
        return vals[0]
    return {k: v for (k, _, _), v in zip(layout.controls, vals, strict=True)}


class _StepBody(nn.Module):
    """The loop body of ``RecursiveFilter.forward`` as a module, so that the traced step can
    take the trained parameters as inputs through :func:`torch.func.functional_call`."""

    def __init__(self, filt: RecursiveFilter) -> None:
        super().__init__()
        self.filter = filt

    def forward(self, belief: dict[str, Tensor], z: Tensor, mask: Tensor | None, u: Any) -> tuple[Any, ...]:
        filt = self.filter
        prior = filt.predict(belief, u)
        post, info = filt.update(prior, z, mask, u)
        post = filt.finalize_belief(post)
        return prior, post, info, filt.record(post)


def _step_function(
    filt: RecursiveFilter, layout: StepLayout, keys: list[str], trained: list[tuple[str, Tensor]], seen: dict[str, Any]
) -> Any:
    """The loop body of ``RecursiveFilter.forward`` on flat inputs; records the keys it produces in ``seen``."""
    nb = len(keys)
    nc = len(layout.controls) if layout.controls else 0
    body = _StepBody(filt)

    def step(*flat: Tensor) -> list[Tensor]:
        belief = dict(zip(keys, flat[:nb], strict=True))
        i = nb + 1
        z = flat[nb]
        mask = None
        if layout.has_mask:
            mask = flat[i] > 0.5
            i += 1
        u = _unflatten_controls(layout, list(flat[i : i + nc]))
        i += nc
        values = {f"filter.{n}": v for (n, _), v in zip(trained, flat[i:], strict=True)}
        # tie_weights=False: only the names given are replaced (a parameter shared by two members
        # of a Blend stays one kernel input, as the kernel's parameter layout expects)
        prior, post, info, rec = functional_call(body, values, (belief, z, mask, u), tie_weights=False)
        seen["post"] = {k: post[k] for k in sorted(post)}
        seen["records"] = list(rec)
        seen["record_values"] = dict(rec)
        out = [seen["post"][k] for k in seen["post"]]
        result = [prior["mean"], prior["cov"], info.log_likelihood, info.nis, info.num_observed, _step_flag(info)]
        return out + result + list(rec.values())

    return step


def _examples(layout: StepLayout, belief: dict[str, Tensor], trained: list[tuple[str, Tensor]]) -> list[Tensor]:
    """The flat inputs of one traced step: ``belief`` (batch one), a zero measurement, a full
    mask, zero controls and the trained parameters."""
    examples = [belief[k].detach().to(layout.dtype) if belief[k].is_floating_point() else belief[k].detach() for k in sorted(belief)]
    examples.append(torch.zeros((1, layout.measurement_dim), dtype=layout.dtype))
    if layout.has_mask:
        examples.append(torch.ones((1, layout.measurement_dim), dtype=layout.dtype))
    examples += [torch.zeros((1, *s), dtype=layout.dtype) for _, s, _ in layout.controls or ()]
    return examples + [p.detach() for _, p in trained]


def eager_steps(filt: RecursiveFilter, layout: StepLayout, belief: dict[str, Tensor], steps: int = 2) -> list[dict[str, Tensor]]:
    """``filt``'s step run eagerly ``steps`` times from ``belief`` (batch one) on the inputs of
    :func:`_examples`, with the substitutions of :func:`_traceable`: per step, every output of
    the traced step by field name (belief entries, ``prior_mean``..., recorded values)."""
    trained = [(n, p) for n, p in filt.named_parameters() if p.requires_grad]
    out: list[dict[str, Tensor]] = []
    with _TRACE_LOCK, _traceable(), torch.no_grad():
        for _ in range(steps):
            seen: dict[str, Any] = {}
            values = _step_function(filt, layout, sorted(belief), trained, seen)(*_examples(layout, belief, trained))
            names = list(seen["post"]) + list(_RESULT_KEYS) + list(seen["records"])
            out.append(dict(zip(names, values, strict=True)))
            belief = seen["post"]
            layout = replace(layout, belief=tuple((k, tuple(v.shape[1:]), v.dtype) for k, v in belief.items()))
    return out


def _trace(
    filt: RecursiveFilter, layout: StepLayout, belief: dict[str, Tensor], trained: list[tuple[str, Tensor]]
) -> tuple[Any, dict[str, Any]]:
    """``(graph module, {"post": eager post-step belief, "records": keys})`` of one step from ``belief``."""
    keys = sorted(belief)
    seen: dict[str, Any] = {}
    step = _step_function(filt, layout, keys, trained, seen)
    examples = _examples(layout, belief, trained)
    # an eager step first: fills lazily built caches (sigma-point weights) with real tensors and
    # gives the belief after a step (the example for a steady step)
    step(*examples)
    eager = dict(seen)
    try:
        # functionalized: in-place writes (e.g. into slices of a block-diagonal matrix) become scatters
        gm = make_fx(torch.func.functionalize(step), tracing_mode="fake", _allow_non_fake_inputs=True)(*examples)
    except UnsupportedOp:
        raise
    except Exception as exc:  # noqa: BLE001 - any tracing failure means "not supported by this engine"
        raise UnsupportedOp(f"the step cannot be traced: {type(exc).__name__}: {str(exc)[:300]}") from exc
    for node in gm.graph.nodes:
        if node.op == "get_attr":
            val = getattr(gm, node.target)
            if isinstance(val, Tensor) and val.requires_grad:
                raise UnsupportedOp(f"the step uses a tensor that requires grad but is not a parameter of the filter ({node.target})")
    return gm, eager


def trace_step(filt: RecursiveFilter, layout: StepLayout, example_belief: dict[str, Tensor]) -> TracedStep:
    """Trace ``filt``'s step for ``layout`` (the belief before the first step) and lower it.

    If the first step adds belief entries (a filter's memory of the previous step), a second
    step is traced from the belief after the first one, and that *steady* step must keep its
    entries.  Raises :class:`UnsupportedOp` when the engine cannot run the filter.
    """
    trained = [(n, p) for n, p in filt.named_parameters() if p.requires_grad]
    with _TRACE_LOCK, _traceable(), torch.no_grad():
        gm0, eager0 = _trace(filt, layout, example_belief, trained)
        post = list(eager0["post"])
        if post == [k for k, _, _ in layout.belief]:
            steady, first = (gm0, layout), None
        else:
            steady_layout = replace(layout, belief=tuple((k, tuple(v.shape[1:]), v.dtype) for k, v in eager0["post"].items()))
            gm1, eager1 = _trace(filt, steady_layout, eager0["post"], trained)
            if list(eager1["post"]) != post:
                raise UnsupportedOp(f"the belief's entries keep changing ({post} -> {list(eager1['post'])})")
            steady, first = (gm1, steady_layout), (gm0, layout)
    dtypes = {k: v.dtype for k, v in eager0["post"].items()} | {k: v.dtype for k, v in eager0["record_values"].items()}
    return _lower_traced(steady, first, trained, eager0["records"], layout, dtypes)


def _lower_traced(
    steady: Any, first: Any, trained: list[tuple[str, Tensor]], record_keys: list[str], layout: StepLayout, dtypes: dict[str, torch.dtype]
) -> TracedStep:
    """Lower the steady step (whose belief layout is also the first step's output layout) and
    the optional first step into one graph with shared parameter inputs."""
    g = ScalarGraph()
    counters: dict[str, int] = {}

    def inputs(group: str, shape: tuple[int, ...], level: int = LANE, kind: str = "f") -> np.ndarray:
        start = counters.get(group, 0)
        cnt = math.prod(shape)
        counters[group] = start + cnt
        return np.array([g.input(group, start + i, level=level, kind=kind) for i in range(cnt)], dtype=object).reshape(shape)

    def flat(arrs: list[np.ndarray]) -> list[int]:
        return [int(x) for a in arrs for x in a.reshape(-1)]

    params = [inputs("param", tuple(p.shape), UNIFORM) for _, p in trained]
    keys = tuple(k for k, _, _ in steady[1].belief)
    names = list(keys) + list(_RESULT_KEYS) + record_keys

    def lowered(gm: Any, lay: StepLayout) -> tuple[list[int], list[int], list[int], list[Any]]:
        state = [inputs("state", (1, *s), kind="b" if dt == torch.bool else "f") for _, s, dt in lay.belief]
        step_in = [inputs("step", (1, lay.measurement_dim))]
        if lay.has_mask:
            step_in.append(inputs("step", (1, lay.measurement_dim)))
        ctrl = [inputs("shared" if k in lay.shared else "step", (1, *s)) for k, s, _ in lay.controls or ()]
        own = [a for (k, _, _), a in zip(lay.controls or (), ctrl, strict=True) if k not in lay.shared]
        shared = [a for (k, _, _), a in zip(lay.controls or (), ctrl, strict=True) if k in lay.shared]
        return flat(state), flat(step_in + own), flat(shared), lower(gm, g, lay.dtype, state + step_in + ctrl + params)

    state, step_in, shared_in, outs = lowered(*steady)
    if len(g) > MAX_NODES:
        raise UnsupportedOp(f"the step is too large for the generated engine ({len(g)} scalar operations, limit {MAX_NODES})")
    groups, fields = _groups(names, outs)
    slots = [(fields[k][0], fields[k][1] + i) for k in keys for i in range(math.prod(fields[k][2]))]
    body = StepBody(state, step_in, groups, slots, shared_in)
    first_body = None
    if first is not None:
        state0, step_in0, shared_in0, outs0 = lowered(*first)
        by_name = {name: [int(x) for x in np.asarray(o, dtype=object).reshape(-1)] for name, o in zip(names, outs0, strict=True)}
        groups0: list[list[int | None]] = [[None] * len(grp) for grp in groups]
        for name, (gi, off, _) in fields.items():
            for i, node in enumerate(by_name[name]):
                if groups0[gi][off + i] not in (None, node):
                    raise UnsupportedOp("the first step's outputs differ in layout from the later steps'")
                groups0[gi][off + i] = node
        if any(n is None for grp in groups0 for n in grp):
            raise UnsupportedOp("the first step's outputs differ in layout from the later steps'")
        first_body = StepBody(state0, step_in0, groups0, slots, shared_in0)  # type: ignore[arg-type]
    spec = SequenceSpec(g, layout.dtype, flat(params), body, first_body)
    return TracedStep(spec, layout, trained, fields, tuple(record_keys), keys, dtypes)


def _groups(names: list[str], outs: list[Any]) -> tuple[list[list[int]], dict[str, tuple[int, int, tuple[int, ...]]]]:
    """Output groups and ``fields[name] = (group, offset, shape)``.  An output whose elements
    appear, in order, inside an earlier (larger) group is stored once: e.g. an IMM's per-mode
    covariances are a slice of its stacked mode covariances."""
    arrays = {}
    for name, arr in zip(names, outs, strict=True):
        arr = np.asarray(arr, dtype=object)
        if arr.ndim == 0 or arr.shape[0] != 1:
            raise UnsupportedOp(f"step output {name!r} is not batched (shape {arr.shape})")
        arrays.setdefault(name, arr)
    groups: list[list[int]] = []
    where: dict[int, list[tuple[int, int]]] = {}  # node -> [(group, position)]
    fields: dict[str, tuple[int, int, tuple[int, ...]]] = {}
    for name in sorted(arrays, key=lambda k: -arrays[k].size):
        arr = arrays[name]
        nodes = [int(x) for x in arr.reshape(-1)]
        found = next(
            ((gi, pos) for gi, pos in where.get(nodes[0], []) if groups[gi][pos : pos + len(nodes)] == nodes), None
        ) if nodes else None  # fmt: skip
        if found is None:
            found = (len(groups), 0)
            groups.append(nodes)
            for pos, n in enumerate(nodes):
                where.setdefault(n, []).append((found[0], pos))
        fields[name] = (found[0], found[1], tuple(arr.shape[1:]))
    return groups, fields
