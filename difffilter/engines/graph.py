"""A scalar expression graph: one filter step written out as straight-line arithmetic on scalars.

Every node is one scalar of one trajectory (the batch becomes the vector lane of the generated
kernel).  Nodes are hash-consed (equal expressions share one node), constants are folded, and
each node has a *level*:

* ``CONST`` - a number known when the graph is built;
* ``UNIFORM`` - the same for every trajectory and step (a function of the model's parameters and
  buffers only), computed once per kernel call;
* ``LANE`` - differs per trajectory (depends on the belief, the measurement, masks, controls).

Booleans (comparisons, masks) are nodes of kind ``"b"``; everything else is a float of the
kernel's dtype.  :data:`PARTIALS` gives each float operation's partial derivatives as expressions
in the same graph, which is all the reverse sweep of :mod:`.codegen` needs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

__all__ = ["CONST", "LANE", "UNIFORM", "ScalarGraph", "UNARY", "BINARY", "BOOL_OPS", "CMP_OPS", "UnsupportedOp"]

CONST, UNIFORM, LANE = 0, 1, 2


class UnsupportedOp(NotImplementedError):  # noqa: N818 - names what it reports
    """The step uses an operation the scalar engine does not implement (the caller falls back)."""


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def _softplus(x: float) -> float:
    return x + math.log1p(math.exp(-x)) if x > 0 else math.log1p(math.exp(x))


def _safe(fn: Callable[..., float]) -> Callable[..., float]:
    def call(*a: float) -> float:
        try:
            return fn(*a)
        except (ValueError, ZeroDivisionError, OverflowError):
            return math.nan

    return call


#: float -> float operations and their constant folding
UNARY: dict[str, Callable[[float], float]] = {
    "neg": lambda a: -a,
    "sqrt": _safe(math.sqrt),
    "exp": _safe(math.exp),
    "log": _safe(math.log),
    "log1p": _safe(math.log1p),
    "expm1": _safe(math.expm1),
    "sin": math.sin,
    "cos": math.cos,
    "tan": _safe(math.tan),
    "atan": math.atan,
    "asin": _safe(math.asin),
    "acos": _safe(math.acos),
    "tanh": math.tanh,
    "sinh": _safe(math.sinh),
    "cosh": _safe(math.cosh),
    "sigmoid": _safe(_sigmoid),
    "softplus": _safe(_softplus),
    "abs": abs,
    "floor": _safe(lambda a: float(math.floor(a))),
    "ceil": _safe(lambda a: float(math.ceil(a))),
    "round": _safe(lambda a: float(round(a))),
    "sign": lambda a: float((a > 0) - (a < 0)),
}
BINARY: dict[str, Callable[[float, float], float]] = {
    "add": lambda a, b: a + b,
    "sub": lambda a, b: a - b,
    "mul": lambda a, b: a * b,
    "div": _safe(lambda a, b: a / b),
    "pow": _safe(lambda a, b: a**b),
    "atan2": math.atan2,
    "max": lambda a, b: a if a >= b else b,
    "min": lambda a, b: a if a <= b else b,
    "fmod": _safe(math.fmod),
}
CMP_OPS: dict[str, Callable[[float, float], bool]] = {
    "gt": lambda a, b: a > b,
    "ge": lambda a, b: a >= b,
    "lt": lambda a, b: a < b,
    "le": lambda a, b: a <= b,
    "eq": lambda a, b: a == b,
    "ne": lambda a, b: a != b,
}
BOOL_OPS: dict[str, Callable[..., bool]] = {
    "and": lambda a, b: a and b,
    "or": lambda a, b: a or b,
    "xor": lambda a, b: a != b,
    "not": lambda a: not a,
}


class ScalarGraph:
    """Hash-consed DAG of scalar operations with constant folding.

    Node ``i`` is ``(op[i], args[i])`` of kind ``kind[i]`` (``"f"`` float, ``"b"`` bool) and
    level ``level[i]``; constants keep their value in ``value[i]``.  Inputs are created with
    :meth:`input` and named by ``(group, index)``, e.g. ``("state", 3)``.
    """

    def __init__(self) -> None:
        self.op: list[str] = []
        self.args: list[tuple[int, ...]] = []
        self.kind: list[str] = []
        self.level: list[int] = []
        self.value: list[float | bool | None] = []
        self.inputs: dict[int, tuple[str, int]] = {}
        self._cse: dict[tuple, int] = {}
        self._consts: dict[tuple[str, float | bool], int] = {}

    def __len__(self) -> int:
        return len(self.op)

    # -- construction -----------------------------------------------------------------------
    def _new(self, op: str, args: tuple[int, ...], kind: str, level: int, value: float | bool | None = None) -> int:
        self.op.append(op)
        self.args.append(args)
        self.kind.append(kind)
        self.level.append(level)
        self.value.append(value)
        return len(self.op) - 1

    def const(self, v: float | bool) -> int:
        if isinstance(v, bool):
            key = ("b", v)
        else:
            v = float(v)
            # NaN never equals itself: key it by its text so that one NaN node is shared
            key = ("f", v) if v == v else ("f", "nan")  # type: ignore[assignment]
        node = self._consts.get(key)
        if node is None:
            node = self._new("const", (), key[0], CONST, v)
            self._consts[key] = node
        return node

    def input(self, group: str, index: int, *, level: int = LANE, kind: str = "f") -> int:
        node = self._new("input", (), kind, level)
        self.inputs[node] = (group, index)
        return node

    def is_const(self, a: int, v: float | None = None) -> bool:
        if self.level[a] != CONST:
            return False
        return v is None or self.value[a] == v

    def _emit(self, op: str, args: tuple[int, ...], kind: str) -> int:
        key = (op, args)
        node = self._cse.get(key)
        if node is None:
            node = self._new(op, args, kind, max(self.level[a] for a in args))
            self._cse[key] = node
        return node

    def unary(self, op: str, a: int) -> int:
        if self.kind[a] != "f":
            raise UnsupportedOp(f"{op} of a boolean")
        if self.level[a] == CONST:
            return self.const(UNARY[op](self.value[a]))  # type: ignore[arg-type]
        if op == "neg" and self.op[a] == "neg":
            return self.args[a][0]
        return self._emit(op, (a,), "f")

    def binary(self, op: str, a: int, b: int) -> int:
        if self.kind[a] != "f" or self.kind[b] != "f":
            raise UnsupportedOp(f"{op} of a boolean")
        ca, cb = self.level[a] == CONST, self.level[b] == CONST
        if ca and cb:
            return self.const(BINARY[op](self.value[a], self.value[b]))  # type: ignore[arg-type]
        # Algebraic identities. 0 * x is folded to 0: the kernel then differs from IEEE
        # arithmetic only for an infinite or NaN x, where the filter's result is undefined anyway.
        if op == "add":
            if ca and self.value[a] == 0.0:
                return b
            if cb and self.value[b] == 0.0:
                return a
            if a == b:
                return self.binary("mul", self.const(2.0), a)
            if a > b:  # commutative: one node for a + b and b + a
                a, b = b, a
        elif op == "sub":
            if cb and self.value[b] == 0.0:
                return a
            if ca and self.value[a] == 0.0:
                return self.unary("neg", b)
            if a == b:
                return self.const(0.0)
        elif op == "mul":
            for x, y, cx in ((a, b, ca), (b, a, cb)):
                if cx:
                    if self.value[x] == 0.0:
                        return self.const(0.0)
                    if self.value[x] == 1.0:
                        return y
                    if self.value[x] == -1.0:
                        return self.unary("neg", y)
                    if self.op[y] == "mul":  # c1 * (c2 * z) = (c1 c2) * z
                        for c, z in (self.args[y], self.args[y][::-1]):
                            if self.level[c] == CONST:
                                return self.binary("mul", self.const(self.value[x] * self.value[c]), z)
            if a > b:
                a, b = b, a
        elif op == "div":
            if cb and self.value[b] == 1.0:
                return a
            if ca and self.value[a] == 0.0:
                return self.const(0.0)
        elif op == "pow" and cb:
            e = self.value[b]
            if e == 1.0:
                return a
            if e == 2.0:
                return self.binary("mul", a, a)
            if e == 0.5:
                return self.unary("sqrt", a)
            if e == 0.0:
                return self.const(1.0)
        elif op in ("max", "min") and a > b:
            a, b = b, a
        return self._emit(op, (a, b), "f")

    def compare(self, op: str, a: int, b: int) -> int:
        if self.level[a] == CONST and self.level[b] == CONST:
            return self.const(CMP_OPS[op](self.value[a], self.value[b]))  # type: ignore[arg-type]
        return self._emit(op, (a, b), "b")

    def logical(self, op: str, *args: int) -> int:
        if any(self.kind[a] != "b" for a in args):
            raise UnsupportedOp(f"logical {op} of a float")
        if all(self.level[a] == CONST for a in args):
            return self.const(BOOL_OPS[op](*(self.value[a] for a in args)))
        if op == "not" and self.op[args[0]] == "not":
            return self.args[args[0]][0]
        if op in ("and", "or") and len(args) == 2:
            a, b = args
            for x, y in ((a, b), (b, a)):
                if self.level[x] == CONST:
                    if op == "and":
                        return y if self.value[x] else self.const(False)
                    return self.const(True) if self.value[x] else y
        return self._emit(op, tuple(args), "b")

    def where(self, c: int, x: int, y: int) -> int:
        if self.kind[c] != "b":
            c = self.compare("ne", c, self.const(0.0))
        if self.kind[x] != self.kind[y]:
            raise UnsupportedOp("where with mixed boolean and float branches")
        if self.level[c] == CONST:
            return x if self.value[c] else y
        if x == y:
            return x
        if self.kind[x] == "b":
            return self.logical("or", self.logical("and", c, x), self.logical("and", self.logical("not", c), y))
        return self._emit("where", (c, x, y), "f")

    def to_float(self, a: int) -> int:
        if self.kind[a] == "f":
            return a
        return self.where(a, self.const(1.0), self.const(0.0))

    def to_bool(self, a: int) -> int:
        if self.kind[a] == "b":
            return a
        return self.compare("ne", a, self.const(0.0))

    # -- derivatives ------------------------------------------------------------------------
    def partials(self, node: int) -> Sequence[tuple[int, int]]:
        """``[(arg, d node / d arg)]`` for the float arguments of float node ``node``."""
        op, args = self.op[node], self.args[node]
        g = self
        one = g.const(1.0)
        if op in ("const", "input") or g.kind[node] != "f":
            return ()
        if op == "where":
            c, x, y = args
            zero = g.const(0.0)
            return ((x, g.where(c, one, zero)), (y, g.where(c, zero, one)))
        if len(args) == 1:
            a = args[0]
            fn = _UNARY_PARTIALS.get(op)
            if fn is None:
                raise UnsupportedOp(f"no derivative for {op}")
            return ((a, fn(g, a, node)),)
        a, b = args
        fn2 = _BINARY_PARTIALS.get(op)
        if fn2 is None:
            raise UnsupportedOp(f"no derivative for {op}")
        da, db = fn2(g, a, b, node)
        return ((a, da), (b, db))


def _c(g: ScalarGraph, v: float) -> int:
    return g.const(v)


_UNARY_PARTIALS: dict[str, Callable[[ScalarGraph, int, int], int]] = {
    "neg": lambda g, a, y: _c(g, -1.0),
    "sqrt": lambda g, a, y: g.binary("div", _c(g, 0.5), y),
    "exp": lambda g, a, y: y,
    "log": lambda g, a, y: g.binary("div", _c(g, 1.0), a),
    "log1p": lambda g, a, y: g.binary("div", _c(g, 1.0), g.binary("add", a, _c(g, 1.0))),
    "expm1": lambda g, a, y: g.binary("add", y, _c(g, 1.0)),
    "sin": lambda g, a, y: g.unary("cos", a),
    "cos": lambda g, a, y: g.unary("neg", g.unary("sin", a)),
    "tan": lambda g, a, y: g.binary("add", _c(g, 1.0), g.binary("mul", y, y)),
    "atan": lambda g, a, y: g.binary("div", _c(g, 1.0), g.binary("add", _c(g, 1.0), g.binary("mul", a, a))),
    "asin": lambda g, a, y: g.binary("div", _c(g, 1.0), g.unary("sqrt", g.binary("sub", _c(g, 1.0), g.binary("mul", a, a)))),
    "acos": lambda g, a, y: g.binary("div", _c(g, -1.0), g.unary("sqrt", g.binary("sub", _c(g, 1.0), g.binary("mul", a, a)))),
    "tanh": lambda g, a, y: g.binary("sub", _c(g, 1.0), g.binary("mul", y, y)),
    "sinh": lambda g, a, y: g.unary("cosh", a),
    "cosh": lambda g, a, y: g.unary("sinh", a),
    "sigmoid": lambda g, a, y: g.binary("mul", y, g.binary("sub", _c(g, 1.0), y)),
    "softplus": lambda g, a, y: g.unary("sigmoid", a),
    "abs": lambda g, a, y: g.unary("sign", a),
    "floor": lambda g, a, y: _c(g, 0.0),
    "ceil": lambda g, a, y: _c(g, 0.0),
    "round": lambda g, a, y: _c(g, 0.0),
    "sign": lambda g, a, y: _c(g, 0.0),
}


def _pow_partials(g: ScalarGraph, a: int, b: int, y: int) -> tuple[int, int]:
    da = g.binary("mul", b, g.binary("pow", a, g.binary("sub", b, _c(g, 1.0))))
    db = _c(g, 0.0) if g.is_const(b) else g.binary("mul", y, g.unary("log", a))
    return da, db


def _atan2_partials(g: ScalarGraph, a: int, b: int, y: int) -> tuple[int, int]:
    r2 = g.binary("add", g.binary("mul", a, a), g.binary("mul", b, b))
    return g.binary("div", b, r2), g.binary("div", g.unary("neg", a), r2)


def _minmax_partials(g: ScalarGraph, a: int, b: int, y: int, op: str) -> tuple[int, int]:
    # ties send the whole gradient to the first argument, as torch.maximum splits it evenly;
    # either is a valid subgradient and ties between distinct expressions are rare
    pick = g.compare("ge" if op == "max" else "le", a, b)
    one, zero = _c(g, 1.0), _c(g, 0.0)
    return g.where(pick, one, zero), g.where(pick, zero, one)


_BINARY_PARTIALS: dict[str, Callable[[ScalarGraph, int, int, int], tuple[int, int]]] = {
    "add": lambda g, a, b, y: (_c(g, 1.0), _c(g, 1.0)),
    "sub": lambda g, a, b, y: (_c(g, 1.0), _c(g, -1.0)),
    "mul": lambda g, a, b, y: (b, a),
    "div": lambda g, a, b, y: (g.binary("div", _c(g, 1.0), b), g.unary("neg", g.binary("div", y, b))),
    "pow": _pow_partials,
    "atan2": _atan2_partials,
    "max": lambda g, a, b, y: _minmax_partials(g, a, b, y, "max"),
    "min": lambda g, a, b, y: _minmax_partials(g, a, b, y, "min"),
    "fmod": lambda g, a, b, y: (_c(g, 1.0), g.unary("neg", g.unary("floor", g.binary("div", a, b)))),
}


def evaluate(g: ScalarGraph, nodes: Sequence[int], inputs: dict[int, float | bool]) -> list[float | bool]:
    """Values of ``nodes`` given values of the input nodes they depend on (Python floats:
    a reference interpreter for tests of the lowering)."""
    memo: dict[int, float | bool] = dict(inputs)

    def value(n: int) -> float | bool:
        stack = [n]
        while stack:
            x = stack[-1]
            if x in memo:
                stack.pop()
                continue
            op, args = g.op[x], g.args[x]
            if op == "const":
                memo[x] = g.value[x]  # type: ignore[assignment]
                stack.pop()
                continue
            if op == "input":
                raise KeyError(f"no value for input node {x} {g.inputs[x]}")
            todo = [a for a in args if a not in memo]
            if todo:
                stack.extend(todo)
                continue
            vals = [memo[a] for a in args]
            if op in UNARY:
                memo[x] = UNARY[op](vals[0])  # type: ignore[arg-type]
            elif op in BINARY:
                memo[x] = BINARY[op](vals[0], vals[1])  # type: ignore[arg-type]
            elif op in CMP_OPS:
                memo[x] = CMP_OPS[op](vals[0], vals[1])  # type: ignore[arg-type]
            elif op in BOOL_OPS:
                memo[x] = BOOL_OPS[op](*vals)
            elif op == "where":
                memo[x] = vals[1] if vals[0] else vals[2]
            else:
                raise UnsupportedOp(op)
            stack.pop()
        return memo[n]

    return [value(n) for n in nodes]


__all__ += ["evaluate"]
