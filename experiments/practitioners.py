"""Summary of a practitioners sweep (issue 25, ``results/p00_practitioners.md``).

``python -m experiments.practitioners <sweep_dir>`` writes the sweep's ``summary.md`` /
``summary.csv`` (:func:`experiments.runner.sweep.summarize_sweep`: every filter against the
paper's constants, ``hand-tuned``) and adds to ``summary.csv``, per test set (group):

* the paired difference learned - *best non-learned* (``diff`` and ``diff_pct`` rows of
  ``learned`` whose ``reference`` names the best), where the best is the lowest mean test RMSE
  among the non-learned methods of :data:`experiments.results_report.METHODS` that ran, the rule
  pre-declared in ``results/p00_practitioners.md``; the interval is over seeds x runs when the
  seeds share their test runs (the paper's constants then give the same per-run values in every
  seed), else over seed means, as the sweep's own differences;
* ``tuning_cpu_s`` of every row that reports one (mean over seeds in ``estimate``, min and max in
  ``lo``/``hi``): the CPU seconds of its tuning, the learned row's training.

``results/REPORT.md`` reads both (:func:`experiments.results_report.summary_cells`).
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from typing import Any  # noqa: E402

import torch  # noqa: E402

from experiments.results_report import METHODS, REFERENCE  # noqa: E402
from experiments.results_tables import FIELDS  # noqa: E402
from experiments.runner.sweep import Job, _interval, _matrix, load_jobs, summarize_sweep  # noqa: E402

__all__ = ["best_non_learned", "main", "summarize_practitioners"]

LEARNED = "learned"


def best_non_learned(rows: Sequence[dict[str, Any]], group: str, metric: str = "rmse_pos") -> str | None:
    """The non-learned method (a filter name of ``METHODS``) with the lowest mean ``metric`` in
    ``group`` of a summary's rows, None when none ran."""
    means = {
        r["filter"]: float(r["estimate"])
        for r in rows
        if r["group"] == group and r["quantity"] == metric and not r["reference"] and r["filter"] in {n for _, n in METHODS}
    }
    return min(means, key=lambda n: means[n]) if means else None


def _tuning_rows(jobs: Sequence[Job], group: str) -> list[dict[str, Any]]:
    out = []
    names = list(dict.fromkeys(f for j in jobs for f in j.results))
    for name in names:
        values = [float(v) for j in jobs if (v := j.results.get(name, {}).get("tuning_cpu_s")) not in (None, "", "nan")]
        values = [v for v in values if math.isfinite(v)]
        if values:
            row = {"group": group, "filter": name, "quantity": "tuning_cpu_s", "estimate": sum(values) / len(values)}
            out.append({**row, "lo": min(values), "hi": max(values), "seeds": len(values), "runs": "", "reference": ""})
    return out


def summarize_practitioners(sweep_dir: str | Path, *, metric: str = "rmse_pos", prob: float = 0.95) -> Path:
    """Summarise ``sweep_dir`` (module docstring); returns the ``summary.csv`` path."""
    _, path = summarize_sweep(sweep_dir, metric=metric, reference=REFERENCE, prob=prob)
    with path.open(newline="") as fh:
        rows: list[dict[str, Any]] = list(csv.DictReader(fh))
    jobs = load_jobs(sweep_dir)
    extra: list[dict[str, Any]] = []
    for group in dict.fromkeys(j.group for j in jobs):
        gjobs = [j for j in jobs if j.group == group]
        extra += _tuning_rows(gjobs, group)
        best = best_non_learned(rows, group, metric)
        learned = _matrix(gjobs, LEARNED, metric)
        if best is None or best == REFERENCE or learned is None:
            continue  # against the paper's constants the sweep's own diff rows are the paired ones
        ref, hand = _matrix(gjobs, best, metric), _matrix(gjobs, REFERENCE, metric)
        if ref is None:
            continue
        # the seeds share their test runs when the paper's constants give the same per-run values
        crossed = hand is not None and bool(torch.allclose(hand, hand[:1].expand_as(hand), rtol=1e-12, atol=0.0, equal_nan=True))
        diff = _interval(learned - ref, crossed, prob)
        base = float(ref[torch.isfinite(ref)].mean())
        common = {"group": group, "filter": LEARNED, "seeds": learned.shape[0], "runs": learned.shape[1], "reference": best}
        for qty, iv in (("diff", diff), ("diff_pct", diff.scaled(100.0 / base))):
            extra.append({**common, "quantity": qty, "estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi})
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(FIELDS))
        writer.writeheader()
        writer.writerows(rows + extra)
    return path


def main(argv: Sequence[str] | None = None) -> Path:
    """Command line: ``python -m experiments.practitioners <sweep_dir> [--metric rmse_pos]``."""
    ap = argparse.ArgumentParser(description="Summarise a practitioners sweep: paired learned - best non-learned, tuning CPU.")
    ap.add_argument("sweep_dir")
    ap.add_argument("--metric", default="rmse_pos")
    args = ap.parse_args(argv)
    path = summarize_practitioners(args.sweep_dir, metric=args.metric)
    print(path.read_text())
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
