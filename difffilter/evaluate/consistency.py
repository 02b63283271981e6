"""Covariance consistency (NEES, NIS) judged with the right units of independence.

A consistent filter's NEES at one step is ``chi2(d)`` distributed (``d`` compared components),
but consecutive steps of one run are strongly correlated (an estimation error decays over the
filter's memory, tens to hundreds of steps).  Averaging all runs x steps and comparing with the
``chi2(d B T) / (B T)`` band treats every step as independent and makes the band far too narrow
(for a filter whose errors stay correlated over ``tau`` steps, about ``sqrt(tau)`` times).  Two
statistics that are valid instead:

* **per-step band** - at each step ``t`` the N runs are independent, so the sum over runs of
  the NEES is ``chi2(d N)`` (the mean ``chi2(d N) / N``); :func:`step_band_fraction` is the
  fraction of steps whose mean lies inside the two-sided ``prob`` band, about ``prob`` for a
  consistent filter (steps with a missing truth or measurement use the runs observed there);
* **run-level mean** - average each run over time, then take the t-interval over the N runs
  (:func:`~difffilter.evaluate.intervals.t_interval`); a consistent filter's interval covers ``d``
  in about ``prob`` of experiments.

Both are reported for the whole compared state and for every **state block** (position,
velocity, attitude, sensor errors...): an all-state total averages an over-confident block with
an under-confident one.  Blocks are a plain mapping ``{name: state indices}``.  NIS is treated
the same way, with ``d`` the number of observed measurement components of each step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..filters.base import FilterResult
from .intervals import Interval, t_interval
from .metrics import Index, chi2_quantile, nees

__all__ = [
    "Consistency",
    "block_truth_indices",
    "consistency",
    "nees_by_block",
    "nis_per_step",
    "run_average",
    "step_band_fraction",
]


@dataclass(frozen=True)
class Consistency:
    """Consistency of one NEES (or NIS) series ``[N, T]``.

    Attributes:
        dof: the value a consistent filter's run-level mean has (``d`` for NEES; for NIS the
            mean number of observed components per observed step).
        mean: run-level mean: each run averaged over its steps, then the mean over runs.
        run_ci: t-interval of ``mean`` over runs.
        step_band_frac: fraction of steps whose mean over runs lies in its ``prob`` chi-square band.
        num_runs, num_steps: runs with at least one finite value; steps with at least one.
    """

    dof: float
    mean: float
    run_ci: Interval
    step_band_frac: float
    num_runs: int
    num_steps: int

    @property
    def consistent(self) -> bool:
        """Whether the run-level interval covers ``dof`` (False when it is undefined)."""
        return self.run_ci.contains(self.dof)

    def as_row(self, prefix: str) -> dict[str, float]:
        """Flat columns ``{prefix}``, ``{prefix}_dof``, ``..._run_ci_lo/hi``, ``..._step_band_frac``."""
        return {
            prefix: self.mean,
            f"{prefix}_dof": self.dof,
            f"{prefix}_run_ci_lo": self.run_ci.lo,
            f"{prefix}_run_ci_hi": self.run_ci.hi,
            f"{prefix}_step_band_frac": self.step_band_frac,
        }


def _index_list(index: Index, name: str) -> list[int]:
    if index is None:
        raise ValueError(f"{name} must list indices")
    return [int(i) for i in (index.tolist() if isinstance(index, Tensor) else index)]


def block_truth_indices(
    blocks: Mapping[str, Sequence[int]],
    *,
    state_index: Index = None,
    truth_index: Index = None,
    truth_blocks: Mapping[str, Sequence[int]] | None = None,
) -> dict[str, list[int]]:
    """Truth components of every state block.

    ``truth_blocks`` gives them explicitly; otherwise, when the truth and state layouts differ
    (``truth_index[k]`` is the truth component of state component ``state_index[k]``), each
    block's state indices are mapped through that correspondence; otherwise they are the same.
    """
    if truth_blocks is not None:
        missing = set(blocks) - set(truth_blocks)
        if missing:
            raise ValueError(f"truth_blocks must name every block of blocks; missing {sorted(missing)}")
        return {k: _index_list(truth_blocks[k], f"truth_blocks[{k!r}]") for k in blocks}
    if truth_index is None:
        return {k: _index_list(v, f"blocks[{k!r}]") for k, v in blocks.items()}
    states = _index_list(state_index, "state_index (needed with truth_index to map blocks)")
    truths = _index_list(truth_index, "truth_index")
    if len(states) != len(truths):
        raise ValueError(f"state_index and truth_index must have one length, got {len(states)} and {len(truths)}")
    to_truth = dict(zip(states, truths, strict=True))
    out: dict[str, list[int]] = {}
    for k, idx in blocks.items():
        idx = _index_list(idx, f"blocks[{k!r}]")
        unknown = [i for i in idx if i not in to_truth]
        if unknown:
            raise ValueError(f"blocks[{k!r}] uses state components {unknown} that state_index {states} does not compare with the truth")
        out[k] = [to_truth[i] for i in idx]
    return out


def nees_by_block(
    mean: Tensor,
    cov: Tensor,
    truth: Tensor,
    blocks: Mapping[str, Sequence[int]],
    truth_blocks: Mapping[str, Sequence[int]] | None = None,
) -> dict[str, Tensor]:
    """NEES ``[B, T]`` of each block: the error and the covariance restricted to the block's
    state components (NaN where the block's truth is not finite).  ``truth_blocks`` gives the
    truth components of each block (default: the same indices)."""
    if not blocks:
        raise ValueError("blocks must name at least one block {name: indices}")
    out = {}
    for name, idx in blocks.items():
        idx = _index_list(idx, f"blocks[{name!r}]")
        if not idx:
            raise ValueError(f"blocks[{name!r}] is empty")
        tidx = idx if truth_blocks is None else _index_list(truth_blocks[name], f"truth_blocks[{name!r}]")
        out[name] = nees(mean, cov, truth, idx, tidx)
    return out


def nis_per_step(result: FilterResult) -> tuple[Tensor, Tensor]:
    """``(nis [B, T], dof [B, T])``: NIS with NaN at steps without an observed component, and
    the number of observed components of each step."""
    obs = result.num_observed > 0
    nis = torch.where(obs, result.nis, torch.full_like(result.nis, math.nan))
    return nis, result.num_observed.to(result.nis.dtype)


def run_average(values: Tensor) -> Tensor:
    """``[N]`` mean over the finite entries of each run of ``values [N, T]`` (NaN for a run without any)."""
    ok = torch.isfinite(values)
    total = torch.where(ok, values, torch.zeros_like(values)).sum(-1)
    count = ok.sum(-1)
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, math.nan))


def _dof_grid(dof: float | Tensor, like: Tensor) -> Tensor:
    d = torch.as_tensor(dof, dtype=torch.float64)
    if d.ndim not in (0, like.ndim) or (d.ndim and d.shape != like.shape):
        raise ValueError(f"dof must be a number or shaped like the values {tuple(like.shape)}, got {tuple(d.shape)}")
    return d.expand_as(like)


def step_band_fraction(values: Tensor, dof: float | Tensor, prob: float = 0.95) -> float:
    """Fraction of steps whose sum over runs of ``values [N, T]`` lies in the ``prob`` band of
    ``chi2(sum of dof)`` (equivalently: the mean over runs in ``chi2(d N) / N``).

    Only finite entries count, so a step where some runs have no truth (or no measurement) is
    judged on the others; steps with none are left out.  ``dof`` is a number or ``[N, T]``
    (NIS: observed components).  Returns NaN when no step has a finite value.
    """
    if values.ndim != 2:
        raise ValueError(f"values must be [N, T], got shape {tuple(values.shape)}")
    v = values.detach().to("cpu", torch.float64)
    d = _dof_grid(dof, v)
    ok = torch.isfinite(v) & (d > 0)
    sums = torch.where(ok, v, torch.zeros_like(v)).sum(0)
    dofs = torch.where(ok, d, torch.zeros_like(d)).sum(0)
    steps = dofs > 0
    if not bool(steps.any()):
        return math.nan
    tail = 0.5 * (1.0 - prob)
    bands: dict[float, tuple[float, float]] = {}
    inside = 0
    for s, k in zip(sums[steps].tolist(), dofs[steps].tolist(), strict=True):
        if k not in bands:
            bands[k] = (chi2_quantile(tail, k), chi2_quantile(1.0 - tail, k))
        lo, hi = bands[k]
        inside += int(lo <= s <= hi)
    return inside / int(steps.sum())


def consistency(values: Tensor, dof: float | Tensor, prob: float = 0.95) -> Consistency:
    """Run-level mean with its t-interval and the per-step band fraction of ``values [N, T]``
    (NEES of one block, or NIS) with per-step degrees of freedom ``dof`` (number or ``[N, T]``)."""
    if values.ndim != 2:
        raise ValueError(f"values must be [N, T], got shape {tuple(values.shape)}")
    v = values.detach().to("cpu", torch.float64)
    d = _dof_grid(dof, v)
    per_run = run_average(v)
    ok = torch.isfinite(v)
    ref = run_average(torch.where(ok, d, torch.full_like(d, math.nan)))
    ci = t_interval(per_run, prob)
    runs = torch.isfinite(per_run)
    expected = float(ref[runs].mean()) if bool(runs.any()) else math.nan
    return Consistency(
        dof=expected,
        mean=ci.estimate,
        run_ci=ci,
        step_band_frac=step_band_fraction(v, d, prob),
        num_runs=int(runs.sum()),
        num_steps=int(ok.any(0).sum()),
    )
