"""Variational-Bayes adaptive Kalman filters: for ``R`` (Särkkä & Nummenmaa 2009) and for the
predicted covariance and ``R`` (Huang et al. 2018)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...linalg import symmetrize
from ...models.base import Controls
from ...params import Bounded, Positive, register_constrained
from ..base import Belief, RecursiveFilter, StepInfo
from .base import AdaptiveNoiseFilter, blockdiag_sample

__all__ = ["VBAdaptiveQR", "VBAdaptiveR"]


def _check_iterations(iterations: int) -> int:
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    return iterations


class VBAdaptiveR(AdaptiveNoiseFilter):
    """Variational-Bayes adaptive filter for a diagonal ``R`` (Särkkä & Nummenmaa 2009).

    Each variance ``R_ii`` has an inverse-Gamma posterior ``IG(alpha_i, beta_i)``; the state a
    Gaussian.  At a step that observes component ``i``:

    * dynamics of the noise: ``alpha_i- = rho alpha_i``, ``beta_i- = rho beta_i``;
    * ``alpha_i = alpha_i- + 1/2``, ``beta_i = beta_i-``, then ``iterations`` fixed-point
      rounds: ``R = diag(beta / alpha)``; the inner filter's update of the prior ``N(x-, P-)``
      with ``R`` gives ``N(x, P)``; ``beta_i = beta_i- + ((z - h(x))_i^2 + spread_ii) / 2``
      with ``spread = H P H^T`` at ``x`` (the unscented spread of ``N(x, P)`` around a UKF).

    The estimate after the step is ``R = diag(beta / alpha)`` (``result.noise_R``).  An
    unobserved component keeps ``alpha_i``, ``beta_i`` (so a missing step changes nothing);
    the forgetting acts at observed steps only, which equals the paper's recursion on fully
    observed data.  The prior: ``alpha_i = prior_shape``, ``beta_i = prior_shape R_ii`` with
    the model's ``R`` at the first step (its off-diagonal entries are not used).

    Args:
        inner: the Gaussian filter (``KalmanFilter``, ``EKF``, ``UKF``, ``SimplifiedUKF``).
        rho: forgetting in ``(0, 1)`` (learnable, ``Bounded(0, 1)``); the shape settles at
            ``1 / (2 (1 - rho))``, the number of squared residuals the estimate averages.
        iterations: fixed-point rounds per step (>= 1).
        prior_shape: ``alpha`` of the starting inverse-Gamma (> 0; fixed): the weight of the
            model's ``R`` in squared residuals times two.

    Learnable: ``rho`` and the inner model's parameters.
    """

    def __init__(self, inner: RecursiveFilter, *, rho: float = 0.98, iterations: int = 3, prior_shape: float = 1.0) -> None:
        super().__init__(inner)
        if not 0.0 < float(rho) < 1.0:
            raise ValueError(f"rho (the forgetting factor) must lie in (0, 1), got {rho}")
        if not float(prior_shape) > 0.0:
            raise ValueError(f"prior_shape must be > 0, got {prior_shape}")
        dtype = self._param_dtype() or torch.get_default_dtype()
        register_constrained(self, "rho", torch.tensor(float(rho), dtype=dtype), Bounded(0.0, 1.0))
        self.iterations = _check_iterations(iterations)
        self.prior_shape = float(prior_shape)

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        m = self.measurement_dim
        return {"mean": mean, "cov": cov, "noise_alpha": mean.new_full((*mean.shape[:-1], m), self.prior_shape)}

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        hm = self.model.measurement
        obs = self.observed(z, mask)
        mo = self.measurement_moments(mean, cov, u)
        # the estimate is diagonal from the start: the model's off-diagonal entries are not used
        r_prev = torch.diag_embed(torch.diagonal(self.current_r(belief, u), dim1=-2, dim2=-1))
        zero = torch.zeros_like(z)
        info = self.predictive_info(torch.where(obs, hm.residual(z, mo.zhat), zero), mo.spread + r_prev, mask)
        alpha_prev = belief["noise_alpha"]
        beta_prev = alpha_prev * torch.diagonal(r_prev, dim1=-2, dim2=-1)
        rho = self.rho
        alpha = torch.where(obs, rho * alpha_prev + 0.5, alpha_prev)
        beta_pred = torch.where(obs, rho * beta_prev, beta_prev)
        beta = beta_pred
        upd = None
        for _ in range(self.iterations):
            r = torch.diag_embed(beta / alpha)
            new_mean, new_cov, upd = self.update_with(mean, cov, z, mask, r, mo)
            post = self.measurement_moments(new_mean, new_cov, u)
            res = torch.where(obs, hm.residual(z, post.zhat), zero)
            beta = torch.where(obs, beta_pred + 0.5 * (res * res + torch.diagonal(post.spread, dim1=-2, dim2=-1)), beta_prev)
        r_new = torch.diag_embed(beta / alpha)
        info.untrusted, info.rounding, info.jitter = upd.untrusted, upd.rounding, torch.maximum(upd.jitter, info.jitter)
        return self.finish(belief, new_mean, new_cov, {"noise_R": r_new, "noise_alpha": alpha}), info


class VBAdaptiveQR(AdaptiveNoiseFilter):
    """Variational-Bayes adaptive filter for the predicted covariance and a full ``R`` (Huang,
    Zhang, Wu, Chambers 2018).

    The predicted covariance ``P_k|k-1`` and ``R_k`` get inverse-Wishart posteriors.  With the
    nominal prediction ``x-``, ``P~ = F P F^T + Q`` (the model's ``Q``), the carried estimate
    ``R_{k-1}`` and its degrees of freedom ``nu = u - m - 1``, at a step with an observation:

    * ``nu- = rho nu`` (so ``U- = rho U = nu- R_{k-1}``); the prior of ``P_k|k-1`` is
      ``IW(n + tau + 1, tau P~)``;
    * from ``x^0 = x-``, ``P^0 = P~``, ``iterations`` rounds ``i``:
      ``A = P^i + (x^i - x-)(x^i - x-)^T``, ``P^ = (A + tau P~) / (tau + 1)``;
      ``B = (z - h(x^i))(z - h(x^i))^T + spread(x^i, P^i)``,
      ``R^ = (nu- R_{k-1} + B) / (nu- + 1)``; the inner filter's update of ``N(x-, P^)`` with
      ``R^`` gives ``x^{i+1}``, ``P^{i+1}``;
    * ``nu = nu- + 1``, ``R_k = R^`` of the last round.

    ``P^`` and ``R^`` are convex combinations of a positive-definite and a semi-definite
    matrix, so they stay positive definite without a safeguard.  ``result.noise_R`` holds
    ``R_k``, ``result.noise_Q`` the implied ``Q^ = Q + P^ - P~`` (the model's ``Q`` at a
    missing step) and ``result.noise_prior_cov`` the estimate ``P^`` of ``P_k|k-1``.

    Partial masks: ``B`` on the observed block, ``R_{k-1}`` on the unobserved block, zero
    between them (:func:`blockdiag_sample`); a fully missing step changes neither ``R`` nor
    ``nu`` and is predict-only.  The forgetting acts at observed steps only (the paper's
    recursion on fully observed data).  Nonlinear models: ``h`` and ``spread`` by the inner
    filter's rule (Jacobian at ``x^i`` or sigma points of ``N(x^i, P^i)``).

    Args:
        inner: the Gaussian filter (``KalmanFilter``, ``EKF``, ``UKF``, ``SimplifiedUKF``).
        rho: forgetting of the ``R`` statistics in ``(0, 1)`` (learnable, ``Bounded(0, 1)``).
        tau: prior confidence in the nominal ``P~`` (> 0, learnable, ``Positive``): large
            ``tau`` keeps ``P^ = P~``.
        iterations: variational rounds per step (>= 1; the paper uses 10).
        prior_dof: ``nu = u_0 - m - 1`` of the starting inverse-Wishart of ``R`` (> 0, fixed;
            its scale is ``nu R`` with the model's ``R``).

    Learnable: ``rho``, ``tau`` and the inner model's parameters (its ``Q`` is the nominal one).
    """

    def __init__(
        self, inner: RecursiveFilter, *, rho: float = 0.98, tau: float = 3.0, iterations: int = 10, prior_dof: float = 1.0
    ) -> None:
        super().__init__(inner)
        if not 0.0 < float(rho) < 1.0:
            raise ValueError(f"rho (the forgetting factor) must lie in (0, 1), got {rho}")
        if not float(tau) > 0.0:
            raise ValueError(f"tau must be > 0, got {tau}")
        if not float(prior_dof) > 0.0:
            raise ValueError(f"prior_dof must be > 0, got {prior_dof}")
        dtype = self._param_dtype() or torch.get_default_dtype()
        register_constrained(self, "rho", torch.tensor(float(rho), dtype=dtype), Bounded(0.0, 1.0))
        register_constrained(self, "tau", torch.tensor(float(tau), dtype=dtype), Positive())
        self.iterations = _check_iterations(iterations)
        self.prior_dof = float(prior_dof)
        self.record_keys = ("noise_R", "noise_Q", "noise_prior_cov")

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        return {"mean": mean, "cov": cov, "noise_dof": mean.new_full(mean.shape[:-1], self.prior_dof)}

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        x_pred, p_pred = belief["mean"], belief["cov"]
        hm = self.model.measurement
        obs = self.observed(z, mask)
        any_obs = obs.any(-1)
        mo = self.measurement_moments(x_pred, p_pred, u)
        r_prev = self.current_r(belief, u)
        zero = torch.zeros_like(z)
        info = self.predictive_info(torch.where(obs, hm.residual(z, mo.zhat), zero), mo.spread + r_prev, mask)
        nu_prev = belief["noise_dof"]
        nu_pred = (self.rho * nu_prev)[..., None, None]
        tau = self.tau
        x, p, mo_i = x_pred, p_pred, mo
        for _ in range(self.iterations):
            dx = self.state_difference(x, x_pred)
            p_hat = symmetrize((p + dx[..., :, None] * dx[..., None, :] + tau * p_pred) / (tau + 1.0))
            res = torch.where(obs, hm.residual(z, mo_i.zhat), zero)
            sample = blockdiag_sample(res[..., :, None] * res[..., None, :] + mo_i.spread, r_prev, obs)
            r_hat = symmetrize((nu_pred * r_prev + sample) / (nu_pred + 1.0))
            x, p, upd = self.update_with(x_pred, p_hat, z, mask, r_hat, self.measurement_moments(x_pred, p_hat, u))
            mo_i = self.measurement_moments(x, p, u)
        x = self.keep_where(x, x_pred, any_obs)
        p = self.keep_where(p, p_pred, any_obs)
        p_hat = self.keep_where(p_hat, p_pred, any_obs)
        noise = {
            "noise_R": self.keep_where(r_hat, r_prev, any_obs),
            "noise_dof": torch.where(any_obs, nu_pred[..., 0, 0] + 1.0, nu_prev),
            "noise_Q": self.model_q(x_pred, u) + (p_hat - p_pred),
            "noise_prior_cov": p_hat,
        }
        info.untrusted, info.rounding, info.jitter = upd.untrusted, upd.rounding, torch.maximum(upd.jitter, info.jitter)
        return self.finish(belief, x, p, noise), info
