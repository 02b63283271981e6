"""ATen graph -> scalar graph: run a traced step on arrays of scalar nodes.

:func:`lower` interprets an FX graph of ATen operations (from ``make_fx``) where every tensor is
a NumPy object array of :class:`~.graph.ScalarGraph` node ids, one per element.  Shapes are
static and the batch dimension of the trace has size one, so each element is one scalar of one
trajectory.  Views, broadcasting and concatenation are index bookkeeping; element-wise
operations create one node per element (:mod:`.ops_pointwise`); reductions and small matrix
products become chains of additions, ``linalg.cholesky_ex`` and the triangular solves the
textbook algorithms (:mod:`.ops_structured`, :mod:`.ops`).
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import fx

from .graph import ScalarGraph, UnsupportedOp
from .ops import Lowering
from .ops_pointwise import MISSING, lower_pointwise
from .ops_structured import lower_structured

__all__ = ["lower"]


def _op_name(target: Any) -> str:
    if isinstance(target, torch.library.OpOverload):
        return (
            target.overloadpacket.__name__.rstrip("_")
            if target.overloadpacket.__name__ not in ("__and__", "__or__")
            else target.overloadpacket.__name__
        )
    if callable(getattr(target, "overloads", None)) and isinstance(getattr(target, "__name__", None), str):  # an OpOverloadPacket
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
            name = _op_name(node.target)
            out = lower_pointwise(L, name, tuple(args), dict(kw), node)
            if out is MISSING:
                out = lower_structured(L, name, tuple(args), dict(kw), node)
            env[node] = _as_arrays(out, node.meta.get("val"))
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
