"""Covariance matching: innovation-based adaptive estimation (Mehra 1972; Mohamed & Schwarz 1999)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...linalg import safe_cholesky, symmetrize
from ...models.base import Controls
from ...params import Positive, register_constrained
from .._common import mask_measurement_system
from ..base import Belief, RecursiveFilter, StepInfo
from .base import AdaptiveNoiseFilter, blockdiag_sample, is_positive_definite

__all__ = ["CovarianceMatching"]


class CovarianceMatching(AdaptiveNoiseFilter):
    """Innovation-based adaptive estimation by covariance matching, around a KF, EKF or UKF.

    The innovation covariance is estimated over an exponential window of effective length
    ``W`` (``lambda = 1 - 1/W``, weight sum ``w``, both zero before the first observation):

    * ``w_k = lambda w_{k-1} + 1``, ``C_k = (lambda w_{k-1} C_{k-1} + e e^T) / w_k`` with
      ``e = z - z^`` at the prior;
    * ``R_k = C_k - spread`` with ``spread = H P- H^T`` (the unscented spread of the prior
      around a UKF), the measurement-noise part of ``C = H P- H^T + R``;
    * the inner filter's update with ``R_k``; with ``adapt_q``, ``Q_k = K C_k K^T``
      (Mohamed & Schwarz's approximation of the windowed ``dx dx^T``, ``K`` this step's gain)
      enters the next prediction.

    Safeguard: an ``R_k`` whose Cholesky factor fails after removing ``pd_floor * mean(diag)``
    from its diagonal is not accepted and the previous estimate is kept (per trajectory and
    step; the first steps, while ``C_k`` has rank below ``m``, keep the model's ``R``).  ``Q_k``
    is semi-definite by construction (rank ``<= m``): with ``adapt_q`` the prediction relies on
    ``F P F^T`` for the directions it does not excite, the known weakness of this estimator.

    Partial masks: the sample is ``e e^T`` on the observed block, ``C_{k-1}`` on the unobserved
    block, zero between them (:func:`blockdiag_sample`); the candidate ``R_k`` keeps the
    previous entries outside the observed block.  A fully missing step changes nothing.

    Args:
        inner: the Gaussian filter (``KalmanFilter``, ``EKF``, ``UKF``, ``SimplifiedUKF``).
        window: effective window length ``W > 1`` in steps (learnable, ``Positive(floor=1)``).
        adapt_r, adapt_q: which covariances to estimate.
        pd_floor: relative diagonal margin of the safeguard's definiteness test.

    Learnable: ``window`` and the inner model's parameters.  ``result.noise_R``
    (``result.noise_Q``) per step; ``result.innovation_cov_estimate`` is ``C_k``.
    """

    def __init__(
        self,
        inner: RecursiveFilter,
        *,
        window: float = 30.0,
        adapt_r: bool = True,
        adapt_q: bool = False,
        pd_floor: float = 1e-9,
    ) -> None:
        super().__init__(inner, adapt_q=adapt_q)
        if not float(window) > 1.0:
            raise ValueError(f"window (the effective number of innovations averaged) must be > 1, got {window}")
        if not pd_floor >= 0.0:
            raise ValueError(f"pd_floor must be >= 0, got {pd_floor}")
        dtype = self._param_dtype() or torch.get_default_dtype()
        register_constrained(self, "window", torch.tensor(float(window), dtype=dtype), Positive(floor=1.0))
        self.adapt_r = bool(adapt_r)
        self.pd_floor = float(pd_floor)
        self.record_keys = (*self.record_keys, "innovation_cov_estimate")

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        m = self.measurement_dim
        batch = mean.shape[:-1]
        return {
            "mean": mean,
            "cov": cov,
            "innovation_cov_estimate": mean.new_zeros(*batch, m, m),
            "noise_weight": mean.new_zeros(batch),
        }

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        obs = self.observed(z, mask)
        any_obs = obs.any(-1)
        mo = self.measurement_moments(mean, cov, u)
        r_prev = self.current_r(belief, u)
        e = torch.where(obs, self.model.measurement.residual(z, mo.zhat), torch.zeros_like(z))
        info = self.predictive_info(e, mo.spread + r_prev, mask)
        lam = 1.0 - 1.0 / self.window
        w_prev, c_prev = belief["noise_weight"], belief["innovation_cov_estimate"]
        kept = lam * w_prev
        w_new = torch.where(any_obs, kept + 1.0, w_prev)
        sample = blockdiag_sample(e[..., :, None] * e[..., None, :], c_prev, obs)
        c_new = (kept[..., None, None] * c_prev + sample) / (kept + 1.0)[..., None, None]
        c_new = self.keep_where(symmetrize(c_new), c_prev, any_obs)
        r_new = r_prev
        if self.adapt_r:
            pair = obs[..., :, None] & obs[..., None, :]
            cand = symmetrize(torch.where(pair, c_new - mo.spread, r_prev))
            ok = is_positive_definite(cand, self.pd_floor) & any_obs
            r_new = torch.where(ok[..., None, None], cand, r_prev)
        new_mean, new_cov, upd = self.update_with(mean, cov, z, mask, r_new, mo)
        noise = {"noise_R": r_new, "noise_weight": w_new, "innovation_cov_estimate": c_new}
        if self.adapt_q:
            gain = self.gain(mo.spread + r_new, mo.pxz, e, mask)
            q_new = symmetrize(gain @ c_new @ gain.mT)
            noise["noise_Q"] = self.keep_where(q_new, belief["noise_Q"], any_obs)
        info.untrusted, info.rounding, info.jitter = upd.untrusted, upd.rounding, torch.maximum(upd.jitter, info.jitter)
        return self.finish(belief, new_mean, new_cov, noise), info

    @staticmethod
    def gain(innovation_cov: Tensor, cross_cov: Tensor, innovation: Tensor, mask: Tensor | None) -> Tensor:
        """``K = P_xz S^{-1} [B, n, m]`` on the observed components (zero columns elsewhere)."""
        _, s, pxz, _ = mask_measurement_system(innovation, innovation_cov, cross_cov, mask)
        chol, _ = safe_cholesky(s)
        return torch.cholesky_solve(pxz.mT, chol).mT
