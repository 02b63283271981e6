"""The shared Gaussian measurement update of every Kalman-family filter.

:func:`gaussian_update` (covariance form, with the Joseph forms where they are needed) and
:func:`diffuse_gaussian_update` (the exact update of a belief with a diffuse part, see
:mod:`difffilter.filters.diffuse`), and the exact removal of unobserved components
(:func:`~difffilter.filters._common.mask_measurement_system`).  Re-exported by
:mod:`difffilter.filters.base`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from ..linalg import (
    any_set,
    gaussian_log_density,
    joseph_update,
    nonfinite_rows,
    psd_sqrt,
    safe_cholesky,
    symmetrize,
)
from ._common import StepInfo, mask_measurement_system, rounding_flags
from .diffuse import DIFFUSE_COV, DIFFUSE_SCALE, diffuse_update
from .protocol import Belief

__all__ = [
    "JosephForm",
    "diffuse_gaussian_update",
    "gaussian_update",
    "rounding_flags",
    "rounding_terms",
    "rounding_untrusted",
    "square_root_deviations",
    "untrusted_steps",
]


def _trust_limits(dtype: torch.dtype) -> tuple[float, float, float]:
    """``(switch, standard, joseph)``: the posterior/prior variance ratio below which the
    ``P - K S K^T`` form switches to a Joseph-type form (``64 sqrt(eps)``: measured errors of
    that form reach ``~20 eps / ratio``, so it keeps about half of the digits), and the ratios
    below which each form's relative rounding error (``eps / ratio``, resp. ``eps^2 / ratio``)
    exceeds ``1e-2``."""
    eps = torch.finfo(dtype).eps
    return 64.0 * eps**0.5, eps / 1e-2, eps * eps / 1e-2


def rounding_untrusted(chol: Tensor, whitened: Tensor, innovation_cov: Tensor, prediction: Tensor | None, mask: Tensor | None) -> Tensor:
    """``[B]`` steps whose log-likelihood, gain or innovation the working precision cannot resolve.

    * A nearly singular ``S``: forming ``S`` (and factorising it) perturbs it by ``dS`` with
      ``||dS|| <~ m eps max_j S_jj``, which moves ``log det S`` by ``tr(S^-1 dS)`` and the
      Mahalanobis term ``d`` by ``e^T S^-1 dS S^-1 e``: to first order at most
      ``0.5 m eps max_j S_jj (tr(S^-1) + |S^-1 e|^2)`` nats (``S^-1 e = L^-T v``), with
      ``tr(S^-1)`` estimated by ``sum_i 1 / L_ii^2`` (the diagonal of ``L^-1``: a lower bound,
      within a factor ``m`` where the factor reveals the small pivots, as it does for these small
      systems).  Flagged where
      that exceeds ``1e-2 + 1e-4 d`` (a huge innovation is only resolved relatively).  The same
      bound covers the gain's error in ``S``'s weak directions (``P_xz`` and ``S`` are rounded
      apart, so ``K e`` keeps about ``eps cond(S)``), which is why the square-root UKF, whose
      ``S`` itself is accurate, uses it too.
    * ``prediction`` ``z_hat [B, m]``: the innovation ``z - z_hat`` carries an absolute rounding
      error ``eps |z_hat|`` (and so does ``z_hat`` itself, e.g. a range of 2e7 m in float32 keeps
      ~2 m); the correction of the mean then moves by that error in units of ``sqrt(S_jj)``.
      Flagged where ``eps |z_hat_j| > 1e-2 sqrt(S_jj)`` for an observed component.

    ``chol`` ``[B, m, m]``, ``whitened`` ``v = L^-1 e [B, m]`` and ``innovation_cov`` are those of the masked system
    (:func:`gaussian_update`).  A handful of elementwise operations per step, not differentiated
    (a flag).
    """
    return rounding_flags(chol, whitened, torch.diagonal(innovation_cov, dim1=-2, dim2=-1), prediction, mask)


def rounding_terms(
    chol: Tensor, whitened: Tensor, innovation_cov: Tensor, prediction: Tensor | None, mask: Tensor | None
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None]:
    """What :func:`rounding_untrusted` reads (detached; ``S`` only by its diagonal), for
    :attr:`StepInfo.rounding`: the check made later, for many steps at once."""
    var = torch.diagonal(innovation_cov, dim1=-2, dim2=-1).detach()
    return chol.detach(), whitened.detach(), var, None if prediction is None else prediction.detach(), mask


class JosephForm(NamedTuple):
    """The Joseph-type covariance form that :func:`gaussian_update` uses instead of, or as the
    fallback of, ``P - K S K^T``; build it with :meth:`linear` or :meth:`sigma_points`.

    Attributes:
        r: measurement noise ``R [B, m, m]`` (``None`` when sigma points already carry it).
        h: ``H [B, m, n]`` for the linear form ``(I - K H) P (I - K H)^T + K R K^T``.
        points: ``(dx [B, S, n], dz [B, S, m], wc [S])`` sigma-point deviations for the unscented
            form ``sum_i wc_i (dx_i - K dz_i)(dx_i - K dz_i)^T + K R K^T``.
        always: use the form for every batch element (KF/EKF ``joseph=True``); otherwise only
            on the elements where ``P - K S K^T`` cancels (see :func:`gaussian_update`).
    """

    r: Tensor | None
    h: Tensor | None = None
    points: tuple[Tensor, Tensor, Tensor] | None = None
    always: bool = False

    @classmethod
    def linear(cls, h: Tensor, r: Tensor, *, always: bool = False) -> JosephForm:
        """The linear Joseph form with ``H`` and ``R``; ``always``: on every element."""
        return cls(r, h=h, always=bool(always))

    @classmethod
    def sigma_points(cls, dx: Tensor, dz: Tensor, wc: Tensor, r: Tensor | None) -> JosephForm:
        """The unscented Joseph form of sigma-point deviations, as a fallback."""
        return cls(r, points=(dx, dz, wc))

    def covariance(self, cov: Tensor, gain: Tensor, mask: Tensor | None) -> Tensor:
        """The posterior covariance in this form from the prior ``cov`` and the gain ``K``."""
        if self.h is not None:
            return joseph_update(cov, gain, *_masked_system(self.h, self.r, mask))  # type: ignore[arg-type]
        if self.points is None:
            raise ValueError("JosephForm needs h (JosephForm.linear) or points (JosephForm.sigma_points)")
        return _sigma_joseph(gain, *self.points, self.r, mask)


def gaussian_update(
    mean: Tensor,
    cov: Tensor,
    innovation: Tensor,
    innovation_cov: Tensor,
    cross_cov: Tensor,
    mask: Tensor | None,
    *,
    joseph: JosephForm | None = None,
    add: Callable[[Tensor, Tensor], Tensor] | None = None,
    prediction: Tensor | None = None,
) -> tuple[Tensor, Tensor, StepInfo]:
    """Linear-Gaussian measurement update shared by every Kalman-family filter.

    Args:
        mean, cov: prior ``[B, n]``, ``[B, n, n]``.
        innovation: ``e = z - z_hat`` ``[B, m]``.
        innovation_cov: ``S [B, m, m]`` (measurement noise included).
        cross_cov: ``P_xz [B, n, m]``.
        mask: ``[B, m]`` bool, True = observed (``None``: all observed).
        joseph: the :class:`JosephForm`: with ``always`` the covariance is formed that way
            (KF/EKF ``joseph=True``), else it is the fallback on the batch elements where
            ``P - K S K^T`` cancels (below); ``None``: ``P - K S K^T`` only.
        add: ``add(x, dx)``, the state addition (e.g. ``DynamicsModel.add`` wrapping angular
            states) for the mean correction; None adds plainly.
        prediction: the predicted measurement ``z_hat [B, m]``, whose size sets the rounding
            of the innovation (:func:`rounding_untrusted`).

    Returns the posterior mean and covariance and the :class:`StepInfo`.  The gain is never
    formed through an inverse: with ``S = L L^T``, ``W = L^{-1} P_xz^T`` gives
    ``K e = W^T L^{-1} e`` and ``K S K^T = W^T W``.

    ``P - K S K^T`` subtracts two numbers of the prior's size, so a variance that one update
    reduces by a factor ``rho`` keeps about ``eps / rho`` relative accuracy; the Joseph forms
    subtract only inside ``I - K H`` and keep about ``eps^2 / rho``.  Where a posterior variance
    falls below ``64 sqrt(eps)`` times its prior (``9.5e-7`` in float64, ``2.2e-2`` in float32)
    and a fallback is given, those batch elements are recomputed in the fallback's Joseph form;
    ``StepInfo.jitter`` is ``S``'s repair (0 if none); without a Joseph form or a fallback,
    ``StepInfo.untrusted`` marks elements whose reduction ``P - K S K^T`` cannot resolve to
    ``1e-2``; ``StepInfo.flags()`` also marks the steps :func:`rounding_untrusted` finds
    unresolved (a nearly singular ``S``, an innovation below the rounding of ``z_hat``), a check
    left pending in ``StepInfo.rounding`` so that the time loop makes it for a block of steps at
    once.  The time loop flags the rest over the whole run at once (:func:`untrusted_steps`), so
    this function adds no per-step work for it.
    """
    innovation, innovation_cov, cross_cov, num_obs = mask_measurement_system(innovation, innovation_cov, cross_cov, mask)
    chol, jitter = safe_cholesky(innovation_cov)
    rhs = torch.cat([cross_cov.mT, innovation[..., None]], -1)  # [B, m, n+1]
    sol = torch.linalg.solve_triangular(chol, rhs, upper=False)
    w, v = sol[..., :-1], sol[..., -1]  # W [B, m, n], v = L^{-1} e [B, m]
    correction = (w.mT @ v[..., None])[..., 0]
    new_mean = mean + correction if add is None else add(mean, correction)
    untrusted = None
    if joseph is None or not joseph.always:
        new_cov = symmetrize(cov - w.mT @ w)
        switch, std_limit, _ = _trust_limits(mean.dtype)
        prior_var = torch.diagonal(cov, dim1=-2, dim2=-1)
        post_var = torch.diagonal(new_cov, dim1=-2, dim2=-1)
        if joseph is None:
            untrusted = ~(post_var >= std_limit * prior_var).all(-1)
        elif any_set(post_var < switch * prior_var):
            lossy = (post_var < switch * prior_var).any(-1)
            gain = torch.linalg.solve_triangular(chol.mT, w, upper=True).mT  # K = W^T L^{-1}
            new_cov = torch.where(lossy[..., None, None], joseph.covariance(cov, gain, mask), new_cov)
    else:
        gain = torch.linalg.solve_triangular(chol.mT, w, upper=True).mT  # K = W^T L^{-1}
        new_cov = joseph.covariance(cov, gain, mask)
    loglik, maha = gaussian_log_density(innovation, chol, num_obs, whitened=v)
    # the rounding check deferred (StepInfo.flags, or the time loop for a block of steps at once)
    rounding = rounding_terms(chol, v, innovation_cov, prediction, mask)
    info = StepInfo(loglik, maha, num_obs, innovation, innovation_cov, untrusted, jitter, rounding)
    return new_mean, new_cov, info


def untrusted_steps(mean: Tensor, cov: Tensor, prior_cov: Tensor, log_likelihood: Tensor, exact: Tensor | None = None) -> Tensor:
    """``[B, T]`` steps whose posterior cannot be vouched for to ``1e-2`` in a Joseph-type
    update (the weakest form every filter here ends up using): a variance reduced below
    ``eps^2 / 1e-2`` of its prior (``4.9e-30`` in float64, ``1.4e-12`` in float32), a negative
    or non-finite variance, a non-finite mean or log-likelihood.  ``exact [T]`` (bool) marks
    steps to leave out (diffuse-part updates, which flag themselves).  Vectorised over the run."""
    limit = _trust_limits(mean.dtype)[2]
    post_var = torch.diagonal(cov, dim1=-2, dim2=-1)
    prior_var = torch.diagonal(prior_cov, dim1=-2, dim2=-1)
    # a NaN compares False, so non-finite variances are flagged too; whole-run checks first
    # (one reduction each: nonfinite_rows' sum), per-step reductions only when one fails
    # (inside vmap, where values cannot be read, the per-step reductions always run: same value)
    if any_set(nonfinite_rows(log_likelihood, 0)):
        bad = ~torch.isfinite(log_likelihood)
    else:
        bad = torch.zeros(log_likelihood.shape, dtype=torch.bool, device=log_likelihood.device)
    low = ~(post_var >= limit * prior_var)
    if any_set(low):
        bad = bad | low.any(-1)
    if any_set(nonfinite_rows(mean, 0)):
        bad = bad | nonfinite_rows(mean, mean.dim() - 1)
    if exact is not None:
        bad = bad & ~exact
    return bad


def diffuse_gaussian_update(
    belief: Belief,
    innovation: Tensor,
    deviations: tuple[Tensor, Tensor, Tensor, Tensor | None],
    mask: Tensor | None,
    *,
    obs_matrix: Tensor | None = None,
    diffuse_cross: Tensor | None = None,
    diffuse_innovation: Tensor | None = None,
    add: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> tuple[Belief, StepInfo]:
    """:func:`gaussian_update` for a belief with a diffuse part (``"diffuse_cov"``).

    ``deviations`` ``(dx [B, S, n], dz [B, S, m], wc [S], R or None)`` describe the finite part's
    joint moments (:func:`~difffilter.filters.diffuse.diffuse_update`); the diffuse part enters
    through the measurement Jacobian ``obs_matrix`` ``H [B, m, n]`` (or ``[m, n]``), or directly
    through ``P_inf H^T`` and ``H P_inf H^T`` (``diffuse_cross``, ``diffuse_innovation``) when
    the measurement is not a function of the current state alone; ``add`` as for
    :func:`gaussian_update`.  Returns the belief entries
    ``mean``, ``cov`` (finite part), ``diffuse_cov``, ``diffuse_scale`` and the step's
    :class:`StepInfo`; ``untrusted`` marks a finite part whose reduction exceeds what the
    Joseph form resolves (as in :func:`gaussian_update`) or non-finite results.
    """
    mean, p_inf, scale = belief["mean"], belief[DIFFUSE_COV], belief[DIFFUSE_SCALE]
    if diffuse_cross is None or diffuse_innovation is None:
        if obs_matrix is None:
            raise ValueError("diffuse_gaussian_update needs obs_matrix or (diffuse_cross, diffuse_innovation)")
        h = obs_matrix.expand(*mean.shape[:-1], *obs_matrix.shape[-2:])
        diffuse_cross = p_inf @ h.mT
        diffuse_innovation = symmetrize(h @ diffuse_cross)
    new_mean, p_fin, new_inf, loglik, nis, num_obs = diffuse_update(
        mean, p_inf, scale, innovation, deviations, diffuse_cross, diffuse_innovation, mask
    )
    if add is not None:
        new_mean = add(mean, new_mean - mean)
    limit = _trust_limits(mean.dtype)[2]
    var = torch.diagonal(p_fin, dim1=-2, dim2=-1)
    untrusted = ~torch.isfinite(loglik) | ~(var >= limit * torch.diagonal(belief["cov"], dim1=-2, dim2=-1)).all(-1)
    post = {"mean": new_mean, "cov": p_fin, DIFFUSE_COV: new_inf, DIFFUSE_SCALE: scale}
    return post, StepInfo(loglik, nis, num_obs, innovation, None, untrusted)


def square_root_deviations(cov: Tensor, obs_matrix: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(dx [B, n, n], dz [B, n, m], wc [n])``: the columns of a square root of ``cov`` and their
    images under ``obs_matrix`` with unit weights, the deviations form of ``(P, P H^T, H P H^T)``
    that :func:`diffuse_gaussian_update` takes from filters without sigma points."""
    dx = psd_sqrt(cov).factor.mT
    return dx, dx @ obs_matrix.mT, torch.ones(cov.shape[-1], dtype=cov.dtype, device=cov.device)


def _masked_noise(r: Tensor, mask: Tensor | None) -> Tensor:
    """``R`` with the rows and columns of unobserved components zeroed."""
    if mask is None:
        return r
    mo = mask.to(r.dtype)
    return r * (mo[..., :, None] * mo[..., None, :])


def _masked_system(h: Tensor, r: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """``H`` and ``R`` with the rows (and columns) of unobserved components zeroed."""
    if mask is None:
        return h, r
    return h * mask.to(h.dtype)[..., :, None], _masked_noise(r, mask)


def _sigma_joseph(gain: Tensor, dx: Tensor, dz: Tensor, wc: Tensor, r: Tensor | None, mask: Tensor | None) -> Tensor:
    """Joseph form of an unscented update from its sigma-point deviations (``gaussian_update``)."""
    if mask is not None:
        dz = dz * mask.to(dz.dtype)[..., None, :]
    dev = dx - dz @ gain.mT
    out = (dev * wc[:, None]).mT @ dev
    if r is not None:
        out = out + gain @ _masked_noise(r, mask) @ gain.mT
    return symmetrize(out)
