"""Training losses on filter outputs, and parameter priors.

Every loss maps ``(result: FilterResult, batch: Mapping) -> Tensor [B]``: one value per
trajectory, so that the learner can drop trajectories whose loss is not finite and average the
rest.  ``batch`` holds at least ``truth [B, T, n_t]`` for the supervised losses.

* :class:`MSELoss` - mean squared state error against the truth (optionally on a subset of
  components, e.g. positions).  It only sees the posterior *mean*, which for a Kalman filter
  depends on ``Q`` and ``R`` through their ratio (the gain): scaling both leaves it unchanged,
  so mse alone cannot identify noise levels, only their ratio (and whatever shapes the mean,
  like ``tau``).
* :class:`HuberLoss` - robust version of :class:`MSELoss`: Huber function of the error *norm*
  (quadratic up to ``delta``, linear beyond), so a few large errors (lost lock, start-up
  transients) do not dominate; for ``delta`` well below the typical error it behaves like the
  mean error norm, whose minimiser is closer to the median error than the mse's.
* :class:`NLLLoss` - negative innovation log-likelihood per observed step, no truth needed;
  the maximum-likelihood criterion that identifies ``Q`` and ``R`` themselves.
* :class:`NEESLoss` - ``(log(ANEES_b / d))^2``: penalises per-trajectory average NEES away from
  the number of compared components ``d`` (covariance consistency).
* :class:`StateNLLLoss` - negative log-density of the truth under the estimate's Gaussian,
  ``-log N(x_t; x_hat_t, P_t)`` per step: accuracy and consistency in one proper scoring rule.
* :class:`CompositeLoss` - weighted sum, e.g. ``mse + 0.1 nees`` to get accurate *and*
  consistent estimates.

Every loss reads ``result.mean``/``result.cov``: given a
:class:`~difffilter.smoothers.SmootherResult` (``LearnerOptions(smoother="rts")``) the
state losses score the *smoothed* states ``x_{t|T}``, ``P_{t|T}`` (the innovation ``nll`` stays
the filter's likelihood).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch
from hydra.utils import instantiate
from torch import Tensor

from ..evaluate.metrics import Index, component_error, nees, nll_per_step, select
from ..filters.base import FilterResult
from ..linalg import gaussian_log_density, safe_cholesky

__all__ = [
    "CompositeLoss",
    "FilterLoss",
    "HuberLoss",
    "LogNormalPrior",
    "LogPrior",
    "MSELoss",
    "NEESLoss",
    "NLLLoss",
    "NormalPrior",
    "Prior",
    "StateNLLLoss",
    "make_loss",
]


class FilterLoss(Protocol):
    """``(result, batch) -> [B]`` per-trajectory loss."""

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor: ...


def _truth(batch: Mapping[str, Any], name: str) -> Tensor:
    truth = batch.get("truth")
    if truth is None:
        raise ValueError(f"the {name} loss needs batch['truth'] [B, T, n_t]; use the 'nll' loss for data without truth")
    return truth


def _index(index: Index) -> list[int] | None:
    return None if index is None else [int(i) for i in index]


def _mean_over_valid(per_step: Tensor, valid: Tensor) -> Tensor:
    """Per-trajectory mean of ``per_step [B, T]`` (zero where invalid) over the valid steps."""
    return per_step.sum(-1) / valid.sum(-1).clamp_min(1).to(per_step.dtype)


class MSELoss:
    """Per-trajectory mean squared error ``mean_t ||x_hat_t[index] - x_t[truth_index]||^2 / d``.

    Args:
        state_index: estimate components to compare (``None``: all).
        truth_index: matching truth components (default: ``state_index``).
        weights: optional per-component weights ``[d]`` (e.g. to balance units).
    """

    def __init__(self, *, state_index: Index = None, truth_index: Index = None, weights: Sequence[float] | None = None) -> None:
        self.state_index = _index(state_index)
        self.truth_index = _index(truth_index)
        self.weights = None if weights is None else [float(w) for w in weights]

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        err, valid = component_error(result.mean, _truth(batch, "mse"), self.state_index, self.truth_index)
        sq = err * err
        if self.weights is not None:
            sq = sq * torch.as_tensor(self.weights, dtype=sq.dtype, device=sq.device)
        return _mean_over_valid(sq.mean(-1), valid)


class HuberLoss:
    """Per-trajectory mean Huber error ``mean_t rho(||x_hat_t[index] - x_t[truth_index]||)`` with
    ``rho(n) = n^2 / 2`` for ``n <= delta`` and ``delta (n - delta / 2)`` beyond (continuous, with a
    continuous slope).  Steps whose truth is not finite are left out, as in :class:`MSELoss`.

    Args:
        state_index, truth_index: as :class:`MSELoss`.
        delta: the error norm (truth units, e.g. m) where the loss turns from quadratic to linear.
    """

    def __init__(self, *, state_index: Index = None, truth_index: Index = None, delta: float = 1.0) -> None:
        if not float(delta) > 0:
            raise ValueError(f"delta must be positive, got {delta}")
        self.state_index = _index(state_index)
        self.truth_index = _index(truth_index)
        self.delta = float(delta)

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        err, valid = component_error(result.mean, _truth(batch, "huber"), self.state_index, self.truth_index)
        sq = (err * err).sum(-1)
        # the norm only matters (and is differentiated) in the linear branch, where sq > delta^2
        norm = torch.sqrt(sq.clamp_min(self.delta**2))
        # steps without truth have zero error (component_error), hence zero loss and gradient
        per_step = torch.where(sq <= self.delta**2, 0.5 * sq, self.delta * (norm - 0.5 * self.delta))
        return _mean_over_valid(per_step, valid)


class NLLLoss:
    """Negative innovation log-likelihood per observed step ``-sum_t log N(e_t; 0, S_t) / T_obs``."""

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        return nll_per_step(result)


class NEESLoss:
    """``(log(ANEES_b / d))^2`` with ``ANEES_b`` the trajectory's average NEES over ``d`` compared
    components: zero when the filter's covariance matches its errors on average, and symmetric
    in over- and under-confidence on a log scale.

    Args:
        state_index, truth_index: as :class:`MSELoss`.
    """

    def __init__(self, *, state_index: Index = None, truth_index: Index = None) -> None:
        self.state_index = _index(state_index)
        self.truth_index = _index(truth_index)

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        ne = nees(result.mean, result.cov, _truth(batch, "nees"), self.state_index, self.truth_index)
        d = len(self.state_index) if self.state_index is not None else result.mean.shape[-1]
        ok = torch.isfinite(ne)
        avg = torch.where(ok, ne, torch.zeros_like(ne)).sum(-1) / ok.sum(-1).clamp_min(1)
        return torch.log(avg / d) ** 2


class StateNLLLoss:
    """Per-trajectory mean of ``-log N(x_t[truth_index]; x_hat_t[index], P_t[index, index])`` over
    the steps with a finite truth: the negative log-likelihood of the truth under the filtered (or
    smoothed) posterior, which rewards small errors and covariances that match them.

    Args:
        state_index, truth_index: as :class:`MSELoss`.
    """

    def __init__(self, *, state_index: Index = None, truth_index: Index = None) -> None:
        self.state_index = _index(state_index)
        self.truth_index = _index(truth_index)

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        err, valid = component_error(result.mean, _truth(batch, "state_nll"), self.state_index, self.truth_index)
        cov = result.cov
        if self.state_index is not None:
            cov = select(select(cov, self.state_index).mT, self.state_index)
        logp, _ = gaussian_log_density(err, safe_cholesky(cov).factor)
        return _mean_over_valid(torch.where(valid, -logp, torch.zeros_like(logp)), valid)


class CompositeLoss:
    """Weighted sum of losses: ``CompositeLoss({"mse": MSELoss(), "nees": NEESLoss()}, {"nees": 0.1})``."""

    def __init__(self, terms: Mapping[str, FilterLoss], weights: Mapping[str, float] | None = None) -> None:
        if not terms:
            raise ValueError("CompositeLoss needs at least one term")
        self.terms = dict(terms)
        self.weights = {k: float((weights or {}).get(k, 1.0)) for k in self.terms}

    def __call__(self, result: FilterResult, batch: Mapping[str, Any]) -> Tensor:
        # sum() starts from the int 0, which mypy keeps in the type; the terms are tensors, so is the sum
        return sum(self.weights[k] * fn(result, batch) for k, fn in self.terms.items())  # type: ignore[return-value]


class Prior(Protocol):
    """``log_prob(value) -> scalar``: log-density of a constrained parameter value."""

    def log_prob(self, value: Tensor) -> Tensor: ...


class NormalPrior:
    """Independent ``N(loc, scale^2)`` on every element of a constrained value."""

    def __init__(self, *, loc: float | Sequence[float], scale: float | Sequence[float]) -> None:
        self.loc, self.scale = loc, scale

    def log_prob(self, value: Tensor) -> Tensor:
        loc = torch.as_tensor(self.loc, dtype=value.dtype, device=value.device)
        scale = torch.as_tensor(self.scale, dtype=value.dtype, device=value.device)
        z = (value - loc) / scale
        return (-0.5 * z * z - torch.log(scale) - 0.5 * math.log(2 * math.pi)).sum()


class LogNormalPrior:
    """Independent log-normal prior, ``log(value) ~ N(loc, scale^2)`` (for scales such as tau, or
    the diagonal of a covariance: matrices use their diagonal)."""

    def __init__(self, *, loc: float | Sequence[float], scale: float | Sequence[float]) -> None:
        self.loc, self.scale = loc, scale

    def log_prob(self, value: Tensor) -> Tensor:
        if value.ndim >= 2 and value.shape[-1] == value.shape[-2]:
            value = torch.diagonal(value, dim1=-2, dim2=-1)
        logv = torch.log(value)
        return NormalPrior(loc=self.loc, scale=self.scale).log_prob(logv) - logv.sum()


@dataclass(frozen=True)
class LogPrior:
    """Priors on named parameters for a MAP objective: the learner's loss becomes
    ``data_loss - weight * sum_name log p(value of name)``.

    Attributes:
        priors: ``{parameter name: prior with log_prob(value)}`` (names matched as in
            :mod:`difffilter.selection`).
        weight: weight of the log-prior (the data loss is per step and trajectory, so
            ``1 / (trajectories x steps)`` makes the objective the MAP one).
    """

    priors: Mapping[str, Prior]
    weight: float = 1.0

    def __post_init__(self) -> None:
        bad = [k for k, v in self.priors.items() if not callable(getattr(v, "log_prob", None))]
        if bad:
            raise TypeError(f"LogPrior priors must have log_prob(value); not so for {bad}")
        object.__setattr__(self, "weight", float(self.weight))


_LOSSES: dict[str, Callable[[], FilterLoss]] = {"mse": MSELoss, "nll": NLLLoss, "nees": NEESLoss, "state_nll": StateNLLLoss}


def make_loss(loss: FilterLoss | str | Mapping[str, Any]) -> FilterLoss:
    """A loss object from a name (``"mse"``, ``"nll"``, ``"nees"``, ``"state_nll"``), a Hydra config (a mapping
    with ``_target_``, e.g. ``conf/loss/*.yaml``) or a callable."""
    if isinstance(loss, Mapping):
        if "_target_" not in loss:
            raise ValueError(f"a loss config needs a _target_, got keys {sorted(loss)}")
        return make_loss(instantiate(loss, _convert_="all"))
    if isinstance(loss, str):
        if loss not in _LOSSES:
            raise ValueError(f"loss must be one of {sorted(_LOSSES)} or a callable, got {loss!r}")
        return _LOSSES[loss]()
    if not callable(loss):
        raise TypeError(f"loss must be a name or a callable (result, batch) -> [B], got {type(loss).__name__}")
    return loss
