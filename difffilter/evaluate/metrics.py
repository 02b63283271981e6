"""Filter evaluation metrics: RMSE, NEES/NIS consistency with chi-square bounds, innovation
whiteness and IMM mode-switch delay.

Conventions:

* Errors compare a subset of the estimate (``index``) with a subset of the truth
  (``truth_index``, default the same indices), so truth and state layouts may differ (a truth of
  positions only, a filter state with clock terms...).  Non-finite truth entries (gaps in real
  ground truth) are left out.
* ``rmse`` is the root of the mean squared error *norm* over the chosen components (the
  distance error for positions): ``sqrt(mean_{b,t} ||e_{b,t}||^2)``.
* ``NEES_{b,t} = e^T P^{-1} e`` on the chosen sub-block of the covariance; ``ANEES`` averages it
  and is consistent when close to the number of components ``d``.  ``NIS`` is the same for
  innovations (``d`` = observed components per step).  The steps of one run are *not*
  independent, so no band is derived from the runs x steps average here: the consistency
  verdicts (per-step chi-square band over runs, run-level t-interval, per state block) are in
  :mod:`difffilter.evaluate.consistency`.
* Additive sums (:func:`metric_sums`) let batches and processes be combined exactly before
  :func:`finalize_metrics` divides (what the Lightning module does under DDP).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from statistics import NormalDist

import torch
from torch import Tensor

from ..filters.base import FilterResult
from ..linalg import gaussian_log_density, safe_cholesky

__all__ = [
    "ModeSwitchDelays",
    "Whiteness",
    "anees",
    "anis",
    "chi2_interval",
    "chi2_quantile",
    "component_error",
    "finalize_metrics",
    "innovation_whiteness",
    "metric_sums",
    "mode_switch_delay",
    "nees",
    "nll_per_step",
    "rmse",
    "select",
    "wilson_hilferty",
]

Index = Sequence[int] | Tensor | None


def select(x: Tensor, index: Index) -> Tensor:
    """``x[..., index]`` (all components when ``index`` is ``None``)."""
    if index is None:
        return x
    idx = torch.as_tensor(list(index) if not isinstance(index, Tensor) else index, dtype=torch.long, device=x.device)
    return x.index_select(-1, idx)


def component_error(estimate: Tensor, truth: Tensor, index: Index, truth_index: Index) -> tuple[Tensor, Tensor]:
    """Error ``[..., d]`` (zero where the truth is not finite) and its validity ``[...]``."""
    est = select(estimate, index)
    tru = select(truth, index if truth_index is None else truth_index)
    if est.shape[-1] != tru.shape[-1]:
        raise ValueError(f"estimate selects {est.shape[-1]} components but truth selects {tru.shape[-1]}; set truth_index")
    valid = torch.isfinite(tru).all(-1)
    err = torch.where(valid[..., None], est - torch.nan_to_num(tru), torch.zeros_like(est))
    return err, valid


def rmse(estimate: Tensor, truth: Tensor, index: Index = None, truth_index: Index = None, *, per_component: bool = False) -> Tensor:
    """Root-mean-square error over batch and time, ``estimate [B, T, n]``, ``truth [B, T, n_t]``.

    Returns a scalar ``sqrt(mean ||e||^2)`` or, with ``per_component``, ``[d]`` per-component RMSE.
    """
    err, valid = component_error(estimate, truth, index, truth_index)
    count = valid.sum().clamp_min(1).to(err.dtype)
    if per_component:
        return torch.sqrt((err * err).sum(tuple(range(err.ndim - 1))) / count)
    return torch.sqrt((err * err).sum() / count)


def nees(mean: Tensor, cov: Tensor, truth: Tensor, index: Index = None, truth_index: Index = None) -> Tensor:
    """Normalised estimation error squared ``[B, T]`` (NaN where the truth is not finite).

    ``mean [B, T, n]``, ``cov [B, T, n, n]``; the error and covariance are restricted to ``index``.
    """
    err, valid = component_error(mean, truth, index, truth_index)
    if index is not None:
        idx = torch.as_tensor(list(index) if not isinstance(index, Tensor) else index, dtype=torch.long, device=cov.device)
        cov = cov.index_select(-1, idx).index_select(-2, idx)
    _, maha = gaussian_log_density(err, safe_cholesky(cov).factor)
    return torch.where(valid, maha, torch.full_like(maha, float("nan")))


def anees(nees_values: Tensor) -> Tensor:
    """Average NEES over every finite entry (scalar)."""
    ok = torch.isfinite(nees_values)
    return torch.where(ok, nees_values, torch.zeros_like(nees_values)).sum() / ok.sum().clamp_min(1)


def anis(result: FilterResult) -> Tensor:
    """Average NIS over the steps with at least one observed component (scalar)."""
    obs = result.num_observed > 0
    return (result.nis * obs).sum() / obs.sum().clamp_min(1)


def nll_per_step(result: FilterResult) -> Tensor:
    """``[B]`` negative log-likelihood per observed step."""
    steps = (result.num_observed > 0).sum(-1).clamp_min(1)
    return -result.log_likelihood.sum(-1) / steps


def chi2_quantile(prob: float, dof: float) -> float:
    """Quantile of ``chi2(dof)``: scipy when available, else the Wilson-Hilferty approximation
    ``dof (1 - 2/(9 dof) + z_p sqrt(2/(9 dof)))^3`` (relative error of the 2.5/50/97.5 % quantiles below ``0.08 / dof``; the
    per-step bands use ``dof = d x runs``)."""
    if dof <= 0:
        raise ValueError(f"dof must be positive, got {dof}")
    try:
        from scipy.stats import chi2  # test-only dependency
    except ImportError:  # pragma: no cover - exercised by monkeypatching in the tests
        return wilson_hilferty(prob, dof)
    return float(chi2.ppf(prob, dof))


def wilson_hilferty(prob: float, dof: float) -> float:
    """Wilson-Hilferty approximation of the ``chi2(dof)`` quantile."""
    z = NormalDist().inv_cdf(prob)
    c = 2.0 / (9.0 * dof)
    return dof * max(1.0 - c + z * math.sqrt(c), 0.0) ** 3


def chi2_interval(dof: float, num_samples: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of the average of ``num_samples`` *independent* ``chi2(dof)``
    variables: ``chi2(N dof) / N``.  For NEES this is the band of one step's mean over
    ``num_samples`` independent runs; it is not a band for an average over the steps of a run,
    which are correlated (see :mod:`difffilter.evaluate.consistency`)."""
    total = dof * num_samples
    tail = 0.5 * (1.0 - prob)
    return chi2_quantile(tail, total) / num_samples, chi2_quantile(1.0 - tail, total) / num_samples


@dataclass
class Whiteness:
    """Normalised innovation autocorrelation ``rho [L]`` at lags ``1..L``, the 95 % bound
    ``[L]`` under whiteness, and the fraction of lags outside it."""

    rho: Tensor
    bound: Tensor
    fraction_outside: float


def innovation_whiteness(innovations: Tensor, mask: Tensor | None = None, max_lag: int = 10) -> Whiteness:
    """Whiteness test of innovations ``[B, T, m]`` (or ``[B, T]``), pooled over the batch.

    ``rho_l = sum e_t . e_{t+l} / sqrt(sum |e_t|^2 sum |e_{t+l}|^2)`` over all pairs of observed
    steps ``l`` apart.  Under whiteness ``rho_l`` is approximately normal with variance
    ``sum (e_t . e_{t+l})^2 / (sum |e_t|^2 sum |e_{t+l}|^2)`` (the products are uncorrelated),
    which gives the 95 % bound ``1.96 x`` its square root without assuming a noise level.
    ``mask [B, T]`` drops missing steps.
    """
    e = innovations[..., None] if innovations.ndim == 2 else innovations
    steps = e.shape[1]
    if not 1 <= max_lag < steps:
        raise ValueError(f"max_lag must lie in [1, T - 1] = [1, {steps - 1}], got {max_lag}")
    ok = torch.isfinite(e).all(-1) if mask is None else (mask.bool() & torch.isfinite(e).all(-1))
    e = torch.where(ok[..., None], e, torch.zeros_like(e))
    z = NormalDist().inv_cdf(0.975)
    rhos, bounds = [], []
    for lag in range(1, max_lag + 1):
        a, b = e[:, :-lag], e[:, lag:]
        pair = (ok[:, :-lag] & ok[:, lag:]).to(e.dtype)
        prod = (a * b).sum(-1) * pair
        denom = torch.sqrt(((a * a).sum(-1) * pair).sum() * ((b * b).sum(-1) * pair).sum()).clamp_min(torch.finfo(e.dtype).tiny)
        rhos.append(prod.sum() / denom)
        bounds.append(z * torch.sqrt((prod * prod).sum()) / denom)
    rho, bound = torch.stack(rhos), torch.stack(bounds)
    return Whiteness(rho, bound, float((rho.abs() > bound).to(e.dtype).mean()))


@dataclass
class ModeSwitchDelays:
    """One entry per switch of the true mode: ``delay`` in steps (NaN if the matching mode never
    exceeded the threshold before the next switch or the end), trajectory ``batch_index``, the
    ``start`` step and the new ``mode``."""

    delay: Tensor
    batch_index: Tensor
    start: Tensor
    mode: Tensor

    def mean(self) -> float:
        """Mean delay over the detected switches (NaN if none)."""
        ok = torch.isfinite(self.delay)
        return float(self.delay[ok].mean()) if bool(ok.any()) else math.nan


def mode_switch_delay(mode_probs: Tensor, true_modes: Tensor, threshold: float = 0.5) -> ModeSwitchDelays:
    """Steps from each manoeuvre start until the matching IMM mode probability exceeds ``threshold``.

    Args:
        mode_probs: ``[B, T, M]`` posterior mode probabilities.
        true_modes: ``[B, T]`` integer true mode at each step; a switch is a step where it
            differs from the previous step.
        threshold: detection level (0.5: the matching mode is the most likely of two).
    """
    if mode_probs.ndim != 3 or true_modes.shape != mode_probs.shape[:2]:
        raise ValueError(f"mode_probs must be [B, T, M] and true_modes [B, T], got {tuple(mode_probs.shape)}, {tuple(true_modes.shape)}")
    modes = true_modes.long()
    starts = (modes[:, 1:] != modes[:, :-1]).nonzero()
    delays, bidx, tidx, midx = [], [], [], []
    steps = modes.shape[1]
    for b, t in starts.tolist():
        t0, mode = t + 1, int(modes[b, t + 1])
        later = (modes[b, t0:] != mode).nonzero()
        end = t0 + int(later[0]) if later.numel() else steps
        hit = (mode_probs[b, t0:end, mode] > threshold).nonzero()
        delays.append(float(hit[0]) if hit.numel() else math.nan)
        bidx.append(b)
        tidx.append(t0)
        midx.append(mode)
    as_long = lambda v: torch.tensor(v, dtype=torch.long)  # noqa: E731
    return ModeSwitchDelays(torch.tensor(delays, dtype=mode_probs.dtype), as_long(bidx), as_long(tidx), as_long(midx))


def metric_sums(
    result: FilterResult,
    truth: Tensor | None,
    *,
    position_index: Index = None,
    truth_position_index: Index = None,
    state_index: Index = None,
    truth_index: Index = None,
) -> dict[str, Tensor]:
    """Additive statistics of one batch (scalars, float64): squared position error and count,
    squared state error, NEES sum/count/dof, NIS sum/count/dof and negative log-likelihood over
    observed steps.  Combine by summing, then :func:`finalize_metrics`.  Detached (statistics, not
    training targets)."""
    f64 = torch.float64
    obs = result.num_observed > 0
    out = {
        "nis_sum": (result.nis * obs).sum().to(f64),
        "nis_count": obs.sum().to(f64),
        "nis_dof": result.num_observed.sum().to(f64),
        "nll_sum": (-result.log_likelihood).sum().to(f64),
        "nll_steps": obs.sum().to(f64),
    }
    if truth is not None:
        pos_idx = position_index if position_index is not None else state_index
        pos_tidx = truth_position_index if position_index is not None else truth_index
        err, valid = component_error(result.mean, truth, pos_idx, pos_tidx)
        out["sq_pos"] = (err * err).sum().to(f64)
        out["pos_count"] = valid.sum().to(f64)
        err, valid = component_error(result.mean, truth, state_index, truth_index)
        out["sq_state"] = (err * err).sum().to(f64)
        out["state_count"] = valid.sum().to(f64)
        ne = nees(result.mean, result.cov, truth, state_index, truth_index)
        ok = torch.isfinite(ne)
        out["nees_sum"] = torch.where(ok, ne, torch.zeros_like(ne)).sum().to(f64)
        out["nees_count"] = ok.sum().to(f64)
        out["nees_dof"] = out["nees_count"] * err.shape[-1]
    return {k: v.detach() for k, v in out.items()}


def finalize_metrics(sums: Mapping[str, Tensor | float]) -> dict[str, float]:
    """Turn summed statistics into ``rmse_pos``, ``rmse_state``, ``anees`` (mean NEES over every
    run and step), ``nis`` (mean NIS per observed step) and ``nll`` (per observed step).

    Point values only: the steps behind these sums are correlated, so their count gives no valid
    interval (:mod:`difffilter.evaluate.consistency` has the verdicts)."""
    s = {k: float(v) for k, v in sums.items()}
    out: dict[str, float] = {}
    if s.get("nll_steps", 0) > 0:
        out["nll"] = s["nll_sum"] / s["nll_steps"]
    if s.get("nis_count", 0) > 0:
        out["nis"] = s["nis_sum"] / s["nis_count"]
    if s.get("pos_count", 0) > 0:
        out["rmse_pos"] = math.sqrt(s["sq_pos"] / s["pos_count"])
    if s.get("state_count", 0) > 0:
        out["rmse_state"] = math.sqrt(s["sq_state"] / s["state_count"])
    if s.get("nees_count", 0) > 0:
        out["anees"] = s["nees_sum"] / s["nees_count"]
    return out
