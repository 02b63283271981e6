"""Fixed-lag smoothing: ``x_{t|t+L}``, the estimate an online user gets ``L`` steps late."""

from __future__ import annotations

import torch
from torch import Tensor

from ..filters.base import Belief, FilterResult, RecursiveFilter
from ..models.base import Controls, DynamicsModel
from .base import Smoother, rts_step, smoother_gains
from .result import SmootherResult
from .rts import RTSSmoother, faded_prior_cov

__all__ = ["FixedLagSmoother", "fixed_lag_backward"]


def fixed_lag_backward(
    mean: Tensor, cov: Tensor, prior_mean: Tensor, prior_cov: Tensor, gains: Tensor, lag: int, space: DynamicsModel | None = None
) -> tuple[Tensor, Tensor]:
    """``x_{t|min(t+L, T-1)}`` and its covariance for every ``t`` (shapes as :func:`rts_backward`).

    Runs ``L`` backward steps, each vectorised over all target steps ``t`` (and the batch): the
    estimate of target ``t`` starts at the filter posterior of ``e_t = min(t + L, T - 1)`` and
    moves back one step per iteration until it reaches ``t``.
    """
    steps = mean.shape[1]
    idx = torch.arange(steps, device=mean.device)
    cur = (idx + lag).clamp(max=steps - 1)
    s_mean, s_cov = mean[:, cur], cov[:, cur]
    for _ in range(lag):
        active = cur > idx
        if not bool(active.any()):
            break
        src = (cur - 1).clamp(min=0)
        new_m, new_p = rts_step(mean[:, src], cov[:, src], gains[:, cur], prior_mean[:, cur], prior_cov[:, cur], s_mean, s_cov, space)
        s_mean = torch.where(active[:, None], new_m, s_mean)
        s_cov = torch.where(active[:, None, None], new_p, s_cov)
        cur = torch.where(active, cur - 1, cur)
    return s_mean, s_cov


class FixedLagSmoother(Smoother):
    """Fixed-lag RTS smoother with lag ``L``: ``x_{t|t+L}`` (``x_{t|T-1}`` for the last ``L`` steps).

    Batch use: ``FixedLagSmoother(filter, lag=L)(z, m0, P0, ...)`` returns a
    :class:`SmootherResult` whose ``mean[:, t]`` conditions on the measurements up to
    ``min(t + L, T - 1)``; ``L = 0`` is the filter, ``L >= T - 1`` the fixed-interval smoother.
    The backward steps are those of :class:`RTSSmoother` (same filter families, same
    cross-covariances), run ``L`` times vectorised over the window.

    Online use: ``state = smoother.init_state(m0, P0, batch_size)``, then per incoming step
    ``state, mean, cov = smoother.step(state, z_t, mask_t, u_t)``: ``(mean, cov)`` is
    ``x_{t-L|t}`` once ``t >= L`` (before that ``x_{0|t}``); ``state["belief"]`` is the filter's
    belief.  Each step costs one filter step and ``L`` backward steps over a buffer of the last
    ``L + 1`` posteriors.

    Args:
        filter: the forward filter (any filter :class:`RTSSmoother` accepts) or an
            :class:`RTSSmoother` to take the filter and ``time_chunk`` from.
        lag: ``L >= 0``.
        time_chunk: as :class:`~difffilter.smoothers.base.Smoother`.
    """

    def __init__(self, filter: RecursiveFilter | RTSSmoother, *, lag: int, time_chunk: int | None = None) -> None:  # noqa: A002
        rts = filter if isinstance(filter, RTSSmoother) else RTSSmoother(filter, time_chunk=time_chunk)
        if isinstance(lag, bool) or not isinstance(lag, int) or lag < 0:
            raise ValueError(f"lag must be an int >= 0, got {lag!r}")
        super().__init__(rts.filter, time_chunk=rts.time_chunk)
        self.lag = lag
        object.__setattr__(self, "_rts", rts)  # shares self.filter; kept out of the module tree

    def smooth(self, result: FilterResult, initial: Belief, controls: Controls = None) -> SmootherResult:
        """``x_{t|min(t+L, T-1)}`` over ``result`` of a window that started from ``initial``."""
        gains, prior_cov = self._rts.gains(result, initial, controls)
        mean, cov = fixed_lag_backward(result.mean, result.cov, result.prior_mean, prior_cov, gains, self.lag, self._rts.dynamics)
        return SmootherResult(mean=mean, cov=cov, filtered=result, lag=self.lag)

    # -- online use ------------------------------------------------------------------------------
    def init_state(self, initial_mean: Tensor, initial_cov: Tensor, batch_size: int | None = None) -> dict[str, Tensor]:
        """Online state before the first measurement (the filter's initial belief, empty buffers)."""
        belief = self.filter.initial_belief(initial_mean, initial_cov, batch_size)
        return {"belief": belief}  # type: ignore[dict-item]

    def step(self, state: dict, measurement: Tensor, mask: Tensor | None = None, controls: Controls = None) -> tuple[dict, Tensor, Tensor]:
        """One online step (arguments as :meth:`RecursiveFilter.step`); returns ``(state, mean, cov)``
        with ``(mean, cov)`` the smoothed estimate of the oldest buffered step (see the class doc)."""
        belief = state["belief"]
        cross = self._rts.cross_covariance(belief["mean"], belief["cov"], controls)
        post, prior, info = self.filter.step(belief, measurement, mask, controls)
        fields = {
            "means": post["mean"],
            "covs": post["cov"],
            "prior_means": prior["mean"],
            "prior_covs": self._effective_prior(prior, post, belief, controls),
            "gains": None,
        }
        fields["gains"] = smoother_gains(cross, fields["prior_covs"])
        new_state: dict = {"belief": post}
        for k, v in fields.items():
            buf = torch.cat([state[k], v[:, None]], 1) if k in state else v[:, None]
            new_state[k] = buf[:, -(self.lag + 1) :]
        s_mean, s_cov = new_state["means"][:, -1], new_state["covs"][:, -1]
        for i in range(new_state["means"].shape[1] - 1, 0, -1):
            s_mean, s_cov = rts_step(
                new_state["means"][:, i - 1], new_state["covs"][:, i - 1], new_state["gains"][:, i],
                new_state["prior_means"][:, i], new_state["prior_covs"][:, i], s_mean, s_cov, self._rts.dynamics,
            )  # fmt: skip
        return new_state, s_mean, s_cov

    def _effective_prior(self, prior: Belief, post: Belief, previous: Belief, controls: Controls) -> Tensor:
        if "fading_factor" not in post:
            return prior["cov"]
        q = self._rts.process_noise(previous["mean"], controls)
        return faded_prior_cov(prior["cov"], q, post["fading_factor"])
