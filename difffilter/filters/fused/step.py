"""The batch-last, branch-free filter step that ``torch.compile`` fuses (the inductor engine).

Tensors are laid out batch-last (``mean [n, B]``, ``cov [n, n, B]``) and every small matrix
operation (Cholesky factor, triangular solves, products) is element-wise arithmetic over the
batch with no data-dependent branch, so one step is one straight-line graph.  Supported:
``UKF`` (additive noise, redrawn or reused points), ``SimplifiedUKF``, ``EKF`` and
``KalmanFilter`` (Joseph form or not), with masks, controls, angle residuals and
state-dependent noise.

The reference Cholesky retries a failing factor with bounded jitter; :func:`cholesky_lower`
clamps a non-positive pivot to ``n * eps * max(diag)`` instead and counts the clamps.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from ...models.base import Controls
from ..base import RecursiveFilter
from ..ekf import EKF
from ..ukf import UKF, SimplifiedUKF

__all__ = ["batch_last_step", "cholesky_lower", "filter_kind", "to_batch_last", "SmallMatmulAsSum"]

_LOG_2PI = math.log(2.0 * math.pi)
_MAX_CONTRACTION = 32


def filter_kind(filt: RecursiveFilter) -> str | None:
    """``"sukf"``, ``"ukf"`` or ``"ekf"`` (EKF and KalmanFilter) if this step implements ``filt``'s
    equations (not a subclass with its own ``predict``/``update``, additive noise), else None."""
    model = getattr(filt, "model", None)
    if model is None or not all(getattr(part, "additive_noise", True) for part in (model.dynamics, model.measurement)):
        return None  # this step adds Q and R; a model with non-additive noise needs the filter's own equations
    kinds = ((SimplifiedUKF, "sukf"), (UKF, "ukf"), (EKF, "ekf"))
    for cls, kind in kinds:
        if isinstance(filt, cls):
            same = all(getattr(type(filt), name) is getattr(cls, name) for name in ("predict", "update", "init_belief", "finalize_belief"))
            if not same or (kind == "ukf" and filt.noise != "additive"):
                return None
            if kind == "sukf" and callable(getattr(filt.model.dynamics, "linear_prediction", None)):
                return None  # its prediction takes (f, F, Q) from one call: only the generated engine runs it
            return kind
    return None


def transpose01(a: Tensor) -> Tensor:
    return a.transpose(0, 1)


def sum_terms(terms: list[Tensor]) -> Tensor:
    """Sum of same-shaped tensors as a chain of element-wise additions (stays in the fused loop)."""
    acc = terms[0]
    for t in terms[1:]:
        acc = acc + t
    return acc


def matmul_batch_last(a: Tensor, b: Tensor) -> Tensor:
    """``[i, k, B] @ [k, j, B] -> [i, j, B]`` (either factor may have batch size 1)."""
    return (a[:, :, None] * b[None]).sum(1)


def symmetrize(a: Tensor) -> Tensor:
    return 0.5 * (a + transpose01(a))


def cholesky_lower(a: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of ``a [n, n, B]`` and the number of clamped pivots ``[B]``.

    Branch-free: a pivot that is not above ``n * eps * max_j a_jj`` (rounding, a semi-definite
    or a non-finite matrix) is replaced by that floor, so one bad batch element never changes
    the others.  Elements are read with ``unbind`` (one backward node) rather than indexing.
    """
    n = a.shape[0]
    eps = torch.finfo(a.dtype).eps
    tiny = torch.finfo(a.dtype).tiny
    el = [list(r.unbind(0)) for r in a.unbind(0)]
    diag = torch.stack([el[j][j] for j in range(n)])
    floor = (n * eps) * diag.abs().amax(0) + tiny
    rows: list[list[Tensor]] = [[] for _ in range(n)]  # rows[i][j] = L_ij for j <= i
    clamps = torch.zeros_like(floor)
    for j in range(n):
        s = el[j][j]
        for k in range(j):
            s = s - rows[j][k] * rows[j][k]
        ok = s > floor
        clamps = clamps + (~ok).to(a.dtype)
        d = torch.sqrt(torch.where(ok, s, floor))
        rows[j].append(d)
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = el[i][j]
            for k in range(j):
                s = s - rows[i][k] * rows[j][k]
            rows[i].append(s * inv)
    zero = torch.zeros_like(floor)
    return torch.stack([torch.stack(r + [zero] * (n - len(r))) for r in rows]), clamps


def sigma_offsets(cov: Tensor, gamma: float, has_center: bool) -> tuple[Tensor, Tensor]:
    """Sigma-point offsets ``[S, n, B]`` from the mean (``0`` if centred, ``+-gamma L[:, i]``, the
    order of :class:`~difffilter.filters.SigmaPoints`) of ``cov [n, n, B]``, and clamped pivots."""
    factor, clamps = cholesky_lower(cov)
    cols = transpose01(factor) * gamma  # row i = column i of L
    centre = [torch.zeros_like(cols[:1])] if has_center else []
    return torch.cat(centre + [cols, -cols], 0), clamps


def solve_lower(factor: Tensor, b: Tensor) -> Tensor:
    """``L^{-1} b`` for lower-triangular ``L [m, m, B]`` and ``b [m, k, B]`` (forward substitution)."""
    m = factor.shape[0]
    el = [list(r.unbind(0)) for r in factor.unbind(0)]
    rhs = b.unbind(0)
    xs: list[Tensor] = []
    for i in range(m):
        s = rhs[i]
        for k in range(i):
            s = s - el[i][k][None] * xs[k]
        xs.append(s / el[i][i][None])
    return torch.stack(xs)


def solve_lower_transposed(factor: Tensor, b: Tensor) -> Tensor:
    """``L^{-T} b`` for lower-triangular ``L [m, m, B]`` and ``b [m, k, B]`` (back substitution)."""
    m = factor.shape[0]
    el = [list(r.unbind(0)) for r in factor.unbind(0)]
    rhs = b.unbind(0)
    xs: list[Tensor | None] = [None] * m
    for i in range(m - 1, -1, -1):
        s = rhs[i]
        for k in range(i + 1, m):
            s = s - el[k][i][None] * xs[k]  # type: ignore[operator]
        xs[i] = s / el[i][i][None]
    return torch.stack(xs)  # type: ignore[arg-type]


def to_batch_last(mat: Tensor, rank: int) -> Tensor:
    """Batch-first ``[B?, ...]`` model output of ``rank`` trailing dims -> batch-last (size-1 batch if none)."""
    if mat.ndim == rank:
        return mat[..., None]
    if mat.ndim != rank + 1:
        raise ValueError(f"expected a [{', '.join('d' * rank)}] or [B, ...] tensor from the model, got shape {tuple(mat.shape)}")
    return mat.permute(*range(1, rank + 1), 0)


def _call_points(fn: Callable[..., Tensor], pts: Tensor, u: Controls) -> Tensor:
    """Apply a batch-first model function to points ``[S, d, B]`` (as the view ``[S, B, d]``)."""
    return fn(pts.transpose(1, 2), u).transpose(1, 2)


def _weighted_mean(pts: Tensor, wm: Tensor) -> Tensor:
    """Weighted mean of points ``[S, d, B]`` relative to the first point (see ``ukf.weighted_mean``)."""
    ref = pts[0]
    return ref + ((pts - ref[None]) * wm[:, None, None]).sum(0)


def _weighted_cov(a: Tensor, b: Tensor, wc: Tensor) -> Tensor:
    """``sum_s wc_s a_s b_s^T`` for ``a [S, p, B]``, ``b [S, q, B]`` -> ``[p, q, B]``."""
    return ((wc[:, None, None] * a)[:, :, None] * b[:, None]).sum(0)


_MATMULS = (torch.matmul, torch.Tensor.matmul, torch.Tensor.__matmul__, torch.bmm, torch.mm)


class SmallMatmulAsSum(torch.overrides.TorchFunctionMode):
    """Inside the step, matrix products with a short contraction (a model's ``x @ F.mT``,
    ``H @ x``...) become broadcast multiply-and-sum: the compiler then fuses them with the
    rest of the step instead of calling an external GEMM on tiny matrices, which splits the
    step's kernel in two."""

    def __torch_function__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        if func in _MATMULS and not kwargs and len(args) == 2:
            a, b = args
            if isinstance(a, Tensor) and isinstance(b, Tensor) and a.ndim >= 2 and b.ndim >= 2 and a.shape[-1] <= _MAX_CONTRACTION:
                return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
        return func(*args, **(kwargs or {}))


def _noise(static: Tensor | None, fn: Callable[[Tensor, Controls], Tensor], mean: Tensor, u: Controls) -> Tensor:
    return static if static is not None else to_batch_last(fn(transpose01(mean), u), 2)


def _joseph_where_lossy(
    new_cov: Tensor,
    prior_cov: Tensor,
    factor: Tensor,
    w: Tensor,
    observed: Tensor | None,
    jac: Tensor | None,
    r: Tensor,
    dx: Tensor | None,
    dz: Tensor | None,
    wc: Tensor | None,
) -> Tensor:
    """``new_cov [n, n, B]`` where ``P - K S K^T`` keeps its digits, else the Joseph form: of the
    linearised system (``jac`` given) or of the sigma-point deviations ``dx [S, n, B]``,
    ``dz [S, m, B]`` with weights ``wc`` (the reference's ``gaussian_update`` fallbacks)."""
    n = new_cov.shape[0]
    switch = 64.0 * torch.finfo(new_cov.dtype).eps ** 0.5
    lossy = torch.zeros_like(new_cov[0, 0], dtype=torch.bool)
    for i in range(n):
        lossy = lossy | (new_cov[i, i] < switch * prior_cov[i, i])
    gain = transpose01(solve_lower_transposed(factor, w))  # K = W^T L^{-1}: [n, m, B]
    rm = r if observed is None else r * (observed[:, None] * observed[None])
    gr = matmul_batch_last(matmul_batch_last(gain, rm), transpose01(gain))
    if jac is not None:
        h = jac if observed is None else jac * observed[:, None]
        a = torch.eye(n, dtype=new_cov.dtype, device=new_cov.device)[..., None] - matmul_batch_last(gain, h)
        stable = matmul_batch_last(matmul_batch_last(a, prior_cov), transpose01(a)) + gr
    else:
        dzm = dz if observed is None else dz * observed[None]  # type: ignore[index]
        dev = dx - (gain[None] * dzm[:, None]).sum(2)  # type: ignore[operator] # dx_s - K dz_s: [S, n, B]
        stable = _weighted_cov(dev, dev, wc) + gr  # type: ignore[arg-type]
    return torch.where(lossy, symmetrize(stable), new_cov)


def batch_last_step(
    filt: RecursiveFilter,
    kind: str,
    mean: Tensor,
    cov: Tensor,
    z: Tensor,
    observed: Tensor | None,
    u: Controls,
    q_static: Tensor | None,
    r_static: Tensor | None,
) -> tuple[Tensor, ...]:
    """One predict/update of ``filt`` (of :func:`filter_kind` ``kind``) on ``mean [n, B]``,
    ``cov [n, n, B]`` and ``z [B, m]``; ``observed [m, B]`` (1.0 observed, 0.0 missing) or
    None; ``q_static``/``r_static`` batch-last noise matrices or None (state dependent).
    Returns the posterior, the prior, log-likelihood, NIS, observed count, clamped pivots and
    clamped pivots of the innovation covariance, batch-last.

    As in :func:`~difffilter.filters.update.gaussian_update`, a posterior covariance whose
    variance ``P - K S K^T`` falls below ``64 sqrt(eps)`` times its prior is taken from the
    Joseph form instead (branch-free: computed every step, selected per trajectory)."""
    dyn, meas = filt.model.dynamics, filt.model.measurement
    n = mean.shape[0]
    clamps = torch.zeros_like(mean[0])
    q = _noise(q_static, dyn.process_noise, mean, u)

    # ---- predict
    update_offsets = None  # offsets of the update's points from the prior mean (reused points)
    if kind == "ukf":
        sp = filt.sigma_points
        wm, wc = sp.weights(n, mean.dtype, mean.device)
        gamma = sp.gamma(n)
        offsets, c = sigma_offsets(cov, gamma, sp.has_center)
        clamps = clamps + c
        propagated = _call_points(dyn, mean[None] + offsets, u)
        prior_mean = _weighted_mean(propagated, wm)
        dev = propagated - prior_mean[None]
        prior_cov = symmetrize(_weighted_cov(dev, dev, wc) + q)
        if not filt.redraw_after_predict:
            q_factor, c = cholesky_lower(q)
            clamps = clamps + c
            qcols = (transpose01(q_factor) * gamma).expand(-1, -1, dev.shape[-1])
            update_offsets = torch.cat([dev, qcols, -qcols], 0)
            wq = torch.full((2 * n,), 0.5 / gamma**2, dtype=mean.dtype, device=mean.device)
            update_wm = torch.cat([wm, torch.zeros_like(wq)])
            update_wc = torch.cat([wc, wq])
    else:
        if kind == "sukf":
            f = to_batch_last(dyn.matrix(u), 2)
        else:
            f = to_batch_last(filt.transition_jacobian(transpose01(mean), u), 2)
        prior_mean = _call_points(dyn, mean[None], u)[0]
        prior_cov = symmetrize(matmul_batch_last(matmul_batch_last(f, cov), transpose01(f)) + q)

    # ---- update
    r = _noise(r_static, meas.measurement_noise, prior_mean, u)
    jac = None
    if kind in ("ukf", "sukf"):
        if update_offsets is None:
            sp = filt.sigma_points
            update_wm, update_wc = sp.weights(n, mean.dtype, mean.device)
            update_offsets, c = sigma_offsets(prior_cov, sp.gamma(n), sp.has_center)
            clamps = clamps + c
        zs = _call_points(meas, prior_mean[None] + update_offsets, u)
        zhat = _weighted_mean(zs, update_wm)
        dz = meas.residual(zs.transpose(1, 2), transpose01(zhat)[None]).transpose(1, 2)
        pzz = _weighted_cov(dz, dz, update_wc) + r  # only its lower triangle is read
        pxz = _weighted_cov(update_offsets, dz, update_wc)
    else:
        jac = to_batch_last(filt.measurement_jacobian(transpose01(prior_mean), u), 2)  # [m, n, B] or [m, n, 1]
        zhat = _call_points(meas, prior_mean[None], u)[0]
        pxz = matmul_batch_last(prior_cov, transpose01(jac))
        pzz = matmul_batch_last(jac, pxz) + r
    e = transpose01(meas.residual(z, transpose01(zhat)))  # [m, B]
    mdim = e.shape[0]
    if observed is not None:
        e = e * observed
        pxz = pxz * observed[None]
        pzz = pzz * (observed[:, None] * observed[None]) + torch.diag_embed(transpose01(1.0 - observed)).permute(1, 2, 0)
        num_obs = observed.sum(0)
    else:
        num_obs = torch.full_like(mean[0], float(mdim))
    factor, s_clamps = cholesky_lower(pzz)
    clamps = clamps + s_clamps
    sol = solve_lower(factor, torch.cat([transpose01(pxz), e[:, None]], 1))  # [m, n + 1, B]
    w, v = sol[:, :-1], sol[:, -1]
    new_mean = prior_mean + sum_terms([w[i] * v[i] for i in range(mdim)])
    if kind == "ekf" and filt.joseph:
        gain = transpose01(solve_lower_transposed(factor, w))  # K = W^T L^{-1}: [n, m, B]
        h, rm = jac, r
        if observed is not None:
            h = jac * observed[:, None]
            rm = r * (observed[:, None] * observed[None])
        eye = torch.eye(n, dtype=mean.dtype, device=mean.device)[..., None]
        a = eye - matmul_batch_last(gain, h)
        new_cov = symmetrize(
            matmul_batch_last(matmul_batch_last(a, prior_cov), transpose01(a))
            + matmul_batch_last(matmul_batch_last(gain, rm), transpose01(gain))
        )
    else:
        new_cov = prior_cov - sum_terms([w[i][:, None] * w[i][None] for i in range(mdim)])  # P- - W^T W
        new_cov = _joseph_where_lossy(
            new_cov,
            prior_cov,
            factor,
            w,
            observed,
            jac,
            r,
            update_offsets if jac is None else None,
            dz if jac is None else None,
            update_wc if jac is None else None,
        )
    maha = sum_terms([v[i] * v[i] for i in range(mdim)])
    logdet = 2.0 * sum_terms([torch.log(factor[i, i]) for i in range(mdim)])
    ll = -0.5 * (maha + logdet + num_obs * _LOG_2PI)
    return new_mean, new_cov, prior_mean, prior_cov, ll, maha, num_obs, clamps, s_clamps
