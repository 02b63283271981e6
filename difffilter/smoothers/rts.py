"""Fixed-interval Rauch-Tung-Striebel smoothers: extended (KF/EKF) and unscented (UKF family)."""

from __future__ import annotations

from torch import Tensor

from ..filters.adaptive import RCUKF
from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..filters.ukf import UKF
from ..models.base import Controls, DynamicsModel
from .base import Smoother, previous_posteriors, rts_backward, smoother_gains
from .result import SmootherResult
from .transition import check_smoothable, needs_points, predicting_filter, transition_cross_covariance

__all__ = ["RTSSmoother", "UnscentedRTSSmoother", "faded_prior_cov"]


def faded_prior_cov(prior_cov: Tensor, process_noise: Tensor, eta: Tensor) -> Tensor:
    """RCUKF's faded prior ``P- + (eta - 1) S`` (per state: ``(sqrt(eta_i eta_j) - 1) S_ij``) with
    ``S = P- - Q`` the propagated spread; ``eta [...]`` or ``[..., n]``."""
    spread = prior_cov - process_noise
    if eta.ndim == prior_cov.ndim - 2:
        return prior_cov + (eta - 1.0)[..., None, None] * spread
    root = eta.sqrt()
    return prior_cov + (root[..., :, None] * root[..., None, :] - 1.0) * spread


class RTSSmoother(Smoother):
    """Rauch-Tung-Striebel fixed-interval smoother over a window (batched, differentiable).

    ``x_{t|T}``, ``P_{t|T}`` for every step from the forward filter's posteriors and priors and the
    backward recursion of :mod:`difffilter.smoothers.base`; the prediction's cross-covariance is
    the filter's own (:func:`~difffilter.smoothers.transition.transition_cross_covariance`):

    * :class:`~difffilter.filters.KalmanFilter`: the RTS smoother, exact on linear-Gaussian models
      (equal to the conditional of the dense joint Gaussian of the window);
    * :class:`~difffilter.filters.EKF` / :class:`~difffilter.filters.IteratedEKF`: the extended RTS
      smoother (``F`` at the filtered mean);
    * :class:`~difffilter.filters.UKF`, ``SquareRootUKF``: Sarkka's unscented RTS smoother (same
      sigma points and noise handling as the filter's prediction; see also
      :class:`UnscentedRTSSmoother`); ``SimplifiedUKF``: the RTS step of its Kalman prediction;
    * :class:`~difffilter.filters.RCUKF`: the fading factor acts as extra process noise
      ``(eta - 1) S`` at its step (``S`` the propagated spread), so the gains use the faded prior.

    Example::

        smoother = RTSSmoother(KalmanFilter(model))
        out = smoother(z, m0, P0, mask=mask)      # out.mean [B, T, n]: x_{t|T}; out.filtered: the filter's result
        next_out = smoother(z_next, belief=out.final_belief)   # the next window, from the carried belief

    Learnable: the filter's parameters (gradients flow through both passes).
    """

    def __init__(self, filter: RecursiveFilter, *, time_chunk: int | None = None) -> None:  # noqa: A002
        check_smoothable(filter)
        super().__init__(filter, time_chunk=time_chunk)

    def cross_covariance(self, mean: Tensor, cov: Tensor, u: Controls) -> Tensor:
        """``Cov(x_{t-1}, x_t)`` of the filter's prediction from ``N(mean [N, n], cov)`` with step inputs ``u``."""
        return transition_cross_covariance(self.filter, mean, cov, u)

    def effective_prior_cov(self, result: FilterResult, prev_mean: Tensor, controls: Controls) -> Tensor:
        """The prior covariance ``[B, T, n, n]`` the filter's update used (the recorded prior, or
        RCUKF's faded one)."""
        if not isinstance(predicting_filter(self.filter), RCUKF):
            return result.prior_cov
        q = self.per_step(lambda m, p, u: self.process_noise(m, u), prev_mean, result.prior_cov, controls)
        return faded_prior_cov(result.prior_cov, q, result.extras["fading_factor"])

    @property
    def dynamics(self) -> DynamicsModel:
        """The dynamics of the filter's prediction (its angular states are wrapped in the backward step)."""
        return predicting_filter(self.filter).model.dynamics

    def process_noise(self, mean: Tensor, u: Controls) -> Tensor:
        """The filter model's ``Q`` at the posterior ``mean [N, n]``, expanded to ``[N, n, n]``."""
        n = mean.shape[-1]
        return self.dynamics.process_noise(mean, u).expand(mean.shape[0], n, n)

    def gains(self, result: FilterResult, initial: Belief, controls: Controls = None) -> tuple[Tensor, Tensor]:
        """Smoother gains ``G_t [B, T, n, n]`` and the prior covariances they use."""
        prev_mean, prev_cov = previous_posteriors(result, initial)
        cross = self.per_step(self.cross_covariance, prev_mean, prev_cov, controls, whole=not needs_points(self.filter, controls))
        prior_cov = self.effective_prior_cov(result, prev_mean, controls)
        return smoother_gains(cross, prior_cov), prior_cov

    def smooth(self, result: FilterResult, initial: Belief, controls: Controls = None) -> SmootherResult:
        """Backward pass over ``result`` of a window that started from the belief ``initial``."""
        gains, prior_cov = self.gains(result, initial, controls)
        mean, cov, cross, m0, p0 = rts_backward(
            result.mean, result.cov, result.prior_mean, prior_cov, gains, initial["mean"], initial["cov"], self.dynamics
        )
        return SmootherResult(mean=mean, cov=cov, filtered=result, cross_cov=cross, initial_mean=m0, initial_cov=p0)


class UnscentedRTSSmoother(RTSSmoother):
    """Sarkka's unscented RTS smoother (URTS) for the UKF family.

    Backward step with the filter's sigma points of the posterior ``N(x_{t-1}, P_{t-1})``:
    ``C_t = sum_i wc_i (chi_i - x_{t-1})(f(chi_i, u_t) - x-_t)^T``, ``G_t = C_t (P-_t)^{-1}``, then the
    RTS recursion; with ``noise="augmented"`` the points are those of ``[x; w]`` (non-additive
    ``f(x, w, u)`` included).  For :class:`~difffilter.filters.SimplifiedUKF`, whose prediction is
    the Kalman one, the step is the RTS step with its ``F``.  On linear models it equals the RTS
    smoother (the unscented transform is exact there).  Learnable: the filter's parameters.
    """

    def __init__(self, filter: RecursiveFilter, *, time_chunk: int | None = None) -> None:  # noqa: A002
        if not isinstance(predicting_filter(filter), UKF):
            raise TypeError(f"UnscentedRTSSmoother needs a UKF-family filter, got {type(filter).__name__}; use RTSSmoother")
        super().__init__(filter, time_chunk=time_chunk)
