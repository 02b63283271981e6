"""Confidence intervals for the evaluation protocol: Student-t intervals over independent units,
the seeds x runs crossed design, paired circular moving-block bootstrap for one long time series,
and the "gap closed" ratio.

Units of replication (what the intervals treat as independent):

* **test runs** - trajectories simulated with independent noise; the steps of one run are not
  independent (errors and NEES are correlated over tens to hundreds of steps), so a per-run
  metric is first averaged over time, then compared across runs;
* **training seeds** - independent training replicates (data and initialisation), all evaluated
  on the *same* test runs, which makes seeds x runs a crossed design (:func:`crossed_interval`);
* **blocks of epochs** - for a single long series (one real drive) a circular moving-block
  bootstrap resamples blocks longer than the error's correlation time
  (:func:`block_bootstrap_difference`).

Every function takes plain tensors (or anything ``torch.as_tensor`` accepts), works in float64
and returns an :class:`Interval` (point estimate, two-sided bounds, standard error, degrees of
freedom).  The Student-t quantile comes from :mod:`difffilter.evaluate.student_t`, so scipy stays a
test-only dependency.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .student_t import student_t_quantile

__all__ = [
    "GapClosed",
    "Interval",
    "block_bootstrap_difference",
    "circular_block_indices",
    "crossed_interval",
    "gap_closed",
    "nested_interval",
    "t_interval",
]

_NAN = float("nan")


@dataclass(frozen=True)
class Interval:
    """A point estimate with a two-sided interval.

    Attributes:
        estimate: the point estimate.
        lo, hi: interval bounds (NaN when there are too few units to form one).
        se: standard error of the estimate (NaN for percentile bootstrap intervals: the
            bootstrap standard deviation instead).
        dof: degrees of freedom of the t quantile used (NaN for bootstrap intervals).
        n: number of independent units behind the interval.
    """

    estimate: float
    lo: float
    hi: float
    se: float = _NAN
    dof: float = _NAN
    n: int = 0

    def contains(self, value: float) -> bool:
        """Whether ``lo <= value <= hi`` (False when the interval is undefined)."""
        return bool(self.lo <= value <= self.hi)

    @property
    def excludes_zero(self) -> bool:
        """Whether the interval lies strictly on one side of 0 (a difference that is not a tie)."""
        return bool(self.lo > 0.0 or self.hi < 0.0)

    def scaled(self, factor: float) -> Interval:
        """The interval of ``factor x`` the estimate (e.g. a difference as a percentage)."""
        lo, hi = sorted((self.lo * factor, self.hi * factor))
        return Interval(self.estimate * factor, lo, hi, abs(self.se * factor), self.dof, self.n)


def _as_f64(values: object, name: str, ndim: int) -> Tensor:
    v = torch.as_tensor(values).detach().to("cpu", torch.float64)
    if v.ndim != ndim:
        raise ValueError(f"{name} must be a {ndim}-D array, got shape {tuple(v.shape)}")
    return v


def _check_prob(prob: float) -> float:
    prob = float(prob)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob must lie in (0, 1), got {prob}")
    return prob


def _t_bounds(estimate: float, var: float, dof: float, n: int, prob: float) -> Interval:
    se = math.sqrt(max(var, 0.0))
    if not (dof > 0.0) or not math.isfinite(se):
        return Interval(estimate, _NAN, _NAN, se, dof, n)
    half = student_t_quantile(0.5 + 0.5 * prob, dof) * se
    return Interval(estimate, estimate - half, estimate + half, se, dof, n)


def t_interval(values: object, prob: float = 0.95) -> Interval:
    """Student-t interval of the mean of independent values ``[N]`` (non-finite entries dropped).

    ``mean +- t_{(1+prob)/2, N-1} s / sqrt(N)``; bounds are NaN when fewer than 2 values are finite.
    """
    prob = _check_prob(prob)
    v = _as_f64(values, "values", 1)
    v = v[torch.isfinite(v)]
    n = int(v.numel())
    if n == 0:
        return Interval(_NAN, _NAN, _NAN)
    mean = float(v.mean())
    if n < 2:
        return Interval(mean, _NAN, _NAN, _NAN, _NAN, n)
    return _t_bounds(mean, float(v.var(unbiased=True)) / n, n - 1.0, n, prob)


def crossed_interval(values: object, prob: float = 0.95) -> Interval:
    """Interval of the grand mean of ``values [S, N]``: S training seeds evaluated on the same N test runs.

    Model: ``y_sr = mu + a_s + b_r + e_sr`` (seed effect, run effect, interaction), so
    ``Var(mean) = s_a^2/S + s_b^2/N + s_e^2/(S N)``.  The sample variance of the seed means over
    ``S`` estimates ``s_a^2/S + s_e^2/(S N)`` and that of the run means over ``N`` estimates
    ``s_b^2/N + s_e^2/(S N)``; their sum (the standard error used) counts the interaction twice,
    so the interval is slightly conservative.  Degrees of freedom: Welch-Satterthwaite.  With
    ``S = 1`` (or a filter that does not depend on the seed) it is the t-interval over runs, with
    ``N = 1`` the t-interval over seeds.  Rows or columns with a non-finite entry are dropped
    (a run where any seed's metric is undefined, then a seed).
    """
    prob = _check_prob(prob)
    v = _as_f64(values, "values", 2)
    v = v[:, torch.isfinite(v).all(0)]
    v = v[torch.isfinite(v).all(1)]
    s, n = v.shape
    if s == 0 or n == 0:
        return Interval(_NAN, _NAN, _NAN)
    mean = float(v.mean())
    parts: list[tuple[float, float]] = []
    if s >= 2:
        parts.append((float(v.mean(1).var(unbiased=True)) / s, s - 1.0))
    if n >= 2:
        parts.append((float(v.mean(0).var(unbiased=True)) / n, n - 1.0))
    if not parts:
        return Interval(mean, _NAN, _NAN, _NAN, _NAN, s * n)
    var = sum(p for p, _ in parts)
    if var == 0.0:
        return Interval(mean, mean, mean, 0.0, math.inf, s * n)
    dof = var * var / sum(p * p / d for p, d in parts if p > 0.0)
    return _t_bounds(mean, var, dof, s * n, prob)


def nested_interval(seed_means: object, prob: float = 0.95) -> Interval:
    """Interval of the mean over seeds when every seed was tested on its *own* runs: the
    t-interval of the per-seed means ``[S]`` (each already averages its runs)."""
    return t_interval(seed_means, prob)


# -- block bootstrap ------------------------------------------------------------------------------
def circular_block_indices(length: int, *, block: int, draws: int, generator: torch.Generator) -> Tensor:
    """``[draws, length]`` indices of circular moving-block bootstrap resamples of a series of ``length``.

    Each resample concatenates ``ceil(length / block)`` blocks of ``block`` consecutive indices
    (wrapping around the end) starting at uniform positions, cut to ``length``.
    """
    if length < 1:
        raise ValueError(f"length must be positive, got {length}")
    if not 1 <= block <= length:
        raise ValueError(f"block must lie in [1, {length}], got {block}")
    if draws < 1:
        raise ValueError(f"draws must be positive, got {draws}")
    per = -(-length // block)
    starts = torch.randint(0, length, (draws, per), generator=generator)
    return ((starts[..., None] + torch.arange(block)) % length).reshape(draws, -1)[:, :length]


Statistic = Callable[[Tensor], Tensor]

_STATISTICS: dict[str, Statistic] = {
    "mean": lambda x: x.mean(-1),
    "rms": lambda x: x.pow(2).mean(-1).sqrt(),
    "median": lambda x: x.median(-1).values,
}


def _percentile(draws: Tensor, prob: float, *, outward: bool = False) -> tuple[float, float]:
    """Two-sided percentile interval of bootstrap draws (linear interpolation; ``outward``: the
    order statistics just outside, which stays defined when some draws are infinite)."""
    tail = 0.5 * (1.0 - prob)
    q = torch.tensor([tail, 1.0 - tail], dtype=torch.float64)
    if not outward:
        lo, hi = torch.quantile(draws, q)
        return float(lo), float(hi)
    return float(torch.quantile(draws, q[0], interpolation="lower")), float(torch.quantile(draws, q[1], interpolation="higher"))


def block_bootstrap_difference(
    a: object,
    b: object,
    *,
    statistic: str | Statistic = "rms",
    block: int,
    draws: int = 4000,
    seed: int = 0,
    prob: float = 0.95,
) -> Interval:
    """Paired interval of ``statistic(a) - statistic(b)`` for two filters' per-step errors ``[T]``
    on the same time series (one long drive), by the circular moving-block bootstrap.

    Both series are resampled with the *same* blocks, which keeps the pairing and, with
    ``block`` longer than the errors' correlation time, their serial dependence; resampling
    single steps would make the interval far too narrow.  Percentile interval; ``se`` is the
    bootstrap standard deviation.

    Args:
        a, b: paired per-step values ``[T]`` (e.g. horizontal error norms), finite.
        statistic: ``"rms"``, ``"mean"``, ``"median"`` or a callable ``[draws, T] -> [draws]``.
        block: block length in steps.
        draws: bootstrap resamples.
        seed: seed of the resampling.
        prob: coverage of the interval.
    """
    prob = _check_prob(prob)
    x, y = _as_f64(a, "a", 1), _as_f64(b, "b", 1)
    if x.shape != y.shape:
        raise ValueError(f"a and b must be paired series of one length, got {tuple(x.shape)} and {tuple(y.shape)}")
    if not bool(torch.isfinite(x).all() and torch.isfinite(y).all()):
        raise ValueError("a and b must be finite (drop the steps without a truth first, in both)")
    if isinstance(statistic, str):
        if statistic not in _STATISTICS:
            raise ValueError(f"statistic must be one of {sorted(_STATISTICS)} or a callable, got {statistic!r}")
        stat = _STATISTICS[statistic]
    elif callable(statistic):
        stat = statistic
    else:
        raise TypeError(f"statistic must be a name or a callable, got {type(statistic).__name__}")
    idx = circular_block_indices(x.numel(), block=block, draws=draws, generator=torch.Generator().manual_seed(int(seed)))
    diffs = stat(x[idx]) - stat(y[idx])
    estimate = float(stat(x[None]) - stat(y[None]))
    lo, hi = _percentile(diffs, prob)
    return Interval(estimate, lo, hi, float(diffs.std()), _NAN, -(-x.numel() // block))


# -- gap closed -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class GapClosed:
    """``G = (e_hand - e_learned) / (e_hand - e_oracle)`` with a bootstrap interval.

    Attributes:
        value, lo, hi: ``G`` and its percentile interval (NaN when not defined; an infinite bound
            when more than the interval's tail of resamples had no positive gap).
        gap: interval of ``e_hand - e_oracle`` (crossed design over seeds and runs).
        defined: whether the hand-tuned filter is measurably worse than the oracle (``gap``
            excludes 0 and is positive); otherwise ``G`` is undefined, not 0 or 1.
        reason: why ``G`` is undefined ("" when defined).
    """

    value: float
    lo: float
    hi: float
    gap: Interval
    defined: bool
    reason: str = ""


def _as_matrix(values: object, name: str) -> Tensor:
    v = torch.as_tensor(values).detach().to("cpu", torch.float64)
    if v.ndim == 1:
        v = v[None]
    if v.ndim != 2:
        raise ValueError(f"{name} must be [N] or [S, N], got shape {tuple(v.shape)}")
    return v


def gap_closed(
    hand: object,
    learned: object,
    oracle: object,
    *,
    prob: float = 0.95,
    draws: int = 4000,
    seed: int = 0,
) -> GapClosed:
    """Fraction of the hand-tuned-to-oracle gap that learning closes, from per-run errors.

    ``e_f`` is the mean of filter ``f``'s per-run metric over runs (and seeds); lower is better.
    ``G = 1``: learned matches the oracle; ``G = 0``: no better than hand-tuned; ``G < 0``:
    worse.  ``G`` is only defined when the denominator is measurably positive: the paired
    interval of ``e_hand - e_oracle`` (:func:`crossed_interval`) must exclude 0.  A hand-tuned
    filter that ties the oracle leaves nothing to close, and dividing by a difference that is
    within noise of 0 gives meaningless, arbitrarily large ratios.

    The interval resamples test runs (the same runs for every filter, keeping the pairing) and,
    when there are several, training seeds (the same seeds for every seed-dependent filter),
    ``draws`` times; a resample whose gap is not positive gives ``G = +-inf`` (sign of the
    numerator), so an interval reaching such resamples is honestly unbounded.

    Args:
        hand, learned, oracle: per-run metrics ``[N]`` or ``[S, N]`` (seeds x the same N runs);
            ``[N]`` is a filter that does not depend on the seed.
        prob: coverage of the intervals.
        draws: bootstrap resamples.
        seed: seed of the resampling.
    """
    prob = _check_prob(prob)
    mats = {k: _as_matrix(v, k) for k, v in {"hand": hand, "learned": learned, "oracle": oracle}.items()}
    runs = {m.shape[1] for m in mats.values()}
    if len(runs) != 1:
        raise ValueError(f"hand, learned and oracle must cover the same runs, got run counts {sorted(runs)}")
    seeds = max(m.shape[0] for m in mats.values())
    if any(m.shape[0] not in (1, seeds) for m in mats.values()):
        raise ValueError(f"seed counts must be 1 or {seeds}, got {[m.shape[0] for m in mats.values()]}")
    h, lrn, o = (m.expand(seeds, -1) for m in mats.values())
    gap = crossed_interval(h - o, prob)
    num = float((h - lrn).mean())
    den = float((h - o).mean())
    if not gap.excludes_zero or gap.estimate <= 0.0:
        why = "hand-tuned ties the oracle" if not gap.excludes_zero else "hand-tuned is better than the oracle"
        reason = f"{why}: e_hand - e_oracle = {gap.estimate:.4g} [{gap.lo:.4g}, {gap.hi:.4g}]"
        return GapClosed(_NAN, _NAN, _NAN, gap, False, reason)
    gen = torch.Generator().manual_seed(int(seed))
    n = h.shape[1]
    run_idx = torch.randint(0, n, (draws, n), generator=gen)
    seed_idx = torch.randint(0, seeds, (draws, seeds), generator=gen) if seeds > 1 else torch.zeros(draws, 1, dtype=torch.long)

    def resampled_mean(m: Tensor) -> Tensor:
        rows = m[seed_idx]  # [draws, S', N]
        return torch.gather(rows, 2, run_idx[:, None, :].expand(-1, rows.shape[1], -1)).mean((1, 2))

    eh, el, eo = resampled_mean(h), resampled_mean(lrn), resampled_mean(o)
    d_num, d_den = eh - el, eh - eo
    ratio = torch.where(
        d_den > 0, d_num / d_den.where(d_den > 0, torch.ones_like(d_den)), torch.copysign(torch.full_like(d_num, math.inf), d_num)
    )
    lo, hi = _percentile(ratio, prob, outward=True)
    return GapClosed(num / den, lo, hi, gap, True, "")
