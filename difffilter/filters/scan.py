"""Parallel-in-time Kalman filtering and RTS smoothing of affine-Gaussian systems by an
associative scan (Särkkä & García-Fernández 2021, "Temporal parallelization of Bayesian
smoothers").

The system of a window of ``T`` steps, per trajectory ``b`` and step ``t`` (all tensors
batch-first ``[B, T, ...]``)::

    x_t = F_t x_{t-1} + c_t + w_t,   w_t ~ N(0, Q_t)
    z_t = H_t x_t + d_t + v_t,       v_t ~ N(0, R_t)

from ``x_{-1} ~ N(m0, P0)``, the filters' convention (every step predicts, then updates).

Filtering: each step becomes an element ``(A, b, C, eta, J)`` of the conditional
``p(x_t | x_{t-1}, z_t) = N(A x_{t-1} + b, C)`` and the likelihood ``p(z_t | x_{t-1})`` in
information form ``N_I(x_{t-1}; eta, J)``; step 0, whose ``x_{-1}`` is integrated out, gets
``A = 0``, ``eta = 0``, ``J = 0``.  The associative operator (``i`` before ``j``)::

    M = I + C_i J_j
    A_ij = A_j M^{-1} A_i              b_ij = A_j M^{-1} (b_i + C_i eta_j) + b_j
    C_ij = A_j M^{-1} C_i A_j^T + C_j
    eta_ij = A_i^T M^{-T} (eta_j - J_j b_i) + eta_i
    J_ij = A_i^T M^{-T} J_j A_i + J_i

An inclusive prefix scan gives ``(0, x_{t|t}, P_{t|t}, 0, 0)`` at every step.  The priors,
innovations and log-likelihoods follow from the filtered moments of the previous step in one
batched call, so they are the sequential filter's exactly (up to rounding).

Smoothing: the state ``x_k`` (``k = -1 .. T-1``) gets ``(E, g, L)`` with ``E = G`` the RTS
gain, ``g = x_{k|k} - G x^-_{k+1}``, ``L = P_{k|k} - G P^-_{k+1} G^T`` (the last one
``(0, x_{T-1|T-1}, P_{T-1|T-1})``); the operator ``(E_i E_j, E_i g_j + g_i, E_i L_j E_i^T + L_i)``
scanned from the end gives the smoothed moments.

:func:`associative_scan` is the work-efficient odd/even recursion (``O(T)`` work,
``2 log2 T`` sequential levels), written with batched tensor ops, so it runs the same way on
CPU and GPU and is differentiable and ``torch.func.vmap``-able.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from ..linalg import gaussian_log_density, psd_solve, safe_cholesky, symmetrize

__all__ = ["AffineSystem", "associative_scan", "scan_filter", "scan_rts", "scan_smoother"]

Elements = tuple[Tensor, ...]


class AffineSystem(NamedTuple):
    """Per-step matrices of an affine-Gaussian system, each expanded to ``[B, T, ...]``:
    ``F [B, T, n, n]``, ``c [B, T, n]``, ``Q [B, T, n, n]``, ``H [B, T, m, n]``, ``d [B, T, m]``,
    ``R [B, T, m, m]`` (module docstring)."""

    F: Tensor
    c: Tensor
    Q: Tensor
    H: Tensor
    d: Tensor
    R: Tensor


def _interleave(even: Elements, odd: Elements) -> Elements:
    """``[e0, o0, e1, o1, ...]`` along dim 1; ``even`` has as many entries as ``odd`` or one more."""
    out = []
    for e, o in zip(even, odd, strict=True):
        k = o.shape[1]
        pairs = torch.stack([e[:, :k], o], 2).reshape(e.shape[0], 2 * k, *e.shape[2:])
        out.append(torch.cat([pairs, e[:, k:]], 1) if e.shape[1] > k else pairs)
    return tuple(out)


def associative_scan(op: Callable[[Elements, Elements], Elements], elems: Elements, *, reverse: bool = False) -> Elements:
    """Inclusive scan of ``op`` over dim 1 (time) of the tensors ``elems`` (each ``[B, T, ...]``).

    ``op(x, y)`` combines elements ``x`` (earlier in scan order) and ``y`` (later), batched over
    all leading dimensions; it must be associative.  ``reverse=True`` scans from the last step
    (``op`` then gets the later time step as ``x``).  Work-efficient odd/even recursion: each
    level combines neighbouring pairs, recurses on the half-length sequence and fills in the
    even positions, so the sequential depth is ``O(log T)``.
    """
    if reverse:
        flipped = associative_scan(op, tuple(e.flip(1) for e in elems))
        return tuple(e.flip(1) for e in flipped)
    steps = elems[0].shape[1]
    if steps < 2:
        return elems
    reduced = op(tuple(e[:, 0:-1:2] for e in elems), tuple(e[:, 1::2] for e in elems))
    odd = associative_scan(op, reduced)
    later = tuple(e[:, 2::2] for e in elems)
    if later[0].shape[1] == 0:
        even: Elements = tuple(e[:, :1] for e in elems)
    else:
        earlier = odd if steps % 2 else tuple(o[:, :-1] for o in odd)
        even = tuple(torch.cat([e[:, :1], r], 1) for e, r in zip(elems, op(earlier, later), strict=True))
    return _interleave(even, odd)


def _mv(a: Tensor, v: Tensor) -> Tensor:
    return (a @ v[..., None])[..., 0]


def _filter_op(x: Elements, y: Elements) -> Elements:
    a1, b1, c1, eta1, j1 = x
    a2, b2, c2, eta2, j2 = y
    eye = torch.eye(a1.shape[-1], dtype=a1.dtype, device=a1.device)
    m = eye + c1 @ j2
    # A_j M^{-1} = (M^{-T} A_j^T)^T and A_i^T M^{-T} = (M^{-1} A_i)^T: solves, no inverse
    am = torch.linalg.solve(m.mT, a2.mT).mT
    at = torch.linalg.solve(m, a1).mT
    a = am @ a1
    b = _mv(am, b1 + _mv(c1, eta2)) + b2
    c = symmetrize(am @ c1 @ a2.mT + c2)
    eta = _mv(at, eta2 - _mv(j2, b1)) + eta1
    j = symmetrize(at @ j2 @ a1 + j1)
    return a, b, c, eta, j


def _smoother_op(x: Elements, y: Elements) -> Elements:
    # reverse scan: x is the later state's accumulated element, y the earlier state's own
    e1, g1, l1 = x
    e2, g2, l2 = y
    return e2 @ e1, _mv(e2, g1) + g2, symmetrize(e2 @ l1 @ e2.mT + l2)


def _masked(system: AffineSystem, z: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(H, z - d, R, num_observed)`` with unobserved components removed exactly: zero rows
    of ``H`` and of the residual, zero rows/columns of ``R`` with a unit diagonal (the update on
    the observed subset; see :func:`~difffilter.filters._common.mask_measurement_system`)."""
    resid = z - system.d
    if mask is None:
        m = z.shape[-1]
        return system.H, resid, system.R, torch.full(z.shape[:-1], float(m), dtype=z.dtype, device=z.device)
    obs = mask.to(z.dtype)
    h = system.H * obs[..., None]
    resid = torch.where(mask, resid, torch.zeros_like(resid))
    r = system.R * (obs[..., :, None] * obs[..., None, :]) + torch.diag_embed(1.0 - obs)
    return h, resid, r, obs.sum(-1)


def scan_filter(
    system: AffineSystem, z: Tensor, mask: Tensor | None, m0: Tensor, p0: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Kalman filter of ``system`` by a parallel scan.

    Args:
        system: the per-step matrices ``[B, T, ...]`` (:class:`AffineSystem`).
        z: measurements ``[B, T, m]`` (zeros where masked).
        mask: ``[B, T, m]`` bool (True = observed) or None.
        m0, p0: the belief about ``x_{-1}``, ``[B, n]``, ``[B, n, n]``.

    Returns ``(mean, cov, prior_mean, prior_cov, log_likelihood, nis, num_observed)`` with the
    shapes of :class:`~difffilter.filters.protocol.FilterResult`.
    """
    h, resid, r, nobs = _masked(system, z, mask)
    f, c, q = system.F, system.c, system.Q
    # step 0 integrates x_{-1} out: its element is the update of the first prediction
    prior0_mean = _mv(f[:, 0], m0) + c[:, 0]
    prior0_cov = symmetrize(f[:, 0] @ p0 @ f[:, 0].mT + q[:, 0])
    fe = torch.cat([torch.zeros_like(f[:, :1]), f[:, 1:]], 1)
    ce = torch.cat([prior0_mean[:, None], c[:, 1:]], 1)
    qe = torch.cat([prior0_cov[:, None], q[:, 1:]], 1)
    chol = safe_cholesky(symmetrize(h @ qe @ h.mT + r)).factor
    solve = lambda rhs: torch.linalg.solve_triangular(chol, rhs, upper=False)  # noqa: E731
    w = solve(h @ qe)  # L^{-1} H Q [B, T, m, n]
    v = solve((resid - _mv(h, ce))[..., None])[..., 0]  # L^{-1} (z - H c - d)
    gain = torch.linalg.solve_triangular(chol.mT, w, upper=True).mT  # K = Q H^T S^{-1}
    eye = torch.eye(f.shape[-1], dtype=f.dtype, device=f.device)
    ikh = eye - gain @ h
    a = ikh @ fe
    b = ce + _mv(w.mT, v)
    cc = symmetrize(ikh @ qe @ ikh.mT + gain @ r @ gain.mT)  # Joseph form
    u = solve(h @ fe)  # L^{-1} H F
    eta = _mv(u.mT, v)
    j = symmetrize(u.mT @ u)
    _, mean, cov, _, _ = associative_scan(_filter_op, (a, b, cc, eta, j))
    # priors and innovation statistics from the previous step's posterior, all steps at once
    prev_mean = torch.cat([m0[:, None], mean[:, :-1]], 1)
    prev_cov = torch.cat([p0[:, None], cov[:, :-1]], 1)
    prior_mean = _mv(f, prev_mean) + c
    prior_cov = symmetrize(f @ prev_cov @ f.mT + q)
    s_chol = safe_cholesky(symmetrize(h @ prior_cov @ h.mT + r)).factor
    loglik, nis = gaussian_log_density(resid - _mv(h, prior_mean), s_chol, nobs)
    return mean, cov, prior_mean, prior_cov, loglik, nis, nobs


def scan_smoother(
    system: AffineSystem, mean: Tensor, cov: Tensor, prior_mean: Tensor, prior_cov: Tensor, m0: Tensor, p0: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """RTS smoother of ``system`` by a reverse parallel scan over the filter's moments.

    Args:
        system: the per-step matrices (only ``F`` is used: ``prior_*`` carry ``c`` and ``Q``).
        mean, cov: filtered ``[B, T, n]``, ``[B, T, n, n]``.
        prior_mean, prior_cov: the filter's predictions at the same steps.
        m0, p0: the belief about ``x_{-1}`` ``[B, n]``, ``[B, n, n]``.

    Returns ``(mean, cov, cross_cov, initial_mean, initial_cov)`` smoothed, as
    :func:`~difffilter.smoothers.base.rts_backward` (``cross_cov[:, t] = P_{t-1,t|T}``).
    """
    prev_cov = torch.cat([p0[:, None], cov[:, :-1]], 1)
    # G_t = P_{t-1} F_t^T (P-_t)^{-1}, the gain between x_{t-1} and x_t (Cholesky solve)
    gains = psd_solve(symmetrize(prior_cov), (prev_cov @ system.F.mT).mT).mT
    return scan_rts(gains, mean, cov, prior_mean, prior_cov, m0, p0)


def scan_rts(
    gains: Tensor, mean: Tensor, cov: Tensor, prior_mean: Tensor, prior_cov: Tensor, m0: Tensor, p0: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The RTS backward recursion for given gains, by a reverse parallel scan.

    The recursion ``x_{t-1|T} = x_{t-1} + G_t (x_{t|T} - x-_t)``, ``P_{t-1|T} = P_{t-1} + G_t
    (P_{t|T} - P-_t) G_t^T`` is affine in the later smoothed moments whatever produced ``G_t``
    (KF, EKF or unscented gains), so it scans in ``O(log T)`` batched levels.

    Args:
        gains: ``G_t [B, T, n, n]`` between ``x_{t-1}`` (``x_{-1}`` for ``t = 0``) and ``x_t``.
        mean, cov, prior_mean, prior_cov, m0, p0: as :func:`scan_smoother`.

    Returns as :func:`scan_smoother`.
    """
    prev_mean = torch.cat([m0[:, None], mean], 1)  # x_{k|k}, k = -1 .. T-1
    prev_cov = torch.cat([p0[:, None], cov], 1)
    g = prev_mean[:, :-1] - _mv(gains, prior_mean)
    ell = symmetrize(prev_cov[:, :-1] - gains @ prior_cov @ gains.mT)
    e = torch.cat([gains, torch.zeros_like(gains[:, :1])], 1)
    g = torch.cat([g, mean[:, -1:]], 1)
    ell = torch.cat([ell, cov[:, -1:]], 1)
    _, s_mean, s_cov = associative_scan(_smoother_op, (e, g, ell), reverse=True)
    cross = gains @ s_cov[:, 1:]
    return s_mean[:, 1:], s_cov[:, 1:], cross, s_mean[:, 0], s_cov[:, 0]
