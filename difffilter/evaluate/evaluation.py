"""Evaluating a filter on held-out test runs: pooled metrics, per-run metrics and consistency.

The evaluation protocol every experiment follows (see also :mod:`difffilter.evaluate.intervals`
and :mod:`experiments.runner.sweep`):

* **filters** - *hand-tuned* (the paper's own filter and values), *learned* (trained from
  several seeds: data and initialisation), *oracle* (the true parameters, where the truth is in
  the filter's family) and baselines, all run on the **same test runs**;
* **per-run metrics** - :func:`evaluate_runs` returns, besides the pooled table row, one value
  per test run and filter (``rmse_pos``, ``anees``, ``nis``, ``nll``, per-block NEES...);
  :func:`write_per_run` stores them as ``per_run.csv`` in the run directory so that the runs of
  several filters and seeds can be paired later;
* **paired comparisons** - differences of per-run metrics between filters on the same runs,
  with intervals over runs and seeds (:func:`~difffilter.evaluate.intervals.crossed_interval`),
  and the gap closed ``G = (e_hand - e_learned) / (e_hand - e_oracle)``
  (:func:`~difffilter.evaluate.intervals.gap_closed`);
* **consistency** - NEES per state block and NIS with the per-step chi-square band over runs and
  the run-level t-interval (:mod:`difffilter.evaluate.consistency`); never a band from runs x steps.

Columns of the summary row (the experiment's ``results.csv``): ``rmse_pos``, ``rmse_state``
(pooled over every run and step), ``nll``, ``time_per_step_ms``; ``anees`` (NEES of the compared
state) and ``nis`` as run-level means, each with ``*_dof`` (the value of a consistent filter),
``*_run_ci_lo/hi`` (95 % t-interval over runs) and ``*_step_band_frac`` (fraction of steps whose
mean over runs lies in the per-step chi-square band); for each state block ``b`` the same as
``nees_<b>``, ``nees_<b>_dof``, ``nees_<b>_run_ci_lo/hi``, ``nees_<b>_step_band_frac``.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .. import linalg
from ..filters.protocol import Filter, FilterResult
from ..smoothers import Smoother
from .consistency import Consistency, block_truth_indices, consistency, nees_by_block, nis_per_step, run_average
from .metrics import component_error, finalize_metrics, metric_sums, nees, nll_per_step

__all__ = [
    "EXTRA_TESTS_DIR",
    "PER_RUN_FILE",
    "Evaluation",
    "consistency_table",
    "evaluate_runs",
    "evaluate_filter",
    "per_run_metrics",
    "read_per_run",
    "write_per_run",
]

PER_RUN_FILE = "per_run.csv"
#: Subdirectory of a run directory holding one directory per extra test set (``experiment.extra_tests``).
EXTRA_TESTS_DIR = "extra_tests"

Indices = Sequence[int] | None
Blocks = Mapping[str, Sequence[int]]


@dataclass
class Evaluation:
    """One filter on one test set.

    Attributes:
        summary: the pooled table row (module docstring for its columns).
        per_run: ``{metric: [N]}`` float64 values per test run (``rmse_pos``, ``mse_pos``,
            ``rmse_state``, ``rmse_<block>``, ``anees``, ``nees_<block>``, ``nis``, ``nis_dof``,
            ``nll``, ``steps``).
        consistency: ``{"nees": ..., "nees_<block>": ..., "nis": ...}``.
    """

    summary: dict[str, float]
    per_run: dict[str, Tensor]
    consistency: dict[str, Consistency]


def _errors_per_run(estimate: Tensor, truth: Tensor, index: Indices, truth_index: Indices) -> tuple[Tensor, Tensor]:
    err, valid = component_error(estimate, truth, index, truth_index)
    sq = (err * err).sum(-1).to(torch.float64)
    count = valid.sum(-1)
    mean_sq = torch.where(count > 0, sq.sum(-1) / count.clamp_min(1), torch.full_like(sq[:, 0], math.nan))
    return mean_sq, count.to(torch.float64)


def per_run_metrics(
    result: FilterResult,
    truth: Tensor | None,
    *,
    position_index: Indices = None,
    truth_position_index: Indices = None,
    state_index: Indices = None,
    truth_index: Indices = None,
    blocks: Blocks | None = None,
    truth_blocks: Blocks | None = None,
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """Per-run metrics ``{name: [B]}`` of one batch and the per-step series ``{name: [B, T]}``
    the consistency statistics need (``nees``, ``nees_<block>``, ``nis``, ``nis_dof``).

    ``rmse_pos`` of a run is ``sqrt(mean_t ||e_t||^2)`` over its steps with a truth (``mse_pos``
    its square; ``rmse_<block>`` the same for each state block); ``anees``/``nees_<block>``/``nis``
    are time averages of the run; ``nll`` is the negative log-likelihood per observed step.  Index
    arguments as :func:`metric_sums`; blocks as :func:`~difffilter.evaluate.consistency.block_truth_indices`.
    """
    nis, nis_dof = nis_per_step(result)
    runs: dict[str, Tensor] = {"nis": run_average(nis), "nis_dof": run_average(torch.where(torch.isfinite(nis), nis_dof, nis))}
    runs["nll"] = nll_per_step(result).to(torch.float64)
    steps: dict[str, Tensor] = {"nis": nis, "nis_dof": nis_dof}
    if truth is not None:
        pos_idx = position_index if position_index is not None else state_index
        pos_tidx = truth_position_index if position_index is not None else truth_index
        mse_pos, count = _errors_per_run(result.mean, truth, pos_idx, pos_tidx)
        mse_state, _ = _errors_per_run(result.mean, truth, state_index, truth_index)
        runs.update(mse_pos=mse_pos, rmse_pos=mse_pos.sqrt(), rmse_state=mse_state.sqrt(), steps=count)
        steps["nees"] = nees(result.mean, result.cov, truth, state_index, truth_index)
        if blocks:
            tblocks = block_truth_indices(blocks, state_index=state_index, truth_index=truth_index, truth_blocks=truth_blocks)
            for name, value in nees_by_block(result.mean, result.cov, truth, blocks, tblocks).items():
                steps[f"nees_{name}"] = value
                runs[f"rmse_{name}"] = _errors_per_run(result.mean, truth, blocks[name], tblocks[name])[0].sqrt()
        for key in [k for k in steps if k.startswith("nees")]:
            runs["anees" if key == "nees" else key] = run_average(steps[key])
    return {k: v.detach().to("cpu", torch.float64) for k, v in runs.items()}, {
        k: v.detach().to("cpu", torch.float64) for k, v in steps.items()
    }


@torch.no_grad()
def evaluate_runs(
    filt: Filter,
    data: Any,
    *,
    initial_mean: Tensor | None = None,
    initial_cov: Tensor | None = None,
    batch_size: int | None = None,
    max_jitter: float | None = None,
    position_index: Indices = None,
    truth_position_index: Indices = None,
    state_index: Indices = None,
    truth_index: Indices = None,
    error_quantiles: Sequence[float] | None = None,
    blocks: Blocks | None = None,
    truth_blocks: Blocks | None = None,
    prob: float = 0.95,
    smoother: Smoother | None = None,
) -> Evaluation:
    """Run ``filt`` on every trajectory of ``data`` (a :class:`~difffilter.learn.data.TrajectorySet`)
    and evaluate it: pooled row, per-run metrics and consistency (module docstring).

    ``time_per_step_ms`` is the wall time of one filter step on a batch of ``batch_size``
    trajectories (default: all at once); ``pos_err_p{100 q}`` for each ``q`` of
    ``error_quantiles`` the ``q``-quantile of the position error norm over all steps with a truth.
    ``blocks`` (``{name: state indices}``) adds per-block NEES; ``prob`` is the coverage of the
    consistency bands and intervals.  With a ``smoother`` (built on ``filt``) every metric but
    ``nis``/``nll`` (the filter's innovations) is that of the smoothed states, and the time
    includes the smoother.
    """
    n = len(data)
    size = batch_size or n
    sums: dict[str, Tensor] = {}
    elapsed, batches, dim = 0.0, 0, 0
    norms: list[Tensor] = []
    runs: dict[str, list[Tensor]] = {}
    steps: dict[str, list[Tensor]] = {}
    idx = {
        "position_index": position_index,
        "truth_position_index": truth_position_index,
        "state_index": state_index,
        "truth_index": truth_index,
    }
    for first in range(0, n, size):
        batch = data.batch(torch.arange(first, min(first + size, n)))
        mean0 = batch["initial_mean"] if batch["initial_mean"] is not None else initial_mean
        cov0 = batch["initial_cov"] if batch["initial_cov"] is not None else initial_cov
        if mean0 is None or cov0 is None:
            raise ValueError("no initial belief: the data carries none and none was given")
        tic = time.perf_counter()
        with linalg.jitter_bound(max_jitter):
            res = filt(batch["measurements"], mean0, cov0, mask=batch["mask"], controls=batch["controls"])
            if smoother is not None:
                start = smoother.initial_belief(batch["measurements"], mean0, cov0, None)
                res = smoother.smooth(res, start, batch["controls"])
        elapsed += time.perf_counter() - tic
        batches += 1
        dim = len(state_index) if state_index is not None else res.mean.shape[-1]
        truth = batch["truth"]
        if error_quantiles and truth is not None:
            pos_idx = position_index if position_index is not None else state_index
            pos_tidx = truth_position_index if position_index is not None else truth_index
            err, valid = component_error(res.mean, truth, pos_idx, pos_tidx)
            norms.append(torch.linalg.vector_norm(err, dim=-1)[valid].to(torch.float64))
        for k, v in metric_sums(res, truth, **idx).items():
            sums[k] = sums.get(k, torch.zeros((), dtype=torch.float64)) + v.to("cpu")
        per_run, per_step = per_run_metrics(res, truth, **idx, blocks=blocks, truth_blocks=truth_blocks)
        for k, v in per_run.items():
            runs.setdefault(k, []).append(v)
        for k, v in per_step.items():
            steps.setdefault(k, []).append(v)
    out = finalize_metrics(sums)
    out["time_per_step_ms"] = 1e3 * elapsed / (batches * data.num_steps)
    if norms and sum(v.numel() for v in norms) > 0:
        all_norms = torch.cat(norms)
        for q in error_quantiles or []:
            out[f"pos_err_p{100 * float(q):g}"] = float(torch.quantile(all_norms, float(q)))
    series = {k: torch.cat(v) for k, v in steps.items()}
    checks: dict[str, Consistency] = {"nis": consistency(series["nis"], series["nis_dof"], prob)}
    for key in [k for k in series if k.startswith("nees")]:
        d = len(blocks[key.removeprefix("nees_")]) if blocks and key != "nees" else dim
        checks[key] = consistency(series[key], float(d), prob)
    for key, c in checks.items():
        out.update(c.as_row("anees" if key == "nees" else key))
    return Evaluation(out, {k: torch.cat(v) for k, v in runs.items()}, checks)


def write_per_run(per_run: Mapping[str, Mapping[str, Tensor]], path: str | Path) -> Path:
    """Write ``{filter: {metric: [N]}}`` as a CSV with columns ``filter, run, <metrics>``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metrics = list(dict.fromkeys(m for values in per_run.values() for m in values))  # first-seen order: blocks as configured
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["filter", "run", *metrics])
        for name, values in per_run.items():
            count = max((int(v.numel()) for v in values.values()), default=0)
            for r in range(count):
                cells = [repr(float(values[m][r])) if m in values else "" for m in metrics]
                writer.writerow([name, r, *cells])
    return path


def read_per_run(path: str | Path) -> dict[str, dict[str, Tensor]]:
    """Read :func:`write_per_run`'s CSV back: ``{filter: {metric: [N] float64}}`` ordered by run."""
    out: dict[str, dict[str, list[tuple[int, float]]]] = {}
    with Path(path).open(newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not {"filter", "run"} <= set(reader.fieldnames):
            raise ValueError(f"{path} is not a per-run CSV (columns filter, run, ...)")
        for row in reader:
            slot = out.setdefault(row["filter"], {})
            for k, v in row.items():
                if k not in ("filter", "run") and v != "":
                    slot.setdefault(k, []).append((int(row["run"]), float(v)))
    return {f: {k: torch.tensor([v for _, v in sorted(vals)], dtype=torch.float64) for k, vals in m.items()} for f, m in out.items()}


def consistency_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A markdown table of every row's consistency: for NEES (all compared states), each block
    and NIS, ``mean [run CI] (dof) step-band fraction`` (empty when the row has none)."""
    present = {k for r in rows for k in r}
    blocks = list(dict.fromkeys(k for r in rows for k in r if k.startswith("nees_") and f"{k}_dof" in r))
    keys = [k for k in ("anees", *blocks, "nis") if k in present]
    if not keys:
        return ""

    def cell(r: Mapping[str, Any], k: str) -> str:
        if k not in r or not isinstance(r[k], float) or math.isnan(r[k]):
            return ""
        lo, hi, d, frac = (r.get(f"{k}_{s}", math.nan) for s in ("run_ci_lo", "run_ci_hi", "dof", "step_band_frac"))
        verdict = "in" if lo <= d <= hi else ("out" if math.isfinite(lo) else "")
        return f"{r[k]:.4g} [{lo:.4g}, {hi:.4g}] (d = {d:.3g}) {verdict}; {100 * frac:.0f} % steps in band"

    names = {"anees": "NEES (all)", "nis": "NIS"}
    lines = ["| filter | " + " | ".join(names.get(k, k.removeprefix("nees_")) for k in keys) + " |", "|---|" + "---|" * len(keys)]
    lines += ["| " + " | ".join([str(r.get("filter", "")), *(cell(r, k) for k in keys)]) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def evaluate_filter(
    filt: Filter,
    data: Any,
    *,
    initial_mean: Tensor | None = None,
    initial_cov: Tensor | None = None,
    batch_size: int | None = None,
    max_jitter: float | None = None,
    position_index: Indices = None,
    truth_position_index: Indices = None,
    state_index: Indices = None,
    truth_index: Indices = None,
    error_quantiles: Sequence[float] | None = None,
    blocks: Blocks | None = None,
    truth_blocks: Blocks | None = None,
    smoother: Smoother | None = None,
) -> dict[str, float]:
    """The pooled results row of ``filt`` on every trajectory of ``data``: the ``summary`` of
    :func:`difffilter.evaluate.evaluation.evaluate_runs` (same arguments; its per-run metrics too;
    with a ``smoother`` built on ``filt``, of the smoothed states)."""
    return evaluate_runs(
        filt,
        data,
        initial_mean=initial_mean,
        initial_cov=initial_cov,
        batch_size=batch_size,
        max_jitter=max_jitter,
        position_index=position_index,
        truth_position_index=truth_position_index,
        state_index=state_index,
        truth_index=truth_index,
        error_quantiles=error_quantiles,
        blocks=blocks,
        truth_blocks=truth_blocks,
        smoother=smoother,
    ).summary
