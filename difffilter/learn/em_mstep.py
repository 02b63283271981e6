"""Closed-form M-steps of EM for noise covariances and Markov-chain probabilities.

Given the E-step's expected residual moments (:mod:`difffilter.smoothers.expectations`), the
expected complete-data log-likelihood is maximised in closed form for each structure a
covariance can be registered with (:func:`difffilter.params.register_covariance`):

* ``full``: ``Q = S / N``, ``S = sum_{b,t} A_{b,t}``, ``N`` the number of transitions;
* ``diagonal``: ``Q = diag(S) / N``;
* ``scalar`` (``Q = s B`` with a fixed, possibly semi-definite ``B``):
  ``s = tr(B^+ S) / (N rank B)``.

For ``R`` the complete data are the states and the *observed* measurement components.  A fully
missing step contributes nothing.  With per-component masks, ``diagonal`` and ``scalar`` R count
each observed component (``R_ii = sum_t M_t,ii / #obs_i``; ``s = sum_t tr((B_OO)^+ M_t,OO) /
sum_t rank B_OO``), and ``full`` R uses the exact EM step of Shumway and Stoffer for partly
observed vectors: with ``O`` the observed set and the current ``R``,
``E[v v^T] = K M_t K^T + R - K R_O.`` with ``K = R_.O R_OO^{-1}`` (the unobserved noise
components regressed on the observed ones), which reduces to ``M_t`` on fully observed steps.

Markov chains (an IMM's modes): ``Pi[j, i] = sum_t P(j at t-1, i at t) / sum_{t,i'} P(j, i')``
from the smoother's expected transition counts, and the initial probabilities as the average
smoothed probabilities of the mode before the first measurement.

Every estimate is then moved into its constraint's set (eigenvalues clamped at a relative
``64 n eps``, the probability floor applied) so that assigning it cannot fail on rounding.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..constraints import PositiveDefinite, RowStochastic
from ..linalg import symmetrize
from ..params import ScaledMatrix

__all__ = [
    "covariance_structure",
    "markov_step",
    "measurement_noise_step",
    "process_noise_step",
    "to_constraint_set",
]


def covariance_structure(constraint: nn.Module) -> str:
    """``"full"``, ``"diagonal"`` or ``"scalar"`` for the constraints whose M-step is closed form;
    ``ValueError`` for the others."""
    if isinstance(constraint, PositiveDefinite):
        return "diagonal" if constraint.diagonal else "full"
    if isinstance(constraint, ScaledMatrix):
        return "scalar"
    raise ValueError(
        f"EM has no closed-form M-step for a covariance parametrised by {type(constraint).__name__} "
        "(supported structures: 'full', 'diagonal', 'scalar'); leave it out of learn="
    )


def _pinv_rank(base: Tensor) -> tuple[Tensor, Tensor]:
    """Pseudo-inverse ``[..., d, d]`` and numerical rank ``[...]`` of symmetric PSD ``base``."""
    lam, vecs = torch.linalg.eigh(symmetrize(base))
    tol = 64 * base.shape[-1] * torch.finfo(base.dtype).eps * lam.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(base.dtype).tiny)
    keep = lam > tol
    inv = torch.where(keep, 1.0 / torch.where(keep, lam, torch.ones_like(lam)), torch.zeros_like(lam))
    return (vecs * inv[..., None, :]) @ vecs.mT, keep.sum(-1)


def process_noise_step(total: Tensor, count: int, structure: str, base: Tensor | None = None) -> Tensor:
    """M-step for ``Q`` from ``total = sum A_t [n, n]`` over ``count`` transitions: the new value
    (a scalar scale for ``structure="scalar"``, whose fixed matrix is ``base``)."""
    if structure == "full":
        return symmetrize(total / count)
    if structure == "diagonal":
        return torch.diag_embed(torch.diagonal(total) / count)
    if base is None:
        raise ValueError("structure 'scalar' needs the base matrix")
    pinv, rank = _pinv_rank(base)
    return torch.trace(pinv @ total) / (count * rank.to(total.dtype))


def _patterns(obs: Tensor) -> tuple[Tensor, Tensor]:
    """Distinct observation patterns ``[P, m]`` of ``obs [B, T, m]`` and each step's pattern ``[B*T]``."""
    pats, inverse = torch.unique(obs.reshape(-1, obs.shape[-1]), dim=0, return_inverse=True)
    return pats, inverse


def measurement_noise_step(moments: Tensor, obs: Tensor, current: Tensor, structure: str, base: Tensor | None = None) -> Tensor:
    """M-step for ``R`` (module docstring).

    Args:
        moments: ``M_t [B, T, m, m]``, zero outside the observed components.
        obs: ``[B, T, m]`` bool, True = observed.
        current: the current ``R [m, m]`` (used for the partly observed steps of a full ``R``,
            and kept for components that are never observed).
        structure: ``"full"``, ``"diagonal"`` or ``"scalar"``.
        base: the fixed matrix of a ``scalar`` structure.

    Returns the new ``R`` (a scalar scale for ``scalar``).
    """
    m = current.shape[-1]
    obs_f = obs.to(moments.dtype)
    if structure == "diagonal":
        num = torch.diagonal(moments, dim1=-2, dim2=-1).sum((0, 1))
        cnt = obs_f.sum((0, 1))
        diag = torch.where(cnt > 0, num / cnt.clamp_min(1.0), torch.diagonal(current))
        return torch.diag_embed(diag)
    pats, inverse = _patterns(obs)
    sums = moments.new_zeros(pats.shape[0], m, m).index_add_(0, inverse, moments.reshape(-1, m, m))
    counts = torch.bincount(inverse, minlength=pats.shape[0]).to(moments.dtype)
    seen = pats.any(-1)
    if not bool(seen.any()):
        return current if structure == "full" else torch.ones((), dtype=current.dtype, device=current.device)
    pats, sums, counts = pats[seen], sums[seen], counts[seen]
    d = torch.diag_embed(pats.to(moments.dtype))  # [P, m, m]
    eye = torch.eye(m, dtype=moments.dtype, device=moments.device)
    if structure == "scalar":
        if base is None:
            raise ValueError("structure 'scalar' needs the base matrix")
        pinv, rank = _pinv_rank(d @ base @ d)
        num = torch.diagonal(pinv @ sums, dim1=-2, dim2=-1).sum()
        return num / (counts * rank.to(moments.dtype)).sum()
    a = d @ current @ d + (eye - d)
    gain = torch.linalg.solve(a, d @ current).mT @ d  # K = R D A^{-1} D
    total = gain @ sums @ gain.mT + counts[:, None, None] * (current - gain @ d @ current)
    return symmetrize(total.sum(0) / counts.sum())


def markov_step(pair_counts: Tensor, initial_probs: Tensor, current: Tensor) -> tuple[Tensor, Tensor]:
    """``(Pi, mu_0)`` from expected transition counts ``[M, M]`` (``[j, i]``: from ``j`` to ``i``)
    and the average smoothed initial mode probabilities ``[M]``; rows of modes never left keep
    ``current``'s."""
    rows = pair_counts.sum(-1, keepdim=True)
    pi = torch.where(rows > 0, pair_counts / rows.clamp_min(torch.finfo(pair_counts.dtype).tiny), current)
    return pi, initial_probs / initial_probs.sum()


def to_constraint_set(value: Tensor, constraint: nn.Module) -> Tensor:
    """``value`` moved just inside ``constraint``'s set, so that assigning it succeeds."""
    fi = torch.finfo(value.dtype)
    if isinstance(constraint, RowStochastic):
        m = value.shape[-1]
        p = value.clamp_min(0.0)
        p = p / p.sum(-1, keepdim=True)
        return constraint.floor + (1.0 - m * constraint.floor) * p
    if isinstance(constraint, ScaledMatrix):
        floor = constraint._scale.floor
        return value.clamp_min(max(floor * (1.0 + 1e-6), fi.tiny**0.5))
    if isinstance(constraint, PositiveDefinite):
        low = constraint.floor**2 * (1.0 + 1e-6) + 4.0 * fi.tiny**0.5
        if constraint.diagonal:
            return torch.diag_embed(torch.diagonal(value).clamp_min(low))
        n = value.shape[-1]
        lam, vecs = torch.linalg.eigh(symmetrize(value))
        lam = lam.clamp_min(max(low, 64 * n * fi.eps * float(lam.abs().max())))
        return symmetrize((vecs * lam[..., None, :]) @ vecs.mT)
    return value
