"""Householder QR written once over an arithmetic: tensors (the inductor engine's element-wise
step, :mod:`.step`) or scalar graph nodes (the generated engine's lowering, :mod:`.ops`).

LAPACK's sign convention (``R_jj = -sign(a_jj) ||a_j:||``); a column with nothing below its
diagonal is left as it is (no reflection), chosen with ``where`` so nothing divides by zero.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["Arithmetic", "householder"]


@dataclass(frozen=True)
class Arithmetic:
    """The operations the factorisation needs, on whatever values ``zero``/``one`` are."""

    add: Callable[[Any, Any], Any]
    sub: Callable[[Any, Any], Any]
    mul: Callable[[Any, Any], Any]
    div: Callable[[Any, Any], Any]
    neg: Callable[[Any], Any]
    sqrt: Callable[[Any], Any]
    lt: Callable[[Any, Any], Any]
    eq: Callable[[Any, Any], Any]
    where: Callable[[Any, Any, Any], Any]
    zero: Any
    one: Any


def householder(w: list[list[Any]], ar: Arithmetic, *, want_q: bool, guard_sqrt: bool) -> tuple[list[list[Any]] | None, list[list[Any]]]:
    """Factor the ``m x k`` matrix ``w`` (rows of values; overwritten) as ``Q R``.

    Returns ``(Q, R)`` as rows: ``Q`` is ``m x min(m, k)`` (``None`` unless ``want_q``), ``R`` is
    ``min(m, k) x k``.  ``guard_sqrt`` takes the norm of a trivial column as ``sqrt(a_jj^2 + 1)``
    (not selected, but its derivative stays finite under autograd's ``where``).
    """
    m, k = len(w), len(w[0])
    p = min(m, k)
    zero, one = ar.zero, ar.one
    reflectors = []
    for j in range(p):
        alpha = w[j][j]
        xnorm2 = zero
        for i in range(j + 1, m):
            xnorm2 = ar.add(xnorm2, ar.mul(w[i][j], w[i][j]))
        if guard_sqrt:
            trivial = ar.eq(xnorm2, zero)
            norm = ar.sqrt(ar.add(ar.mul(alpha, alpha), ar.where(trivial, one, xnorm2)))
        else:
            norm = ar.sqrt(ar.add(ar.mul(alpha, alpha), xnorm2))
        beta = ar.where(ar.lt(alpha, zero), norm, ar.neg(norm))
        if not guard_sqrt:
            trivial = ar.eq(xnorm2, zero)  # nothing below the diagonal: H = I
        safe = ar.where(trivial, one, ar.sub(alpha, beta))
        tau = ar.where(trivial, zero, ar.div(ar.sub(beta, alpha), ar.where(trivial, one, beta)))
        v = [one] + [ar.div(w[i][j], safe) for i in range(j + 1, m)]
        w[j][j] = ar.where(trivial, alpha, beta)
        for i in range(j + 1, m):
            w[i][j] = zero
        for c in range(j + 1, k):  # w[j:, c] -= tau v (v^T w[j:, c])
            dot = w[j][c]
            for i in range(j + 1, m):
                dot = ar.add(dot, ar.mul(v[i - j], w[i][c]))
            s = ar.mul(tau, dot)
            for i in range(j, m):
                w[i][c] = ar.sub(w[i][c], ar.mul(s, v[i - j]))
        reflectors.append((j, v, tau))
    r = [[w[i][j] if j >= i else zero for j in range(k)] for i in range(p)]
    if not want_q:
        return None, r
    qm = [[one if i == c else zero for c in range(p)] for i in range(m)]
    for j, v, tau in reversed(reflectors):
        for c in range(p):
            dot = zero
            for i in range(j, m):
                dot = ar.add(dot, ar.mul(v[i - j], qm[i][c]))
            s = ar.mul(tau, dot)
            for i in range(j, m):
                qm[i][c] = ar.sub(qm[i][c], ar.mul(s, v[i - j]))
    return qm, r
