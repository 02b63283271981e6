"""The result of a smoother run: smoothed moments beside the filter's own result."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor
from torch.utils import _pytree

from ..filters.base import Belief, FilterResult

__all__ = ["SmootherResult"]


@dataclass
class SmootherResult:
    """Smoothed Gaussian moments of a window (batch-first), with the filter result they came from.

    Attributes:
        mean, cov: smoothed ``x_{t|T-1}`` and ``P_{t|T-1}`` at every step, ``[B, T, n]``,
            ``[B, T, n, n]`` (fixed-lag smoothers: ``x_{t|min(t+L, T-1)}``).
        cross_cov: lag-one smoothed cross-covariance ``cross_cov[:, t] = Cov(x_{t-1}, x_t | all
            measurements)`` ``[B, T, n, n]``, so ``cross_cov[:, k + 1] = P_{k,k+1|T}``; at ``t = 0``
            ``x_{-1}`` is the state before the first measurement (the initial belief's state).
            ``None`` for fixed-lag smoothing, whose estimates have different conditioning sets.
        initial_mean, initial_cov: smoothed state before the first measurement ``[B, n]``,
            ``[B, n, n]`` (the initial belief conditioned on the whole window); ``None`` for
            fixed-lag smoothing.
        filtered: the forward filter's :class:`~difffilter.filters.base.FilterResult`
            (posterior, prior, log-likelihood, final belief for carry-over).
        extras: smoother-specific outputs, also reachable as attributes (IMM smoother:
            ``mode_probs [B, T, M]``, ``mode_means``, ``mode_covs``).
        lag: the fixed lag ``L`` (``None`` for fixed-interval smoothing).

    The filter's per-step statistics (``log_likelihood``, ``nis``, ``num_observed``) and its
    ``final_belief`` are available under the same names, so losses and metrics written for a
    :class:`FilterResult` accept a :class:`SmootherResult` and then see the smoothed states.
    """

    mean: Tensor
    cov: Tensor
    filtered: FilterResult
    cross_cov: Tensor | None = None
    initial_mean: Tensor | None = None
    initial_cov: Tensor | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)
    lag: int | None = None

    def __getattr__(self, name: str) -> Tensor:
        extras = self.__dict__.get("extras", {})
        if name in extras:
            return extras[name]
        raise AttributeError(name)

    @property
    def prior_mean(self) -> Tensor:
        """The filter's predicted means ``[B, T, n]``."""
        return self.filtered.prior_mean

    @property
    def prior_cov(self) -> Tensor:
        """The filter's predicted covariances ``[B, T, n, n]``."""
        return self.filtered.prior_cov

    @property
    def log_likelihood(self) -> Tensor:
        """The filter's innovation log-likelihood ``[B, T]``."""
        return self.filtered.log_likelihood

    @property
    def nis(self) -> Tensor:
        return self.filtered.nis

    @property
    def num_observed(self) -> Tensor:
        return self.filtered.num_observed

    @property
    def final_belief(self) -> Belief:
        """The filter's belief after the last step: continue the next window from it."""
        return self.filtered.final_belief

    @property
    def total_log_likelihood(self) -> Tensor:
        return self.filtered.total_log_likelihood


_FIELDS = ("mean", "cov", "filtered", "cross_cov", "initial_mean", "initial_cov", "extras")


def _flatten(r: SmootherResult) -> tuple[list, tuple]:
    present = tuple(k for k in _FIELDS if getattr(r, k) is not None)
    return [getattr(r, k) for k in present], (present, r.lag)


def _unflatten(children: list, context: tuple) -> SmootherResult:
    present, lag = context
    return SmootherResult(**dict(zip(present, children, strict=True)), lag=lag)


# A pytree node (absent fields and the lag are static context), so that torch.func.vmap can
# return a SmootherResult.
# torch types unflatten's first argument as Iterable; _unflatten takes the list torch passes.
_pytree.register_pytree_node(SmootherResult, _flatten, _unflatten, serialized_type_name="difffilter.SmootherResult")  # type: ignore[arg-type]
