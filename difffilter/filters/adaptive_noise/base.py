"""What every adaptive noise-estimating filter shares: the wrapped Gaussian filter, its
measurement moments, the update with an estimated ``R`` and the one-step predictive density.

An :class:`AdaptiveNoiseFilter` wraps one of the library's Gaussian filters (``KalmanFilter``,
``EKF``, ``UKF``, ``SimplifiedUKF``; additive noise) and replaces the model's noise covariances
by estimates carried in the belief (``noise_R [B, m, m]``, ``noise_Q [B, n, n]``).  The inner
filter supplies the prediction and the measurement moments at a Gaussian ``N(x, P)``:

* KF/EKF: ``z^ = h(x)``, ``P_xz = P H^T``, ``spread = H P H^T`` (``H`` the Jacobian at ``x``);
* UKF: the inner filter's sigma points of ``N(x, P)``: ``z^ = sum wm h(chi)``, ``P_xz``,
  ``spread = sum wc dz dz^T``;

so that the subclasses write each method's equations once for every inner filter.  The update
itself is :func:`~difffilter.filters.update.gaussian_update` with ``S = spread + R_hat`` (the
inner filter's Joseph forms included).

Conventions shared by the subclasses:

* the statistics start from the model's ``R`` (and ``Q``) at the first step, so an adaptive
  filter with frozen statistics *is* its inner filter;
* ``log_likelihood`` and ``nis`` are the one-step predictive density of ``z_k`` under the noise
  estimate held *before* ``z_k`` (``S = spread + R_{k-1}``), a proper score of the data: the
  density under the estimate adapted to ``z_k`` itself would reward fitting each innovation,
  and maximising it drives the forgetting towards zero;
* a fully missing step is predict-only and leaves every noise statistic unchanged; on a partial
  mask the statistics use the observed components only (each subclass says how);
* the filter always runs in plain covariance form (``diffuse_prior = False``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...linalg import gaussian_log_density, safe_cholesky, symmetrize
from ...models.base import Controls
from .._common import StepInfo, expand_controls, mask_measurement_system
from ..base import Belief, RecursiveFilter, gaussian_update
from ..ekf import EKF
from ..kalman import KalmanFilter
from ..ukf import UKF, SimplifiedUKF, deviations, state_add, weighted_mean
from ..update import JosephForm

__all__ = ["AdaptiveNoiseFilter", "Moments", "blockdiag_sample", "is_positive_definite"]

_INNER_TYPES = (KalmanFilter, EKF, UKF, SimplifiedUKF)


@dataclass
class Moments:
    """Measurement moments at ``N(x, P)``: ``zhat [B, m]``, ``pxz [B, n, m]``, ``spread [B, m, m]``
    (``Pzz`` without the noise), and the update's Joseph-form ingredients: ``h [B, m, n]`` for
    KF/EKF, or the sigma-point deviations ``dx [B, S, n]``, ``dz [B, S, m]``, weights ``wc [S]``."""

    zhat: Tensor
    pxz: Tensor
    spread: Tensor
    h: Tensor | None = None
    dx: Tensor | None = None
    dz: Tensor | None = None
    wc: Tensor | None = None


def is_positive_definite(a: Tensor, floor: float) -> Tensor:
    """``[B]`` bool: ``a - floor * mean(diag a) I`` has a Cholesky factor (no gradient: a test)."""
    with torch.no_grad():
        m = a.shape[-1]
        level = torch.diagonal(a, dim1=-2, dim2=-1).mean(-1).abs()
        eye = torch.eye(m, dtype=a.dtype, device=a.device)
        _, info = torch.linalg.cholesky_ex(symmetrize(a) - floor * level[..., None, None] * eye)
        return (info == 0) & torch.isfinite(a).all(-1).all(-1)


def blockdiag_sample(sample: Tensor, current: Tensor, observed: Tensor) -> Tensor:
    """The sample of a partially observed step: ``sample`` on the observed block, ``current`` on
    the unobserved block, zero between them.  ``observed [B, m]`` bool.

    A convex combination ``(1 - d) current + d blockdiag`` then keeps the unobserved variances,
    shrinks their correlations with the observed components by ``1 - d`` and stays positive
    definite whenever ``current`` is and the observed sample is semi-definite."""
    pair = observed[..., :, None] & observed[..., None, :]
    unobs = ~observed
    upair = unobs[..., :, None] & unobs[..., None, :]
    zero = torch.zeros((), dtype=sample.dtype, device=sample.device)
    return torch.where(pair, sample, torch.where(upair, current, zero))


class AdaptiveNoiseFilter(RecursiveFilter):
    """Base of the adaptive noise-estimating filters (see the module docstring).

    Args:
        inner: the Gaussian filter to wrap: ``KalmanFilter``, ``EKF``, ``UKF`` or
            ``SimplifiedUKF`` with additive noise (a UKF must redraw its update points,
            ``redraw_after_predict=True``, so that the update sees the estimated ``Q``).
        adapt_q: whether the subclass also estimates ``Q`` (carried as ``noise_Q``).

    Subclasses implement :meth:`update` (and, for ``Q``, may rely on :meth:`predict`, which
    replaces the model's ``Q`` by ``belief["noise_Q"]``).  ``result.noise_R [B, T, m, m]`` (and
    ``result.noise_Q [B, T, n, n]``) are the estimates after each step.
    """

    diffuse_prior = False

    def __init__(self, inner: RecursiveFilter, *, adapt_q: bool = False) -> None:
        if type(inner) not in _INNER_TYPES:
            names = ", ".join(t.__name__ for t in _INNER_TYPES)
            raise TypeError(f"inner must be one of {names} (a Gaussian filter to adapt), got {type(inner).__name__}")
        model = inner.model
        if not (model.dynamics.additive_noise and model.measurement.additive_noise):
            raise ValueError("inner's model declares non-additive noise: the adaptive filters estimate additive Q and R only")
        if isinstance(inner, UKF) and (inner.noise != "additive" or not inner.redraw_after_predict):
            raise ValueError(
                "inner UKF must use noise='additive' and redraw_after_predict=True (its update points must see the estimated Q)"
            )
        super().__init__(model)
        self.inner = inner
        self.adapt_q = bool(adapt_q)
        self.record_keys = ("noise_R", "noise_Q") if self.adapt_q else ("noise_R",)

    # -- the inner filter's pieces ------------------------------------------------------------
    @property
    def unscented(self) -> bool:
        return isinstance(self.inner, UKF)

    def model_r(self, mean: Tensor, u: Controls) -> Tensor:
        """The model's ``R [B, m, m]`` at ``mean`` (the statistics' starting value)."""
        r = self.model.measurement.measurement_noise(mean, u)
        return r.expand(*mean.shape[:-1], *r.shape[-2:])

    def model_q(self, mean: Tensor, u: Controls) -> Tensor:
        """The model's ``Q [B, n, n]`` at ``mean``."""
        q = self.model.dynamics.process_noise(mean, u)
        return q.expand(*mean.shape[:-1], *q.shape[-2:])

    def current_r(self, belief: Belief, u: Controls) -> Tensor:
        """The estimate of ``R`` held before this step's measurement."""
        return belief["noise_R"] if "noise_R" in belief else self.model_r(belief["mean"], u)

    def measurement_moments(self, mean: Tensor, cov: Tensor, u: Controls) -> Moments:
        """:class:`Moments` of the measurement at ``N(mean, cov)`` by the inner filter's rule."""
        hm, dyn = self.model.measurement, self.model.dynamics
        if self.unscented:
            inner: UKF = self.inner  # type: ignore[assignment]
            wm, wc = inner._weights(mean.shape[-1], mean)
            chi = inner._points(mean, cov)
            zeta = hm(chi, expand_controls(u))
            zhat = weighted_mean(zeta, wm, hm)
            dz = hm.residual(zeta, zhat[..., None, :])
            dx = deviations(chi, mean, dyn)
            spread = symmetrize((dz * wc[:, None]).mT @ dz)
            return Moments(zhat, (dx * wc[:, None]).mT @ dz, spread, dx=dx, dz=dz, wc=wc)
        h = self.inner.measurement_jacobian(mean, u)
        h = h.expand(*mean.shape[:-1], *h.shape[-2:])
        pxz = cov @ h.mT
        return Moments(hm(mean, u), pxz, symmetrize(h @ pxz), h=h)

    def update_with(
        self, mean: Tensor, cov: Tensor, z: Tensor, mask: Tensor | None, r: Tensor, mo: Moments
    ) -> tuple[Tensor, Tensor, StepInfo]:
        """The inner filter's update of ``N(mean, cov)`` (moments ``mo``) with noise ``r``."""
        e = self.model.measurement.residual(z, mo.zhat)
        s = mo.spread + r
        add = state_add(self.model.dynamics)
        if self.unscented:
            joseph = JosephForm.sigma_points(mo.dx, mo.dz, mo.wc, r)
            return gaussian_update(mean, cov, e, s, mo.pxz, mask, joseph=joseph, add=add, prediction=mo.zhat)
        joseph = JosephForm.linear(mo.h, r, always=self.inner.joseph)
        return gaussian_update(mean, cov, e, s, mo.pxz, mask, joseph=joseph, add=add, prediction=mo.zhat)

    @staticmethod
    def predictive_info(innovation: Tensor, innovation_cov: Tensor, mask: Tensor | None) -> StepInfo:
        """Log-density ``log N(e; 0, S)`` of the observed components, NIS and their number."""
        e, s, _, nobs = mask_measurement_system(innovation, innovation_cov, innovation[..., None, :], mask)
        chol, jitter = safe_cholesky(s)
        loglik, maha = gaussian_log_density(e, chol, nobs)
        return StepInfo(loglik, maha, nobs, e, s, None, jitter)

    @staticmethod
    def observed(z: Tensor, mask: Tensor | None) -> Tensor:
        """``[B, m]`` bool: the observed components."""
        return torch.ones_like(z, dtype=torch.bool) if mask is None else mask

    def state_difference(self, x: Tensor, ref: Tensor) -> Tensor:
        """``x - ref`` (angular components wrapped)."""
        return deviations(x[..., None, :], ref, self.model.dynamics)[..., 0, :]

    # -- prediction with the estimated Q ------------------------------------------------------
    def predict(self, belief: Belief, u: Controls) -> Belief:
        """The inner prediction; with ``adapt_q`` the model's ``Q`` is replaced by the estimate
        (exact for additive noise: ``P- = spread_f + Q``), and the propagated spread
        ``spread_f [B, n, n]`` is kept for the update as ``belief["noise_spread"]``."""
        out = self.inner.predict(belief, u)
        if not self.adapt_q:
            return out
        q_model = self.model_q(belief["mean"], u)
        q_hat = belief["noise_Q"] if "noise_Q" in belief else q_model
        spread = out["cov"] - q_model
        out["cov"] = symmetrize(spread + q_hat)
        out["noise_Q"] = q_hat
        out["noise_spread"] = spread
        return out

    def finish(self, belief: Belief, mean: Tensor, cov: Tensor, noise: dict[str, Tensor]) -> Belief:
        """The posterior belief: predict-only entries dropped, statistics ``noise`` set."""
        out = {k: v for k, v in belief.items() if k != "noise_spread"}
        out.update(noise)
        out["mean"], out["cov"] = mean, cov
        return out

    @staticmethod
    def keep_where(update: Tensor, previous: Tensor, any_obs: Tensor) -> Tensor:
        """``update`` on trajectories with an observation at this step, else ``previous``."""
        cond = any_obs.reshape(any_obs.shape + (1,) * (update.ndim - any_obs.ndim))
        return torch.where(cond, update, previous)
