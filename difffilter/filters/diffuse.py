"""Exact filtering from a diffuse (very large) prior: the two-part covariance ``P = kappa P_inf + P_fin``.

A prior covariance ``1e24 I`` against a measurement noise ``1e-8`` spans 32 orders of magnitude,
twice what float64 resolves: the covariance-form prediction ``F P F^T + Q`` then rounds the
finite information away (after one position fix, ``Var(position) = 1e-8`` sits next to
``Var(velocity) = 1e24`` and ``F`` adds them), and no update formula can restore it.  Kept
apart, both parts stay exact:

* the belief carries ``"cov"`` = the finite part ``P_fin`` (what each filter's own predict and
  update work on: sigma points, Jacobians, square-root factors), ``"diffuse_cov"`` =
  ``P_inf`` (normalised, largest eigenvalue 1) and ``"diffuse_scale"`` = ``kappa [B]``;
* prediction: ``P_inf <- J P_inf J^T`` with the transition's Jacobian ``J`` (exact for linear
  dynamics; for nonlinear ones a direction of practically infinite variance has no other
  meaningful propagation), ``P_fin`` by the filter's own prediction;
* update: the joint Gaussian of ``[x; z]`` is conditioned on one measurement component at a
  time.  Its two parts are ``J_inf = [[P_inf, P_inf H^T], [H P_inf, H P_inf H^T]]`` and
  ``J_fin = [[P_fin, P_xz], [P_xz^T, P_zz]]`` (the filter's own moments, given as weighted
  deviations so that the update can run in Joseph form).  With ``a``, ``f`` the
  column and diagonal entry of the conditioned component, a component the diffuse part reaches
  (``f_inf > 0``) takes the gain ``k = (a_inf + a_fin / kappa) / (f_inf + f_fin / kappa)`` and

  ``J_inf <- J_inf - a_inf a_inf^T / f_inf``,
  ``J_fin <- J_fin - [a_inf a_fin^T + a_fin a_inf^T - (f_fin / f_inf) a_inf a_inf^T + a_fin a_fin^T / kappa] / (f_inf + f_fin / kappa)``,

  which is the covariance-form update ``J - a a^T / f`` of ``J = kappa J_inf + J_fin``
  rearranged so that no term of order ``kappa`` is ever subtracted from another: exact for any
  finite ``kappa`` (as ``kappa -> inf`` it becomes Koopman's exact initial Kalman filter).  The
  log-density ``log N(e; 0, kappa f_inf + f_fin)`` is evaluated as
  ``log kappa + log(f_inf + f_fin / kappa)``.  A component the diffuse part does not reach gets
  the ordinary update of ``J_fin``.  A state column that one update reduces to rounding
  (``|column| <= 8 d eps |column before|``) is set to exactly zero, so a measured coordinate
  leaves no ``kappa * eps`` residue behind; a measurement that resolves only a combination of
  states (a non-coordinate row of ``H``) leaves residues of order ``kappa * eps`` in the
  combination's cross-covariances, the rounding of the total covariance in those coordinates.

When every batch element's ``P_inf`` is exactly zero the diffuse entries are dropped and the
filter runs its ordinary recursion at its ordinary cost.

When to split (:func:`split_prior`): an eigen-direction ``u`` (variance ``lambda``) of the
initial covariance is diffuse when ``lambda * max_i (g_i^T u)^2`` exceeds ``eps^{-1/2}``
(``6.7e7`` in float64, ``2.9e3`` in float32), the rows ``g_i`` being the measurement rows
``H_i / sqrt(R_ii)`` and their propagation ``(H F^k)_i / sqrt(R_ii)`` over ``n - 1`` steps (the
directions the measurements will resolve): past that ratio the covariance form loses more than
half of the digits.  Directions no measurement reaches stay in ``P_fin``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..linalg import LOG_2PI, symmetrize, vmapped
from ..models.base import Controls, StateSpaceModel
from .jacobians import measurement_matrix, measurement_noise_cov, transition_matrix

__all__ = [
    "DIFFUSE_COV",
    "DIFFUSE_SCALE",
    "dangerous_ratio",
    "diffuse_update",
    "drop_resolved",
    "measurement_sensitivity",
    "propagate_diffuse",
    "split_prior",
    "total_cov",
]

DIFFUSE_COV = "diffuse_cov"
DIFFUSE_SCALE = "diffuse_scale"
_LOG_2PI = LOG_2PI


def dangerous_ratio(dtype: torch.dtype) -> float:
    """Prior-to-measurement variance ratio beyond which the covariance form keeps less than
    half of the digits of ``dtype`` (``eps^{-1/2}``)."""
    return torch.finfo(dtype).eps ** -0.5


def measurement_sensitivity(model: StateSpaceModel, mean: Tensor, u: Controls) -> Tensor:
    """Rows ``g [B, n m, n]``: ``(H F^k)_i / sqrt(R_ii)`` for ``k = 0..n-1`` at ``mean [B, n]``.

    ``(g^T u)^2 lambda`` is the variance ratio at which measurement ``i`` resolves a prior
    direction ``u`` of variance ``lambda``, directly (``k = 0``) or through the dynamics.
    Jacobians the model does not provide come from forward differences: a magnitude is all
    this needs, and any model a sigma-point filter runs can be differenced.
    """
    n = mean.shape[-1]
    # no torch.no_grad() here: inside parametrize.cached() it would cache Q and R without their
    # graph for the whole run; the result is detached instead
    h = measurement_matrix(model.measurement, mean, u, differences=True).detach()
    r = measurement_noise_cov(model.measurement, mean, u).detach()
    rdiag = torch.diagonal(r, dim1=-2, dim2=-1).expand(*mean.shape[:-1], h.shape[-2])
    inv_sd = torch.rsqrt(rdiag.clamp_min(torch.finfo(mean.dtype).tiny))
    f = transition_matrix(model.dynamics, mean, u, differences=True).detach()
    rows = [h]
    for _ in range(n - 1):
        rows.append(rows[-1] @ f)
    return torch.cat(rows, -2) * torch.cat([inv_sd] * n, -1)[..., None]


def split_prior(cov: Tensor, sensitivity: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """``(P_fin, P_inf, kappa)`` with ``cov = kappa P_inf + P_fin`` when some direction of
    ``cov [B, n, n]`` is dangerously large against ``sensitivity [B, k, n]`` (module docstring),
    else ``None``.  ``P_inf`` has largest eigenvalue 1; elements without a diffuse direction get
    ``P_inf = 0`` and ``kappa = 1``.  A diagonal ``cov`` is split without eigen-decomposition
    (exactly, and differentiably)."""
    limit = dangerous_ratio(cov.dtype)
    with torch.no_grad():
        gain = (sensitivity * sensitivity).sum(-1).amax(-1)  # max_i |g_i|^2
        bound = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1).abs() * gain
        # inside vmap a split that depends on the vmapped values cannot be decided: none is made
        if vmapped(bound) or not bool((bound > limit).any()):
            return None
    n = cov.shape[-1]
    diagonal = not vmapped(cov) and bool((cov * (1.0 - torch.eye(n, dtype=cov.dtype, device=cov.device)) == 0).all())
    if diagonal:
        lam = torch.diagonal(cov, dim1=-2, dim2=-1)
        vecs = torch.eye(n, dtype=cov.dtype, device=cov.device).expand_as(cov)
    else:
        lam, vecs = torch.linalg.eigh(symmetrize(cov))
    with torch.no_grad():
        reach = ((sensitivity @ vecs) ** 2).amax(-2)  # [B, n] per eigen-direction
        diffuse = lam.clamp_min(0.0) * reach > limit
        if vmapped(diffuse) or not bool(diffuse.any()):
            return None
    zero = torch.zeros_like(lam)
    kappa = torch.where(diffuse, lam, zero).amax(-1)
    kappa = torch.where(kappa > 0, kappa, torch.ones_like(kappa))
    inf_part = torch.where(diffuse, lam / kappa[..., None], zero)
    fin_part = torch.where(diffuse, zero, lam)
    if diagonal:
        return torch.diag_embed(fin_part), torch.diag_embed(inf_part), kappa
    p_inf = symmetrize((vecs * inf_part[..., None, :]) @ vecs.mT)
    p_fin = symmetrize((vecs * fin_part[..., None, :]) @ vecs.mT)
    return p_fin, p_inf, kappa


def total_cov(belief: dict[str, Tensor], key: str = "cov") -> Tensor:
    """``P_fin + kappa P_inf`` (just ``belief[key]`` when the belief has no diffuse part)."""
    if DIFFUSE_COV not in belief:
        return belief[key]
    return belief[key] + belief[DIFFUSE_SCALE][..., None, None] * belief[DIFFUSE_COV]


def drop_resolved(belief: dict[str, Tensor]) -> dict[str, Tensor]:
    """The belief without its diffuse entries once every ``*diffuse_cov*`` entry is zero."""
    keys = [k for k in belief if "diffuse" in k]
    if not keys or any(vmapped(belief[k]) or bool(belief[k].any()) for k in keys if "diffuse_cov" in k):
        return belief
    return {k: v for k, v in belief.items() if k not in keys}


def propagate_diffuse(
    belief: dict[str, Tensor], prior: dict[str, Tensor], jacobian: Tensor | None, model: StateSpaceModel, u: Controls
) -> None:
    """Set ``prior["diffuse_cov"] = J P_inf J^T`` (``J`` the given transition Jacobian at the
    posterior mean, or the model's) when ``belief`` has a diffuse part; in place."""
    if DIFFUSE_COV not in belief:
        return
    if jacobian is None:
        jacobian = transition_matrix(model.dynamics, belief["mean"], u)
    jac = jacobian.expand(*belief["mean"].shape[:-1], *jacobian.shape[-2:])
    prior[DIFFUSE_COV] = symmetrize(jac @ belief[DIFFUSE_COV] @ jac.mT)
    prior[DIFFUSE_SCALE] = belief[DIFFUSE_SCALE]


def _outer(a: Tensor, b: Tensor) -> Tensor:
    return a[..., :, None] * b[..., None, :]


def _condition_noise(noise: Tensor, gain: Tensor, i: int, active: Tensor) -> Tensor:
    """``A N A^T`` with ``A = I - k e_i^T`` where ``active [B]``, else ``N``."""
    col = noise[..., :, i]
    new = noise - _outer(gain, col) - _outer(col, gain) + noise[..., i, i][..., None, None] * _outer(gain, gain)
    return torch.where(active[..., None, None], new, noise)


def diffuse_update(
    mean: Tensor,
    diffuse_cov: Tensor,
    scale: Tensor,
    innovation: Tensor,
    deviations: tuple[Tensor, Tensor, Tensor, Tensor | None],
    diffuse_cross: Tensor,
    diffuse_innovation: Tensor,
    mask: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Exact update of a two-part belief (module docstring), in Joseph form.

    Args:
        mean, diffuse_cov, scale: prior ``x [B, n]``, ``P_inf [B, n, n]``, ``kappa [B]``.
        innovation: ``e = z - z_hat [B, m]``.
        deviations: the finite part as weighted deviations ``(dx [B, S, n], dz [B, S, m], wc
            [S], R [B, m, m] or None)``: ``J_fin = sum_s wc_s [dx_s; dz_s][dx_s; dz_s]^T`` plus
            ``R`` on the measurement block (None when ``dz`` already carries the noise).  Sigma
            points give them directly; a Kalman filter passes the columns of a square root of
            ``P_fin`` and their images under ``H``.
        diffuse_cross, diffuse_innovation: ``P_inf H^T [B, n, m]``, ``H P_inf H^T [B, m, m]``.
        mask: ``[B, m]`` True = observed, or None.

    Conditioning on a component multiplies the joint by ``A = I - k e_c^T`` on both sides; done
    on the deviations (``d_s <- d_s - k d_{s,c}``) and on the noise block separately, as the
    Joseph form does, so the finite part keeps ``eps^2``-level rounding however much one
    component reduces it (the κ-order difference between the exact and the limiting gain adds
    the rank-one term ``f_inf kappa dk dk^T``, ``dk = k - a_inf / f_inf``).

    Returns ``(mean, P_fin, P_inf, log_likelihood [B], nis [B], num_observed [B])``.
    """
    n, m = mean.shape[-1], innovation.shape[-1]
    d = n + m
    dtype = mean.dtype
    dx, dz, wc, noise_r = deviations
    bsz = mean.shape[:-1]
    dev = torch.cat([dx.expand(*bsz, *dx.shape[-2:]), dz.expand(*bsz, dz.shape[-2], m)], -1)  # [B, S, d]
    noise = mean.new_zeros(*bsz, d, d)
    if noise_r is not None:
        noise = torch.cat([noise[..., :n], torch.cat([noise.new_zeros(*bsz, n, m), noise_r.expand(*bsz, m, m)], -2)], -1)
    j_inf = torch.cat([torch.cat([diffuse_cov, diffuse_cross], -1), torch.cat([diffuse_cross.mT, diffuse_innovation], -1)], -2)
    w = torch.cat([mean, -innovation], -1)  # conditioning on z_c adds k * e_c to every entry
    inv_k = 1.0 / scale
    log_k = torch.log(scale)
    eps = torch.finfo(dtype).eps
    observed = torch.ones_like(innovation, dtype=torch.bool) if mask is None else mask
    loglik = torch.zeros_like(scale)
    nis = torch.zeros_like(scale)
    index = torch.arange(d, device=mean.device)
    for c in range(m):
        i = n + c
        e_c = -w[..., i]
        dev_c = dev[..., :, i]  # [B, S]
        a_fin = ((dev * (wc * dev_c)[..., None]).sum(-2)) + noise[..., :, i]
        f_fin = a_fin[..., i]
        a_inf, f_inf = j_inf[..., :, i], j_inf[..., i, i]
        tol = (1e3 * d * eps) * torch.diagonal(j_inf, dim1=-2, dim2=-1).abs().amax(-1)
        obs = observed[..., c]
        dif = obs & (f_inf > tol) & (f_inf > 0)
        fin = obs & ~dif
        # diffuse component (safe operands where it does not apply, so no NaN reaches gradients)
        f_safe = torch.where(dif, f_inf, torch.ones_like(f_inf))
        den = torch.where(dif, f_safe + f_fin * inv_k, torch.ones_like(f_inf))
        gain_d = (a_inf + a_fin * inv_k[..., None]) / den[..., None]
        new_inf = j_inf - _outer(a_inf, a_inf / f_safe[..., None])  # exact zero column for a unit-coefficient coordinate
        # kappa f_inf dk dk^T with dk = (f_inf a_fin - f_fin a_inf) / (f_inf kappa den)
        v = (f_safe[..., None] * a_fin - f_fin[..., None] * a_inf) / den[..., None]
        extra = _outer(v, v) * (inv_k / f_safe)[..., None, None]
        ll_d = -0.5 * (_LOG_2PI + log_k + torch.log(den) + e_c * e_c * inv_k / den)
        # a state column reduced to rounding is resolved: exact zero, no kappa * eps residue
        before = j_inf.abs().amax(-2)
        resolved = (new_inf.abs().amax(-2) <= (8 * d * eps) * before) | (index == i)
        new_inf = symmetrize(new_inf) * (~resolved)[..., :, None] * (~resolved)[..., None, :]
        # ordinary component
        g_safe = torch.where(fin, f_fin, torch.ones_like(f_fin)).clamp_min(torch.finfo(dtype).tiny)
        gain_f = a_fin / g_safe[..., None]
        ll_f = -0.5 * (_LOG_2PI + torch.log(g_safe) + e_c * e_c / g_safe)
        gain = torch.where(dif[..., None], gain_d, torch.where(fin[..., None], gain_f, torch.zeros_like(gain_f)))
        w = w + gain * torch.where(obs, e_c, torch.zeros_like(e_c))[..., None]
        dev = dev - dev_c[..., :, None] * gain[..., None, :]
        noise = _condition_noise(noise, gain, i, obs) + torch.where(dif[..., None, None], extra, torch.zeros_like(extra))
        j_inf = torch.where(dif[..., None, None], new_inf, j_inf)
        # the conditioned component is known exactly from here on
        keep = torch.where(obs[..., None], index != i, torch.ones_like(index, dtype=torch.bool))
        dev = dev * keep[..., None, :]
        noise = noise * keep[..., :, None] * keep[..., None, :]
        j_inf = j_inf * keep[..., :, None] * keep[..., None, :]
        loglik = loglik + torch.where(dif, ll_d, torch.where(fin, ll_f, torch.zeros_like(ll_f)))
        nis = nis + torch.where(dif, e_c * e_c * inv_k / den, torch.where(fin, e_c * e_c / g_safe, torch.zeros_like(ll_f)))
    num_obs = observed.to(dtype).sum(-1)
    dxn = dev[..., :n]
    p_fin = symmetrize((dxn * wc[:, None]).mT @ dxn + noise[..., :n, :n])
    return w[..., :n], p_fin, j_inf[..., :n, :n], loglik, nis, num_obs
