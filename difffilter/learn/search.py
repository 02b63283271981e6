"""Validation search over a few named knobs: the tuning a practitioner does instead of learning.

Each candidate sets one to three constrained parameters by name (the names of
:func:`~difffilter.selection.match_parameters`: ``"R"``, ``"Q"``, ``"tau"``,
``"model.measurement.R"``...), runs the filter on held-out trajectories and scores it with a
validation loss (:func:`validation_loss`: state RMSE against the truth, or the innovation
negative log-likelihood, which needs no truth).  :func:`grid_search` tries every combination of
the given values (log grids from :func:`log_grid`); :func:`random_search` draws candidates
log-uniformly in given bounds from a seeded generator.  Both are deterministic, return the best
values, the table of all candidates and the process CPU seconds spent (the tuning cost), and
leave the filter with the best values (or its original ones, ``apply_best=False``).

A scalar value ``s`` sets a square-matrix parameter to ``s I`` (or the scale of a ``"scalar"``
structure, :func:`~difffilter.selection.assign_parameters`); ``relative=True`` multiplies the
parameter's starting value instead (``R = s R_0``), which keeps a tuned shape and searches its
level.  A grid value may also be a whole value (a nested list, e.g. one transition matrix per
candidate): it is set as given, also under ``relative=True`` (which scales numbers only).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from ..evaluate.metrics import Index, rmse
from ..filters.protocol import Filter
from ..models.base import Controls
from ..selection import assign_parameters, match_parameters, parameter_owners

__all__ = ["SearchResult", "grid_search", "log_grid", "random_search", "validation_loss"]

Score = Callable[[Filter], float]


@dataclass
class SearchResult:
    """Outcome of a search.

    Attributes:
        best: the best candidate's knob values ``{knob: value}`` (a float, or a nested list where
            the grid gave whole values).
        best_score: its validation loss (lower is better).
        table: every candidate in the order tried, ``{knob: value, ..., "score": loss}``.
        cpu_seconds: process CPU time of the whole search (the tuning cost).
        method: ``"grid"`` or ``"random"``.
        values: the constrained values the best candidate set ``{dotted name: tensor}``.
    """

    best: dict[str, Any]
    best_score: float
    table: list[dict[str, Any]]
    cpu_seconds: float
    method: str
    values: dict[str, Tensor] = field(default_factory=dict)


def log_grid(low: float, high: float, num: int) -> list[float]:
    """``num`` values from ``low`` to ``high`` (both included) equally spaced in log scale."""
    if not (low > 0 and high > 0 and math.isfinite(low) and math.isfinite(high)):
        raise ValueError(f"log_grid needs finite low, high > 0, got {low}, {high}")
    if int(num) < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    if num == 1:
        return [float(low)]
    a, b = math.log(low), math.log(high)
    return [math.exp(a + (b - a) * i / (num - 1)) for i in range(int(num))]


def validation_loss(
    measurements: Tensor,
    initial_mean: Tensor,
    initial_cov: Tensor,
    *,
    truth: Tensor | None = None,
    mask: Tensor | None = None,
    controls: Controls = None,
    kind: str = "rmse",
    index: Index = None,
    truth_index: Index = None,
) -> Score:
    """A score ``filter -> float`` on held-out trajectories (lower is better).

    Args:
        measurements: ``[B, T, m]`` validation trajectories.
        initial_mean, initial_cov: their initial belief (as for the filter).
        truth: ``[B, T, n_t]`` true states (needed by ``kind="rmse"``; NaN entries are skipped).
        mask, controls: as for the filter.
        kind: ``"rmse"`` (of the filtered means' components ``index`` against ``truth_index``
            of the truth, e.g. the position) or ``"nll"`` (innovation negative log-likelihood
            per observed step, averaged over trajectories).
        index, truth_index: components for ``"rmse"`` (see :func:`~difffilter.evaluate.metrics.rmse`).
    """
    if kind not in ("rmse", "nll"):
        raise ValueError(f"kind must be 'rmse' or 'nll', got {kind!r}")
    if kind == "rmse" and truth is None:
        raise ValueError("kind='rmse' needs truth= (the validation trajectories' true states)")

    @torch.no_grad()
    def score(filt: Filter) -> float:
        res = filt(measurements, initial_mean, initial_cov, mask=mask, controls=controls)
        if kind == "rmse":
            assert truth is not None
            return float(rmse(res.mean, truth, index, truth_index))
        steps = (res.num_observed > 0).sum().clamp_min(1)
        return float(-res.log_likelihood.sum() / steps)

    return score


def _check_knobs(filt: nn.Module, names: Sequence[str]) -> dict[str, list[str]]:
    if not 1 <= len(names) <= 3:
        raise ValueError(f"knobs: search one to three named knobs, got {len(names)}: {list(names)}")
    try:
        return match_parameters(filt, names)
    except ValueError as exc:
        raise ValueError(f"knobs: {exc}") from exc


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _run(
    filt: Filter,
    candidates: list[dict[str, Any]],
    score: Score,
    hits: dict[str, list[str]],
    relative: bool,
    apply_best: bool,
    method: str,
    start: float,
) -> SearchResult:
    owners = parameter_owners(filt)
    dotted = [n for names in hits.values() for n in names]
    original = {n: getattr(owners[n][0], owners[n][1]).detach().clone() for n in dotted}

    def setting(cand: Mapping[str, Any]) -> dict[str, Any]:
        if not relative:
            return dict(cand)
        # a whole value (nested list) is set as given; a number scales the starting value
        return {n: original[n] * float(cand[k]) if _is_number(cand[k]) else cand[k] for k, names in hits.items() for n in names}

    table: list[dict[str, Any]] = []
    best_i, best_s = -1, math.inf
    try:
        for i, cand in enumerate(candidates):
            assign_parameters(filt, setting(cand))
            with torch.no_grad():
                s = float(score(filt))
            s = s if math.isfinite(s) else math.inf
            table.append({**cand, "score": s})
            if s < best_s:
                best_i, best_s = i, s
    finally:
        assign_parameters(filt, original)
    if best_i < 0:
        raise ValueError("no candidate gave a finite validation loss")
    best = candidates[best_i]
    assign_parameters(filt, setting(best))
    values = {n: getattr(owners[n][0], owners[n][1]).detach().clone() for n in dotted}
    if not apply_best:
        assign_parameters(filt, original)
    return SearchResult(
        best=dict(best), best_score=best_s, table=table, cpu_seconds=time.process_time() - start, method=method, values=values
    )


def _finite_value(value: Any) -> bool:
    """A finite number, or a non-empty nested list/tuple of finite numbers."""
    if _is_number(value):
        return math.isfinite(value)
    if not isinstance(value, list | tuple) or not value:
        return False
    try:
        return bool(torch.isfinite(torch.as_tensor(value, dtype=torch.float64)).all())
    except (TypeError, ValueError, RuntimeError):
        return False


def grid_search(
    filt: Filter, grid: Mapping[str, Sequence[Any]], score: Score, *, relative: bool = False, apply_best: bool = True
) -> SearchResult:
    """Try every combination of ``grid`` (``{knob: values}``, one to three knobs) and keep the best.

    A value is a number (under ``relative=True`` a factor on the starting value) or a whole value
    as a nested list of numbers (set as given, e.g. a transition matrix).  Candidates run in the
    order of ``itertools.product`` over the knobs as given; ties keep the first.  ``score``
    is called on ``filt`` with each candidate set (e.g. :func:`validation_loss`).
    """
    start = time.process_time()
    names = list(grid)
    hits = _check_knobs(filt, names)
    for k, vals in grid.items():
        if len(vals) < 1 or not all(_finite_value(v) for v in vals):
            raise ValueError(f"grid[{k!r}] must be a non-empty sequence of finite numbers (or nested lists of them), got {vals!r}")
    candidates = [
        dict(zip(names, (float(v) if _is_number(v) else v for v in combo), strict=True)) for combo in itertools.product(*grid.values())
    ]
    return _run(filt, candidates, score, hits, relative, apply_best, "grid", start)


def random_search(
    filt: Filter,
    bounds: Mapping[str, tuple[float, float]],
    score: Score,
    *,
    num_samples: int = 20,
    seed: int = 0,
    relative: bool = False,
    apply_best: bool = True,
) -> SearchResult:
    """``num_samples`` candidates drawn log-uniformly in ``bounds`` (``{knob: (low, high)}``,
    positive) from a generator seeded with ``seed`` (the same seed, the same candidates)."""
    start = time.process_time()
    names = list(bounds)
    hits = _check_knobs(filt, names)
    if int(num_samples) < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    for k, lh in bounds.items():
        if len(lh) != 2 or not (0 < lh[0] <= lh[1] < math.inf):
            raise ValueError(f"bounds[{k!r}] must be (low, high) with 0 < low <= high, got {lh!r}")
    gen = torch.Generator().manual_seed(int(seed))
    u = torch.rand(int(num_samples), len(names), generator=gen, dtype=torch.float64)
    lows = torch.tensor([math.log(bounds[k][0]) for k in names], dtype=torch.float64)
    highs = torch.tensor([math.log(bounds[k][1]) for k in names], dtype=torch.float64)
    draws = torch.exp(lows + (highs - lows) * u)
    candidates = [dict(zip(names, row.tolist(), strict=True)) for row in draws]
    return _run(filt, candidates, score, hits, relative, apply_best, "random", start)
