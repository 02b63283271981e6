"""Trace one step of a filter (its own ``predict``/``update``) and lower it to a scalar graph.

The step traced is exactly the body of :meth:`GaussianFilter.forward`'s loop: ``predict``,
``update``, ``finalize_belief`` and ``record``, on a belief of batch size one.  It is traced with
fake tensors (``make_fx``), so any Python decision on the *values* of the belief or the data
fails the trace (and the caller falls back to another engine) instead of being frozen into the
kernel.  One such decision is expected and handled: :func:`~difffilter.linalg.safe_cholesky`
retries a failing factorisation with jitter; while tracing it is replaced by the bare
factorisation, which the lowering writes as a branch-free Cholesky with clamped pivots.

Model parameters that require a gradient become inputs of the kernel; buffers and frozen
parameters are folded in as constants (their values are part of :func:`fingerprint`, so a
changed value means a new kernel).
"""

from __future__ import annotations

import hashlib
import math
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.fx.experimental.proxy_tensor import make_fx
from torch.nn.utils.stateless import _reparametrize_module

from ... import linalg
from ..base import GaussianFilter
from .codegen import SequenceSpec
from .graph import LANE, UNIFORM, ScalarGraph, UnsupportedOp
from .lower import lower

__all__ = ["StepLayout", "TracedStep", "fingerprint", "trace_step"]

_TRACE_LOCK = threading.Lock()
_RESULT_KEYS = ("prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")


@dataclass(frozen=True)
class StepLayout:
    """Names and per-trajectory shapes of the belief, the step inputs and the controls."""

    belief: tuple[tuple[str, tuple[int, ...]], ...]
    measurement_dim: int
    has_mask: bool
    controls: tuple[tuple[str, tuple[int, ...], torch.dtype], ...] | None  # None: no controls; key "" for a bare tensor
    dtype: torch.dtype

    @property
    def state_size(self) -> int:
        return sum(math.prod(s) for _, s in self.belief)

    @property
    def step_size(self) -> int:
        ctrl = sum(math.prod(s) for _, s, _ in self.controls) if self.controls else 0
        return self.measurement_dim * (2 if self.has_mask else 1) + ctrl


@dataclass
class TracedStep:
    """A lowered step: the kernel specification and how outputs map to result fields.

    ``fields[name] = (group, shape)``: the output group holding field ``name`` (``mean``,
    ``cov``, ``prior_mean``, ..., every belief key and every recorded key) and its
    per-trajectory shape.
    """

    spec: SequenceSpec
    layout: StepLayout
    params: list[tuple[str, Tensor]]
    fields: dict[str, tuple[int, tuple[int, ...]]]
    record_keys: tuple[str, ...]


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
        trains = isinstance(t, nn.Parameter) and t.requires_grad
        h.update(f"{name}:{tuple(t.shape)}:{t.dtype}:{trains}".encode())
        if not trains:
            h.update(t.detach().cpu().contiguous().numpy().tobytes() if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())
    return h.hexdigest()


@contextmanager
def _branch_free_cholesky() -> Iterator[None]:
    """Replace ``safe_cholesky`` in every difffilter module by the bare factorisation while tracing."""
    original = linalg.safe_cholesky

    def bare(a: Tensor, *, max_jitter: float | None = None) -> linalg.CholeskyResult:
        chol, info = torch.linalg.cholesky_ex(a)
        return linalg.CholeskyResult(chol, info.to(a.dtype))

    mods = [m for name, m in list(sys.modules.items()) if name.startswith("difffilter") and getattr(m, "safe_cholesky", None) is original]
    for m in mods:
        m.safe_cholesky = bare  # type: ignore[attr-defined]
    try:
        yield
    finally:
        for m in mods:
            m.safe_cholesky = original  # type: ignore[attr-defined]


def _unflatten_controls(layout: StepLayout, flat: list[Tensor]) -> Any:
    if layout.controls is None:
        return None
    vals = [t.to(dt) if dt != layout.dtype else t for t, (_, _, dt) in zip(flat, layout.controls, strict=True)]
    if len(layout.controls) == 1 and layout.controls[0][0] == "":
        return vals[0]
    return {k: v for (k, _, _), v in zip(layout.controls, vals, strict=True)}


def trace_step(filt: GaussianFilter, layout: StepLayout, example_belief: dict[str, Tensor]) -> TracedStep:
    """Trace ``filt``'s step for ``layout`` and lower it (raises :class:`UnsupportedOp`)."""
    dtype = layout.dtype
    trained = [(n, p) for n, p in filt.named_parameters() if p.requires_grad]
    keys = [k for k, _ in layout.belief]
    nb = len(keys)
    nc = len(layout.controls) if layout.controls else 0
    record_keys: list[str] = []

    def step(*flat: Tensor) -> list[Tensor]:
        belief = dict(zip(keys, flat[:nb], strict=True))
        i = nb
        z = flat[i]
        i += 1
        mask = None
        if layout.has_mask:
            mask = flat[i] > 0.5
            i += 1
        u = _unflatten_controls(layout, list(flat[i : i + nc]))
        i += nc
        with _reparametrize_module(filt, {n: v for (n, _), v in zip(trained, flat[i:], strict=True)}):
            prior = filt.predict(belief, u)
            post, info = filt.update(prior, z, mask, u)
            post = filt.finalize_belief(post)
            rec = filt.record(post)
        if sorted(post) != sorted(keys):
            raise UnsupportedOp(f"the belief's entries change during a step ({sorted(keys)} -> {sorted(post)})")
        record_keys[:] = list(rec)
        return [post[k] for k in keys] + [prior["mean"], prior["cov"], info.log_likelihood, info.nis, info.num_observed] + list(rec.values())

    def fake_input(shape: tuple[int, ...]) -> Tensor:
        return torch.zeros((1, *shape), dtype=dtype)

    examples = [example_belief[k].to(dtype) for k in keys]
    examples.append(fake_input((layout.measurement_dim,)))
    if layout.has_mask:
        examples.append(torch.ones((1, layout.measurement_dim), dtype=dtype))
    examples += [fake_input(s) for _, s, _ in layout.controls or ()]
    examples += [p.detach() for _, p in trained]
    with _TRACE_LOCK, _branch_free_cholesky(), torch.no_grad():
        # fill lazily built caches (sigma-point weights) with real tensors before tracing
        step(*examples)
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
    return _lower_traced(gm, layout, trained, record_keys)


def _lower_traced(gm: Any, layout: StepLayout, trained: list[tuple[str, Tensor]], record_keys: list[str]) -> TracedStep:
    g = ScalarGraph()
    counters: dict[str, int] = {}

    def inputs(group: str, shape: tuple[int, ...], level: int = LANE) -> np.ndarray:
        start = counters.get(group, 0)
        cnt = math.prod(shape)
        counters[group] = start + cnt
        return np.array([g.input(group, start + i, level=level) for i in range(cnt)], dtype=object).reshape(shape)

    state = [inputs("state", (1, *s)) for _, s in layout.belief]
    step_in = [inputs("step", (1, layout.measurement_dim))]
    if layout.has_mask:
        step_in.append(inputs("step", (1, layout.measurement_dim)))
    step_in += [inputs("step", (1, *s)) for _, s, _ in layout.controls or ()]
    params = [inputs("param", tuple(p.shape), UNIFORM) for _, p in trained]
    outs = lower(gm, g, layout.dtype, state + step_in + params)
    names = [k for k, _ in layout.belief] + list(_RESULT_KEYS) + record_keys
    groups: list[list[int]] = []
    fields: dict[str, tuple[int, tuple[int, ...]]] = {}
    seen: dict[tuple[int, ...], int] = {}
    for name, arr in zip(names, outs, strict=True):
        arr = np.asarray(arr, dtype=object)
        if arr.ndim == 0 or arr.shape[0] != 1:
            raise UnsupportedOp(f"step output {name!r} is not batched (shape {arr.shape})")
        nodes = tuple(int(x) for x in arr.reshape(-1))
        if name in fields:
            continue
        gi = seen.get(nodes)
        if gi is None:
            gi = len(groups)
            groups.append(list(nodes))
            seen[nodes] = gi
        fields[name] = (gi, tuple(arr.shape[1:]))
    state_slot = [(fields[k][0], i) for k, s in layout.belief for i in range(math.prod(s))]
    flat = lambda arrs: [int(x) for a in arrs for x in a.reshape(-1)]  # noqa: E731
    spec = SequenceSpec(g, layout.dtype, flat(state), flat(step_in), flat(params), groups, state_slot)
    return TracedStep(spec, layout, trained, fields, tuple(record_keys))
