"""Sage–Husa adaptive filter: noise covariances estimated by a fading-memory average."""

from __future__ import annotations

import torch
from torch import Tensor

from ...linalg import symmetrize
from ...models.base import Controls
from ...params import Bounded, register_constrained
from ..base import Belief, RecursiveFilter, StepInfo
from .base import AdaptiveNoiseFilter, blockdiag_sample, is_positive_definite

__all__ = ["SageHusa"]


class SageHusa(AdaptiveNoiseFilter):
    """Sage–Husa adaptive filter around a KF, EKF or UKF (forgetting factor ``b``).

    With ``k`` the number of steps observed so far (this one included, ``k >= 1``) and the
    weight ``d_k = (1 - b) / (1 - b^{k+1})`` (the model's ``R``, ``Q`` count as the sample
    before the first, so ``d_1 = 1 / (1 + b)``), at every step with an observation:

    1. ``e = z - z^`` at the prior ``N(x-, P-)``, ``spread = H P- H^T`` (its unscented
       analogue around a UKF);
    2. ``R_k = (1 - d_k) R_{k-1} + d_k (e e^T - spread)``;
    3. the inner filter's update with ``R_k``: ``x+``, ``P+``, ``dx = x+ - x- = K e``;
    4. (``adapt_q``) ``Q_k = (1 - d_k) Q_{k-1} + d_k (dx dx^T + P+ - F P+_{k-1} F^T)``, where
       ``F P+_{k-1} F^T = P- - Q_{k-1}`` is the propagated spread (unscented around a UKF);
       ``Q_k`` enters the next prediction ``P- = F P F^T + Q_k``.

    Safeguard (the subtractions can make an estimate indefinite): a candidate whose Cholesky
    factor fails after removing ``pd_floor * mean(diag)`` from its diagonal is replaced by the
    *biased* form that drops the subtracted term, ``(1 - d_k) R_{k-1} + d_k e e^T`` (resp.
    ``(1 - d_k) Q_{k-1} + d_k dx dx^T``), which is positive definite because ``d_k < 1``.  The
    choice is made per trajectory and step and is not differentiated (the branch taken is).

    Partial masks: the sample is ``e e^T - spread`` on the observed block, the current ``R``
    on the unobserved block and zero between them (:func:`blockdiag_sample`), so an unobserved
    component keeps its variance; ``k`` counts steps with any observation.  A fully missing
    step leaves ``R``, ``Q`` and ``k`` unchanged.

    Args:
        inner: the Gaussian filter (``KalmanFilter``, ``EKF``, ``UKF``, ``SimplifiedUKF``).
        b: forgetting factor in ``(0, 1)`` (learnable, ``Bounded(0, 1)``): ``1 - b`` is about
            the weight of the newest sample once ``k`` is large.
        adapt_r, adapt_q: which covariances to estimate (``adapt_r=False``: the model's ``R``).
        pd_floor: relative diagonal margin of the safeguard's definiteness test.

    Learnable: ``b`` and the inner model's parameters (its ``R``, ``Q`` are the starting
    estimates).  ``result.noise_R [B, T, m, m]`` (and ``noise_Q``) are the estimates after each step.
    """

    def __init__(
        self, inner: RecursiveFilter, *, b: float = 0.97, adapt_r: bool = True, adapt_q: bool = False, pd_floor: float = 1e-9
    ) -> None:
        super().__init__(inner, adapt_q=adapt_q)
        if not 0.0 < float(b) < 1.0:
            raise ValueError(f"b (the forgetting factor) must lie in (0, 1), got {b}")
        if not pd_floor >= 0.0:
            raise ValueError(f"pd_floor must be >= 0, got {pd_floor}")
        dtype = self._param_dtype() or torch.get_default_dtype()
        register_constrained(self, "b", torch.tensor(float(b), dtype=dtype), Bounded(0.0, 1.0))
        self.adapt_r = bool(adapt_r)
        self.pd_floor = float(pd_floor)

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        return {"mean": mean, "cov": cov, "noise_count": mean.new_zeros(mean.shape[:-1])}

    def weight(self, count: Tensor) -> Tensor:
        """``d_k [B]`` for ``k = count``."""
        b = self.b
        return (1.0 - b) / (1.0 - b ** (count + 1.0))

    def safeguarded(self, previous: Tensor, d: Tensor, sample: Tensor, biased: Tensor) -> Tensor:
        """``(1 - d) previous + d sample`` where positive definite, else with ``biased``."""
        w = d[..., None, None]
        cand = symmetrize((1.0 - w) * previous + w * sample)
        fallback = symmetrize((1.0 - w) * previous + w * biased)
        ok = is_positive_definite(cand, self.pd_floor)
        return torch.where(ok[..., None, None], cand, fallback)

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        mean, cov = belief["mean"], belief["cov"]
        obs = self.observed(z, mask)
        any_obs = obs.any(-1)
        mo = self.measurement_moments(mean, cov, u)
        r_prev = self.current_r(belief, u)
        e = torch.where(obs, self.model.measurement.residual(z, mo.zhat), torch.zeros_like(z))
        info = self.predictive_info(e, mo.spread + r_prev, mask)
        count = belief["noise_count"] + any_obs.to(mean.dtype)
        d = torch.where(any_obs, self.weight(count), torch.zeros_like(count))
        r_new = r_prev
        if self.adapt_r:
            outer = e[..., :, None] * e[..., None, :]
            sample = blockdiag_sample(outer - mo.spread, r_prev, obs)
            biased = blockdiag_sample(outer, r_prev, obs)
            r_new = self.keep_where(self.safeguarded(r_prev, d, sample, biased), r_prev, any_obs)
        new_mean, new_cov, upd = self.update_with(mean, cov, z, mask, r_new, mo)
        noise = {"noise_R": r_new, "noise_count": count}
        if self.adapt_q:
            q_prev = belief["noise_Q"]
            dx = self.state_difference(new_mean, mean)
            gain_part = dx[..., :, None] * dx[..., None, :]
            q_new = self.safeguarded(q_prev, d, gain_part + new_cov - belief["noise_spread"], gain_part)
            noise["noise_Q"] = self.keep_where(q_new, q_prev, any_obs)
        info.untrusted, info.rounding = upd.untrusted, upd.rounding
        info.jitter = upd.jitter if info.jitter is None else torch.maximum(upd.jitter, info.jitter)
        return self.finish(belief, new_mean, new_cov, noise), info
