"""Baselines a practitioner would use instead of learning, built for an experiment's evaluation.

An entry of ``experiment.baselines`` is a filter evaluated beside the hand-tuned and learned
ones.  Without ``tune`` it is evaluated as configured (the paper's own baselines, an adaptive
filter with its textbook hyperparameters, a textbook noise rule).  With ``tune`` it is first
fitted on the experiment's own data, never on the test set:

``tune.method: em``
    maximum likelihood by EM (:func:`difffilter.learn.em.fit_em`) on the *training*
    trajectories, from the hand-tuned values;
``tune.method: grid`` / ``random``
    a validation search (:mod:`difffilter.learn.search`) over one to three named knobs (``grid:
    {name: [values]}`` or ``{name: {low, high, num}}``, log-spaced; a value may be a nested list,
    a whole value per candidate such as an IMM's transition matrix; ``random``: ``bounds: {name:
    [low, high]}``, ``num_samples``, ``seed``), each
    candidate scored on the *validation* trajectories (``score: rmse`` of the position where the
    data have truth, or ``nll`` of the innovations).

::

    baselines:
      em:
        tune: {method: em, learn: [model.dynamics.q, model.measurement.R], num_iters: 20}
      grid-search:
        tune: {method: grid, relative: true, score: rmse,
               grid: {model.measurement.R: [0.25, 1.0, 4.0, 16.0], model.dynamics.q: [0.25, 1.0, 4.0]}}
      sage-husa:
        filter: {_target_: difffilter.filters.SageHusa, inner: ${filter}, b: 0.98}

``tune.trajectories`` (optional) uses only the first so many training (EM) or validation
(search) trajectories: the data-efficiency rows.  Every tuned row reports ``tuning_cpu_s``, the
process CPU seconds its tuning took; the learned row reports its training's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

import torch

from difffilter.filters.protocol import Filter
from difffilter.learn.data import TrajectorySet
from difffilter.learn.em import fit_em
from difffilter.learn.search import grid_search, log_grid, random_search, validation_loss

__all__ = ["TUNE_METHODS", "tune_baseline"]

log = logging.getLogger(__name__)

TUNE_METHODS = ("em", "grid", "random")
_TUNE_KEYS = {
    "em": {"method", "learn", "num_iters", "tol", "trajectories", "time_chunk"},
    "grid": {"method", "grid", "relative", "score", "trajectories"},
    "random": {"method", "bounds", "relative", "score", "trajectories", "num_samples", "seed"},
}


def _subset(data: TrajectorySet, count: Any, key: str) -> dict[str, Any]:
    """The first ``count`` trajectories of ``data`` (all when ``count`` is None) as a batch dict."""
    if count is None:
        return data.all()
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ValueError(f"{key} must be a positive integer or null, got {count!r}")
    if count > len(data):
        raise ValueError(f"{key} = {count} but the data have only {len(data)} trajectories")
    return data.batch(torch.arange(count))


def _belief(batch: Mapping[str, Any], mean: torch.Tensor, cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The data's own initial belief when the simulator gives one, else the learner's."""
    if batch["initial_mean"] is not None and batch["initial_cov"] is not None:
        return batch["initial_mean"], batch["initial_cov"]
    return mean, cov


def _grid(spec: Any, key: str) -> dict[str, list[Any]]:
    if not isinstance(spec, Mapping) or not 1 <= len(spec) <= 3:
        raise ValueError(f"{key} must map one to three parameter names to their values, got {spec!r}")
    out = {}
    for name, values in spec.items():
        if isinstance(values, Mapping):  # {low, high, num}: a log-spaced grid
            missing = {"low", "high", "num"} - set(values)
            if missing:
                raise ValueError(f"{key}.{name} as a range needs low, high and num; missing {sorted(missing)}")
            low, high, num = float(values["low"]), float(values["high"]), int(values["num"])
            if not (0 < low < high and num >= 2):
                raise ValueError(f"{key}.{name} must have 0 < low < high and num >= 2, got {dict(values)}")
            values = log_grid(low, high, num)
        # a nested list is a whole value per candidate (e.g. an IMM's transition matrix), kept as given
        out[str(name)] = [v if isinstance(v, list | tuple) else float(v) for v in values]
    return out


def _show(value: Any) -> str:
    """A chosen knob value in short: ``4.2`` or a nested list with 4 significant digits."""
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return f"{value:.4g}"


def _bounds(spec: Any, key: str) -> dict[str, tuple[float, float]]:
    if not isinstance(spec, Mapping) or not 1 <= len(spec) <= 3:
        raise ValueError(f"{key} must map one to three parameter names to [low, high], got {spec!r}")
    out = {}
    for name, pair in spec.items():
        if not isinstance(pair, list | tuple) or len(pair) != 2 or not 0 < float(pair[0]) < float(pair[1]):
            raise ValueError(f"{key}.{name} must be [low, high] with 0 < low < high, got {pair!r}")
        out[str(name)] = (float(pair[0]), float(pair[1]))
    return out


def tune_baseline(
    filt: Filter,
    tune: Mapping[str, Any],
    *,
    name: str,
    train: TrajectorySet,
    val: TrajectorySet,
    initial_mean: torch.Tensor,
    initial_cov: torch.Tensor,
    position_index: list[int] | None = None,
    truth_position_index: list[int] | None = None,
) -> dict[str, Any]:
    """Fit ``filt`` in place as ``tune`` says (module docstring); returns the row's extra columns
    (``tuning_cpu_s``, ``tuning``: a short description of what was chosen)."""
    key = f"experiment.baselines.{name}.tune"
    method = tune.get("method")
    if method not in TUNE_METHODS:
        raise ValueError(f"{key}.method must be one of {TUNE_METHODS}, got {method!r}")
    unknown = set(tune) - _TUNE_KEYS[method]
    if unknown:
        raise ValueError(f"{key} has unknown keys {sorted(unknown)} for method {method!r}; allowed: {sorted(_TUNE_KEYS[method])}")
    start = time.process_time()
    if method == "em":
        data = _subset(train, tune.get("trajectories"), f"{key}.trajectories")
        mean, cov = _belief(data, initial_mean, initial_cov)
        num_iters = tune.get("num_iters", 20)
        if not isinstance(num_iters, int) or num_iters < 1:
            raise ValueError(f"{key}.num_iters must be a positive integer, got {num_iters!r}")
        result = fit_em(
            filt,  # type: ignore[arg-type]  # fit_em refuses what it cannot fit, naming it
            data["measurements"],
            mean,
            cov,
            data["mask"],
            data["controls"],
            num_iters=num_iters,
            learn=tune.get("learn"),
            tol=float(tune.get("tol", 1e-8)),
            time_chunk=tune.get("time_chunk"),
        )
        ll = result.log_likelihoods
        what = f"EM {result.num_iters} it on {len(data['measurements'])} train traj, loglik {ll[0]:.6g} -> {ll[-1]:.6g}"
        if not result.monotone:  # an approximate E-step lowered it somewhere: say which iterate is kept
            what += f" (not monotone; kept iterate {result.best_iteration}, loglik {ll[result.best_iteration]:.6g})"
    else:
        data = _subset(val, tune.get("trajectories"), f"{key}.trajectories")
        mean, cov = _belief(data, initial_mean, initial_cov)
        kind = tune.get("score", "rmse" if data["truth"] is not None else "nll")
        score = validation_loss(
            data["measurements"],
            mean,
            cov,
            truth=data["truth"],
            mask=data["mask"],
            controls=data["controls"],
            kind=kind,
            index=position_index,
            truth_index=truth_position_index if truth_position_index is not None else position_index,
        )
        relative = bool(tune.get("relative", False))
        if method == "grid":
            found = grid_search(filt, _grid(tune.get("grid"), f"{key}.grid"), score, relative=relative)
        else:
            bounds = _bounds(tune.get("bounds"), f"{key}.bounds")
            draws = {"num_samples": int(tune.get("num_samples", 16)), "seed": int(tune.get("seed", 0))}
            found = random_search(filt, bounds, score, relative=relative, **draws)
        chosen = ", ".join(f"{k}={_show(v)}" for k, v in found.best.items())
        what = f"{method} search over {len(found.table)} candidates on {len(data['measurements'])} val traj ({kind}): {chosen}"
    cpu = time.process_time() - start
    log.info("baseline %s tuned in %.1f CPU-s: %s", name, cpu, what)
    return {"tuning_cpu_s": cpu, "tuning": what}
