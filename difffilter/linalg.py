"""Numerical linear algebra for Gaussian filters: the only home of these primitives.

All functions act on batched tensors ``[..., n, n]`` and are differentiable.  Conventions:
covariances are symmetrised before factorisation; inverses are never formed (triangular solves
against Cholesky factors instead); Cholesky failures are repaired with a *bounded* diagonal
jitter added only to the failing batch elements.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch import Tensor
from torch._C import _functorch

#: ``log(2 pi)``, the Gaussian normaliser per observed component.
LOG_2PI = math.log(2.0 * math.pi)

__all__ = [
    "LOG_2PI",
    "CholeskyResult",
    "any_set",
    "nonfinite_rows",
    "inside_vmap",
    "vmapped",
    "block_diag",
    "cholesky_failure_count",
    "jitter_bound",
    "chol_rank1_update",
    "joseph_update",
    "psd_solve",
    "psd_sqrt",
    "safe_cholesky",
    "symmetrize",
    "tria",
    "gaussian_log_density",
]

#: Relative jitter levels tried by :func:`safe_cholesky`, multiplied by the mean diagonal.
JITTER_LEVELS: tuple[float, ...] = (1e-12, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2)

# Process-wide settings of safe_cholesky: the largest relative jitter, and how many batch
# elements could not be factorised even with it (so that callers can report them, never hide).
_MAX_JITTER = [JITTER_LEVELS[-1]]
_FAILURES = [0]


@contextlib.contextmanager
def jitter_bound(max_jitter: float | None) -> Iterator[None]:
    """Inside the block, :func:`safe_cholesky` adds at most ``max_jitter`` (relative to the mean
    diagonal) unless a call passes its own bound.  ``None`` keeps the current bound.

    A smaller bound keeps an ill-conditioned covariance from being silently regularised by a large
    jitter (up to 1e-2 of its mean diagonal by default); a matrix that still fails then follows
    ``safe_cholesky``'s rule, so bound it only where the covariances are known to be well
    conditioned.  Restored on exit; process-wide (not thread-safe)."""
    saved = _MAX_JITTER[0]
    if max_jitter is not None:
        if max_jitter < 0:
            raise ValueError(f"max_jitter must be >= 0, got {max_jitter}")
        _MAX_JITTER[0] = float(max_jitter)
    try:
        yield
    finally:
        _MAX_JITTER[0] = saved


def cholesky_failure_count() -> int:
    """Batch elements that :func:`safe_cholesky` could not factorise within its jitter bound
    since the process started (they were given an identity factor and ``jitter = inf``)."""
    return _FAILURES[0]


def symmetrize(a: Tensor) -> Tensor:
    """``(A + A^T) / 2`` over the last two dimensions."""
    return 0.5 * (a + a.mT)


class CholeskyResult(NamedTuple):
    """Lower Cholesky factor and, per batch element, the jitter that was added (0 if none)."""

    factor: Tensor
    jitter: Tensor


def _chol_ok(chol: Tensor, info: Tensor) -> Tensor:
    # A NaN or inf anywhere in the factorised triangle reaches the factor's diagonal (each L_ii
    # depends on the whole row i), so the diagonal suffices and is much cheaper to scan.
    finite = torch.isfinite(torch.diagonal(chol, dim1=-2, dim2=-1)).all(-1)
    return (info == 0) & finite


def inside_vmap() -> bool:
    """Whether the code runs inside a ``torch.func.vmap`` transform (at any level)."""
    if torch.compiler.is_compiling():  # a traced graph never holds functorch wrappers
        return False
    stack = _functorch.get_interpreter_stack()
    return bool(stack) and any(i.key() == _functorch.TransformType.Vmap for i in stack)


def vmapped(*tensors: Tensor) -> bool:
    """Whether any of ``tensors`` is batched by ``torch.func.vmap``: its per-sample values cannot
    be read in Python (``bool()``, ``.item()``), so a data-dependent branch must take a path
    that is right for every sample (``torch.where`` over both, or the conservative one)."""
    if torch.compiler.is_compiling():  # a traced graph never holds functorch wrappers
        return False
    for t in tensors:
        while _functorch.maybe_get_level(t) != -1:
            if _functorch.is_batchedtensor(t):
                return True
            t = _functorch.get_unwrapped(t)
    return False


def any_set(flags: Tensor) -> bool:
    """Whether any element of the boolean ``flags`` is set.

    The guard of optional per-element work whose result is selected with ``torch.where`` (e.g. a
    Joseph-form recomputation where ``P - K S K^T`` cancels): skipping the work when no element
    needs it changes no value, so an engine that cannot branch on data (the generated kernels of
    :class:`~difffilter.filters.FusedFilter`) takes the guard as always true, and so does
    ``torch.func.vmap`` (:func:`vmapped`).
    """
    return vmapped(flags) or bool(flags.any())


def nonfinite_rows(x: Tensor, dims: int = 1) -> Tensor:
    """``x.shape[:dims]`` bool: whether each row (``x``'s trailing dimensions flattened) holds a
    non-finite element; no gradient.

    Exact, and cheap when every row is finite: a sum is finite only if each of its terms is (a
    NaN or an infinity makes it NaN or infinite), so one sum of the whole tensor decides that no
    row holds one, about twenty times faster than the element-wise test (and than sums per row,
    which are slow over the strided outputs of the compiled engine); a non-finite sum (a
    non-finite element, or finite ones whose sum overflows) sends the tensor to the element-wise
    test.  Inside ``torch.func.vmap`` or a compiled region, where values cannot be read, the
    element-wise test always runs."""
    x = x.detach()
    rest = tuple(range(dims, x.dim()))
    if not vmapped(x) and not torch.compiler.is_compiling() and bool(torch.isfinite(x.sum())):
        return torch.zeros(x.shape[:dims], dtype=torch.bool, device=x.device)
    finite = torch.isfinite(x)
    return ~finite.all(rest) if rest else ~finite


def safe_cholesky(a: Tensor, *, max_jitter: float | None = None) -> CholeskyResult:
    """Cholesky factor of symmetric ``a [..., n, n]`` with bounded, per-element jitter.

    The common case costs one ``cholesky_ex``.  Batch elements whose factorisation fails
    (non-zero ``info`` or non-finite factor) are retried, without gradient tracking, with a
    jitter ``eps * mean(diag)`` for ``eps`` in :data:`JITTER_LEVELS` up to ``max_jitter``; then
    the final factor is computed once, differentiably, on ``a + jitter * I``.  Elements still
    failing at the largest jitter (e.g. containing NaN) are replaced by the identity so that
    their garbage cannot propagate NaN into the gradients of the other batch elements; their
    ``jitter`` entry is ``inf`` so callers can flag them, and
    :func:`cholesky_failure_count` counts them.  ``max_jitter=None`` uses the bound set by
    :func:`jitter_bound` (default ``1e-2``).
    """
    if max_jitter is None:
        max_jitter = _MAX_JITTER[0]
    # cholesky_ex reads only the lower triangle (and its gradient is symmetric), so the common
    # path needs no symmetrisation; one reduction decides whether any element needs repair
    # (a NaN/inf anywhere reaches the diagonal; an overflowing sum only costs the slow path).
    chol, info = torch.linalg.cholesky_ex(a)
    if vmapped(chol, info):
        return _vmapped_cholesky(a, chol, info, max_jitter)
    if not bool(info.any()) and bool(torch.isfinite(torch.diagonal(chol, dim1=-2, dim2=-1).sum())):
        return CholeskyResult(chol, torch.zeros(info.shape, dtype=a.dtype, device=a.device))
    a = symmetrize(a)
    ok = _chol_ok(chol, info)
    n = a.shape[-1]
    eye = torch.eye(n, dtype=a.dtype, device=a.device)
    with torch.no_grad():
        diag_mean = torch.diagonal(a, dim1=-2, dim2=-1).abs().mean(-1)
        scale = torch.where(torch.isfinite(diag_mean) & (diag_mean > 0), diag_mean, torch.ones_like(diag_mean))
        jitter = torch.zeros_like(diag_mean)
        pending = ~ok
        for eps in JITTER_LEVELS:
            if eps > max_jitter or not bool(pending.any()):
                break
            trial = eps * scale
            c, i = torch.linalg.cholesky_ex(a + trial[..., None, None] * eye)
            fixed = pending & _chol_ok(c, i)
            jitter = torch.where(fixed, trial, jitter)
            pending = pending & ~fixed
        jitter = torch.where(pending, torch.full_like(jitter, math.inf), jitter)
        _FAILURES[0] += int(pending.sum())
    usable = torch.isfinite(jitter)
    safe_a = torch.where(usable[..., None, None], a + jitter.where(usable, 0.0)[..., None, None] * eye, eye)
    chol = torch.linalg.cholesky_ex(safe_a)[0]
    return CholeskyResult(chol, jitter)


def _jitter_scale(a: Tensor) -> Tensor:
    diag_mean = torch.diagonal(a, dim1=-2, dim2=-1).abs().mean(-1)
    return torch.where(torch.isfinite(diag_mean) & (diag_mean > 0), diag_mean, torch.ones_like(diag_mean))


def _vmapped_cholesky(a: Tensor, chol: Tensor, info: Tensor, max_jitter: float) -> CholeskyResult:
    """:func:`safe_cholesky` without reading values (inside ``vmap``): a failing element gets
    the largest allowed jitter at once (or the identity and ``jitter = inf``), selected by
    ``where``; one more factorisation of every element instead of the ladder of levels."""
    ok = _chol_ok(chol, info)
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    a = symmetrize(a)
    with torch.no_grad():
        trial = max_jitter * _jitter_scale(a)
    c2, i2 = torch.linalg.cholesky_ex(a + trial[..., None, None] * eye)
    ok2 = _chol_ok(c2, i2)
    factor = torch.where(ok[..., None, None], chol, torch.where(ok2[..., None, None], c2, eye))
    jitter = torch.where(ok, torch.zeros_like(trial), torch.where(ok2, trial, torch.full_like(trial, math.inf)))
    return CholeskyResult(factor, jitter)


def _semidefinite_factor(a: Tensor) -> tuple[Tensor, Tensor]:
    """Lower factor ``L`` with ``L L^T = a`` for symmetric positive *semi*-definite ``a``, and
    per element the largest negative pivot relative to its row's diagonal entry (0 when ``a``
    is semi-definite to rounding).

    A Cholesky recursion whose pivots at or below ``n * eps`` times their own diagonal entry
    ``a_jj`` count as zero (the row depends linearly on the previous ones up to rounding, in
    any units: a variance of 1e-8 next to one of 1 is not a zero pivot): their column is set to
    zero, which is the exact factor of a semi-definite matrix (its column below a zero pivot is
    zero too) and never divides by zero.  Branch-free with ``where`` on safe operands, so the
    gradient is finite (zero through the zero columns).
    """
    n = a.shape[-1]
    eps = torch.finfo(a.dtype).eps
    diag = torch.diagonal(a, dim1=-2, dim2=-1)
    floor = (n * eps) * diag.abs() + torch.finfo(a.dtype).tiny
    rows = torch.arange(n, device=a.device)
    cols: list[Tensor] = []
    deficit = torch.zeros_like(diag[..., 0])
    for j in range(n):
        col = a[..., :, j]
        for ck in cols:
            col = col - ck * ck[..., j : j + 1]
        pivot = col[..., j]
        ok = pivot > floor[..., j]
        ref = diag[..., j].abs()
        deficit = torch.maximum(deficit, (-pivot).clamp_min(0.0) / torch.where(ref > 0, ref, torch.ones_like(ref)))
        root = torch.sqrt(torch.where(ok, pivot, torch.ones_like(pivot)))
        new = torch.where(rows > j, col / root[..., None], torch.zeros_like(col))
        new = torch.where(rows == j, root[..., None], new)
        cols.append(torch.where(ok[..., None], new, torch.zeros_like(new)))
    return torch.stack(cols, -1), deficit


def psd_sqrt(a: Tensor) -> CholeskyResult:
    """Lower-triangular square root ``L`` (``L L^T = a``) of symmetric positive semi-definite
    ``a [..., n, n]``: what sigma points and square-root filters need from a covariance that
    may be singular (a rank-deficient process noise, the zero finite part of a diffuse prior).

    The common case is one ``cholesky_ex`` (identical to :func:`safe_cholesky`).  Elements whose
    factorisation fails get the exact semi-definite factor (zero columns for zero pivots, no
    jitter, ``jitter`` entry 0) when they are semi-definite to rounding (no pivot below
    ``-sqrt(eps)`` times its diagonal entry); genuinely indefinite or non-finite
    elements fall back to :func:`safe_cholesky`'s bounded jitter.
    """
    chol, info = torch.linalg.cholesky_ex(a)
    if vmapped(chol, info):
        # inside vmap: the exact semi-definite factor where the Cholesky factor fails (no jitter)
        ok = _chol_ok(chol, info)
        semi = _semidefinite_factor(
            symmetrize(torch.where(ok[..., None, None], torch.eye(a.shape[-1], dtype=a.dtype, device=a.device), a))
        )[0]
        return CholeskyResult(torch.where(ok[..., None, None], chol, semi), torch.zeros(info.shape, dtype=a.dtype, device=a.device))
    if not bool(info.any()) and bool(torch.isfinite(torch.diagonal(chol, dim1=-2, dim2=-1).sum())):
        return CholeskyResult(chol, torch.zeros(info.shape, dtype=a.dtype, device=a.device))
    a = symmetrize(a)
    finite = torch.isfinite(a).flatten(-2).all(-1)
    clean = torch.where(finite[..., None, None], a, torch.zeros_like(a))
    semi, deficit = _semidefinite_factor(clean)
    semi_ok = finite & (deficit <= torch.finfo(a.dtype).eps ** 0.5)
    if bool(semi_ok.all()):
        return CholeskyResult(semi, torch.zeros(info.shape, dtype=a.dtype, device=a.device))
    fallback = safe_cholesky(torch.where(semi_ok[..., None, None], torch.eye(a.shape[-1], dtype=a.dtype, device=a.device), a))
    factor = torch.where(semi_ok[..., None, None], semi, fallback.factor)
    return CholeskyResult(factor, torch.where(semi_ok, torch.zeros_like(fallback.jitter), fallback.jitter))


def psd_solve(a: Tensor, b: Tensor, *, chol: Tensor | None = None) -> Tensor:
    """Solve ``A X = B`` for symmetric positive-definite ``A [..., n, n]``, ``B [..., n, k]``.

    Uses a Cholesky factor (``chol`` if given, else :func:`safe_cholesky`); never an inverse.
    """
    if chol is None:
        chol = safe_cholesky(a).factor
    return torch.cholesky_solve(b, chol)


def joseph_update(cov: Tensor, gain: Tensor, obs_matrix: Tensor, noise_cov: Tensor) -> Tensor:
    """Joseph-form covariance update ``(I - K H) P (I - K H)^T + K R K^T`` (symmetrised).

    Shapes: ``cov [..., n, n]``, ``gain [..., n, m]``, ``obs_matrix [..., m, n]``,
    ``noise_cov [..., m, m]``.  Stays positive semi-definite for any gain, unlike
    ``P - K S K^T``.
    """
    n = cov.shape[-1]
    a = torch.eye(n, dtype=cov.dtype, device=cov.device) - gain @ obs_matrix
    return symmetrize(a @ cov @ a.mT + gain @ noise_cov @ gain.mT)


def tria(a: Tensor) -> Tensor:
    """Lower-triangular ``S [..., n, n]`` with ``S S^T = A A^T`` for ``A [..., n, k]``, ``k >= n``.

    QR re-triangularisation of a compound square-root matrix; the diagonal of the result is
    made non-negative so that the factor is the unique Cholesky factor.
    """
    # mode="r" is cheaper but not differentiable; use it only when no gradient is needed.
    mode = "reduced" if (a.requires_grad and torch.is_grad_enabled()) else "r"
    r = torch.linalg.qr(a.mT, mode=mode)[1]  # [..., n, n] upper, R^T R = A A^T
    s = r.mT
    sign = torch.sign(torch.diagonal(s, dim1=-2, dim2=-1))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    out: Tensor = s * sign[..., None, :]
    return out


def chol_rank1_update(chol: Tensor, v: Tensor, sign: float | Tensor = 1.0) -> Tensor:
    """Cholesky factor of ``L L^T + sign * v v^T`` for lower ``chol [..., n, n]``, ``v [..., n]``.

    A downdate (``sign < 0``) that would lose positive definiteness is clamped: the affected
    diagonal entry is floored at ``sqrt(eps) * |L_kk|`` rather than becoming NaN.  The loop runs
    over the ``n`` columns (never over the batch).
    """
    n = chol.shape[-1]
    sign_t = torch.as_tensor(sign, dtype=chol.dtype, device=chol.device)
    tiny = torch.finfo(chol.dtype).eps ** 0.5
    cols = []
    x = v
    lt = chol
    for k in range(n):
        lkk = lt[..., k, k]
        xk = x[..., k]
        r2 = lkk * lkk + sign_t * xk * xk
        r = torch.sqrt(torch.clamp(r2, min=(tiny * lkk) ** 2 + torch.finfo(chol.dtype).tiny))
        c = r / lkk
        s = xk / lkk
        col_below = (lt[..., k + 1 :, k] + sign_t * s[..., None] * x[..., k + 1 :]) / c[..., None]
        x = torch.cat([x[..., : k + 1], c[..., None] * x[..., k + 1 :] - s[..., None] * col_below], -1)
        col = torch.cat([torch.zeros_like(lt[..., :k, k]), r[..., None], col_below], -1)
        cols.append(col)
    return torch.stack(cols, -1)


def gaussian_log_density(
    residual: Tensor,
    chol: Tensor,
    num_obs: Tensor | float | None = None,
    *,
    whitened: Tensor | None = None,
    logdet: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """``log N(residual; 0, L L^T)`` and the Mahalanobis distance ``r^T (L L^T)^{-1} r``: the one
    Gaussian log-likelihood of the library (filters' innovations, losses, metrics).

    Args:
        residual: ``[..., m]``.
        chol: ``[..., m, m]`` lower Cholesky factor ``L``.
        num_obs: the number of observed components ``[...]`` when a mask has reduced the system
            (unobserved components carry a zero residual and a unit row/column of ``L``, so they
            add nothing to the distance or the log-determinant, only ``log 2 pi`` per count);
            ``None``: ``m``.
        whitened: ``L^{-1} residual [..., m]`` when the caller has it already (not recomputed).
        logdet: ``log det(L L^T) [...]`` when the caller has it already (e.g. one per time step
            shared by a batch).

    Returns:
        ``(log_density [...], mahalanobis [...])``.
    """
    w = torch.linalg.solve_triangular(chol, residual[..., None], upper=False)[..., 0] if whitened is None else whitened
    maha = (w * w).sum(-1)
    if logdet is None:
        logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    count = residual.shape[-1] if num_obs is None else num_obs
    return -0.5 * (maha + logdet + count * LOG_2PI), maha


def block_diag(*blocks: Tensor) -> Tensor:
    """Block-diagonal matrix of ``[..., d_i, d_i]`` blocks whose leading dims broadcast."""
    # torch.broadcast_shapes is defined without annotations in torch's own source
    shape = torch.broadcast_shapes(*(b.shape[:-2] for b in blocks))  # type: ignore[no-untyped-call]
    total = sum(b.shape[-1] for b in blocks)
    out = blocks[0].new_zeros(*shape, total, total)
    start = 0
    for b in blocks:
        d = b.shape[-1]
        out[..., start : start + d, start : start + d] = b
        start += d
    return out
