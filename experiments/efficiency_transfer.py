"""Data-efficiency and transfer summaries (issue 25, ``results/p00_efficiency_transfer.md``).

    python -m experiments.efficiency_transfer efficiency outputs/efficiency/p002_pdr --select test=pdr-P0.4 \
        --out results/data/p002_pdr_efficiency.csv
    python -m experiments.efficiency_transfer transfer --root outputs --out results/data/p002_transfer.csv

**Efficiency**: a sweep over ``data.train_size`` and seeds gives one group per training size
(``N=<size>``): every row's metric (mean over seeds x test runs [95 %]) and its tuning CPU seconds,
and two paired differences, in % of the reference's mean: ``learned`` - the best non-learned row,
and ``em`` - the best of the *other* non-learned rows.  The best non-learned row is the one with the
lowest mean test metric among the rows that are neither learned nor given the truth
(:data:`NOT_BASELINES`), the rule pre-declared in the results file.

**Transfer**: for each pair of :data:`P002_PAIRS`, the target family's test set as seen by two
sweeps: the source's (its extra test set) and the target's own.  Rows: the paper's constants, the
model learned on the target, the model learned on the source (the transfer row), the target's best
non-learned row, and the source's tuned rows; paired: transfer - learned on target, transfer -
the target's best non-learned, transfer - the paper's constants, and (the target's own verdict)
learned on target - the target's best non-learned.  The two sweeps must have tested
on the same runs: a pair whose paper's-constants per-run values differ is refused.

Both write data files in the schema of a sweep's ``summary.csv``
(:data:`experiments.results_tables.FIELDS`), which ``renderer=paired`` tables show.  Intervals as
the sweeps': over seeds x runs when the seeds share their test runs, else over seed means.
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
from dataclasses import dataclass  # noqa: E402
from typing import Any  # noqa: E402

import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from experiments.results_tables import FIELDS  # noqa: E402
from experiments.runner.sweep import Job, _interval, _matrix, load_jobs  # noqa: E402

__all__ = ["DATA_FILES", "NOT_BASELINES", "P002_PAIRS", "Pair", "best_baseline", "main", "summarize_efficiency", "summarize_transfer"]

REFERENCE, LEARNED, EM = "hand-tuned", "learned", "em"
#: Rows that are not a practitioner's non-learned alternative: trained, or given the truth.
NOT_BASELINES = frozenset({LEARNED, "learned-adaptive", "oracle", "exact UKF"})
#: Rows of a source sweep shown on a target's test set as tuned on the source.
SOURCE_TUNED = ("validation-search", EM)


#: The summaries ``experiments/reproduce.py`` writes into the output folders and the data files of
#: ``results/`` they become (``python experiments/report.py --collect`` copies them).
DATA_FILES = (
    ("outputs/efficiency/p002_pdr/efficiency.csv", "results/data/p002_pdr_efficiency.csv"),
    ("outputs/efficiency/p000_infamily/efficiency.csv", "results/data/p000_infamily_efficiency.csv"),
    ("outputs/transfer/p002_transfer.csv", "results/data/p002_transfer.csv"),
)


@dataclass(frozen=True)
class Pair:
    """A transfer pair: ``name`` (``source->target``), the source sweep (below the outputs root)
    and the overrides selecting its jobs on the target's test set, the target sweep and its own."""

    name: str
    source: str
    source_select: tuple[str, ...]
    target: str
    target_select: tuple[str, ...]


_PDR = "efficiency/p002_pdr"
#: The pre-declared p002 pairs (all at 16 training walks).
P002_PAIRS = (
    Pair("pdr->disturbed", _PDR, ("data.train_size=16", "test=disturbed-P0.4"), "transfer/p002_disturbed", ("test=disturbed-P0.4",)),
    Pair("disturbed->pdr", "transfer/p002_disturbed", ("test=pdr-P0.4",), _PDR, ("data.train_size=16", "test=pdr-P0.4")),
    Pair("in-family->pdr", "transfer/p002_infamily", ("test=pdr-P0.4",), _PDR, ("data.train_size=16", "test=pdr-P0.4")),
    Pair("pdr->in-family", _PDR, ("data.train_size=16", "test=in-family"), "transfer/p002_infamily", ("test=in-family",)),
)


def _select(jobs: Sequence[Job], select: Sequence[str], where: str) -> list[Job]:
    """The jobs whose overrides hold every entry of ``select``, ordered by seed (ValueError if none)."""
    out = [j for j in jobs if set(select) <= set(j.overrides)]
    if not out:
        raise ValueError(f"{where}: no job with overrides {list(select)}")
    seeds = [j.replicate for j in out]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"{where}: {list(select)} selects several jobs per seed ({seeds}); select more narrowly")
    return sorted(out, key=lambda j: (len(j.replicate), j.replicate))


def _shared_runs(ref: Tensor | None) -> bool:
    """Whether every seed was tested on the same runs (the paper's constants give the same values)."""
    return ref is not None and bool(torch.allclose(ref, ref[:1].expand_as(ref), rtol=1e-12, atol=0.0, equal_nan=True))


def _varies(m: Tensor) -> bool:
    return not bool(torch.allclose(m, m[:1].expand_as(m), rtol=1e-12, atol=0.0, equal_nan=True))


def _row(group: str, name: str, qty: str, iv: Any, seeds: int, runs: int, reference: str = "") -> dict[str, Any]:
    return {"group": group, "filter": name, "quantity": qty, "estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi,
            "seeds": seeds, "runs": runs, "reference": reference}  # fmt: skip


def _metric_row(group: str, name: str, m: Tensor, crossed: bool, prob: float) -> dict[str, Any]:
    m = m if _varies(m) else m[:1]
    return _row(group, name, "rmse_pos", _interval(m, crossed, prob), m.shape[0], m.shape[1])


def _paired(group: str, name: str, m: Tensor, ref_name: str, ref: Tensor, crossed: bool, prob: float) -> list[dict[str, Any]]:
    """``diff`` and ``diff_pct`` rows of ``m - ref`` (``reference`` = ``ref_name``)."""
    diff = _interval(m - ref, crossed, prob)
    base = float(ref[torch.isfinite(ref)].mean())
    seeds = m.shape[0] if (_varies(m) or _varies(ref)) else 1
    return [
        _row(group, name, "diff", diff, seeds, m.shape[1], ref_name),
        _row(group, name, "diff_pct", diff.scaled(100.0 / base), seeds, m.shape[1], ref_name),
    ]


def _cpu_row(group: str, name: str, jobs: Sequence[Job]) -> dict[str, Any] | None:
    values = []
    for j in jobs:
        try:
            v = float(j.results.get(name, {}).get("tuning_cpu_s") or "nan")
        except ValueError:
            v = math.nan
        if math.isfinite(v):
            values.append(v)
    if not values:
        return None
    return {"group": group, "filter": name, "quantity": "tuning_cpu_s", "estimate": sum(values) / len(values),
            "lo": min(values), "hi": max(values), "seeds": len(values), "runs": "", "reference": ""}  # fmt: skip


def best_baseline(mats: dict[str, Tensor], exclude: Sequence[str] = ()) -> str | None:
    """The row of ``mats`` with the lowest mean metric among those not in :data:`NOT_BASELINES` or ``exclude``."""
    means = {n: float(m[torch.isfinite(m)].mean()) for n, m in mats.items() if n not in NOT_BASELINES and n not in exclude}
    return min(means, key=lambda n: means[n]) if means else None


def _write(rows: Sequence[dict[str, Any]], out: str | Path) -> Path:
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(FIELDS))
        writer.writeheader()
        writer.writerows(rows)
    return path


def summarize_efficiency(
    sweep_dir: str | Path, out: str | Path, *, select: Sequence[str] = (), metric: str = "rmse_pos", prob: float = 0.95
) -> Path:
    """One group per ``data.train_size`` of ``sweep_dir`` (jobs also matching ``select``); writes ``out``.
    A size with fewer finished seeds than the others (a sweep stopped early) is left out."""
    jobs = [j for j in load_jobs(sweep_dir) if set(select) <= set(j.overrides)]
    sizes = sorted({o.split("=", 1)[1] for j in jobs for o in j.overrides if o.startswith("data.train_size=")}, key=int)
    if not sizes:
        raise ValueError(f"{sweep_dir}: no job with a data.train_size override (and {list(select)})")
    rows: list[dict[str, Any]] = []
    by_size = {size: _select(jobs, [f"data.train_size={size}"], f"{sweep_dir} N={size}") for size in sizes}
    seeds = max(len(g) for g in by_size.values())
    for size in sizes:
        group, gjobs = f"N={size}", by_size[size]
        if len(gjobs) < seeds:  # an unfinished sweep: a size with fewer seeds is left out, not shown
            print(f"{sweep_dir}: {group} has {len(gjobs)} of {seeds} seeds finished; left out", file=sys.stderr)
            continue
        names = list(dict.fromkeys(f for j in gjobs for f in j.per_run))
        mats = {n: m for n in names if (m := _matrix(gjobs, n, metric)) is not None}
        crossed = _shared_runs(mats.get(REFERENCE))
        for name, m in mats.items():
            rows.append(_metric_row(group, name, m, crossed, prob))
            if (cpu := _cpu_row(group, name, gjobs)) is not None:
                rows.append(cpu)
        for name in (LEARNED, EM):
            best = best_baseline(mats, exclude=(name,))
            if name in mats and best is not None:
                rows += _paired(group, name, mats[name], best, mats[best], crossed, prob)
    return _write(rows, out)


def summarize_transfer(
    root: str | Path, out: str | Path, *, pairs: Sequence[Pair] = P002_PAIRS, metric: str = "rmse_pos", prob: float = 0.95
) -> Path:
    """Every pair of ``pairs`` (sweeps below ``root``) on its target's test set; writes ``out``.

    Raises:
        ValueError: a pair's sweeps were not tested on the same runs, or do not share their seeds.
    """
    rows: list[dict[str, Any]] = []
    for p in pairs:
        src = _select(load_jobs(Path(root) / p.source), p.source_select, f"{p.name} source {p.source}")
        tgt = _select(load_jobs(Path(root) / p.target), p.target_select, f"{p.name} target {p.target}")
        seeds_s, seeds_t = [j.replicate for j in src], [j.replicate for j in tgt]
        if seeds_s != seeds_t:
            raise ValueError(f"{p.name}: the source's seeds {seeds_s} differ from the target's {seeds_t}")
        hand_s, hand_t = _matrix(src, REFERENCE, metric), _matrix(tgt, REFERENCE, metric)
        if hand_s is None or hand_t is None or hand_s.shape != hand_t.shape or not torch.allclose(hand_s, hand_t, rtol=1e-9, atol=0.0):
            raise ValueError(f"{p.name}: the paper's constants differ between the two sweeps: they were not tested on the same runs")
        crossed = _shared_runs(hand_t)
        source_name = p.name.split("->", 1)[0]
        learned_t, learned_s = _matrix(tgt, LEARNED, metric), _matrix(src, LEARNED, metric)
        if learned_t is None or learned_s is None:
            raise ValueError(f"{p.name}: a learned row is missing")
        tgt_mats = {n: m for n in dict.fromkeys(f for j in tgt for f in j.per_run) if (m := _matrix(tgt, n, metric)) is not None}
        best = best_baseline(tgt_mats)
        transfer = f"learned on {source_name}"
        shown: list[tuple[str, Tensor]] = [(REFERENCE, hand_t), ("learned on target", learned_t), (transfer, learned_s)]
        if best is not None and best != REFERENCE:
            shown.append((f"{best} (target)", tgt_mats[best]))
        for name in SOURCE_TUNED:
            if (m := _matrix(src, name, metric)) is not None:
                shown.append((f"{name} ({source_name})", m))
        for name, m in shown:
            rows.append(_metric_row(p.name, name, m, crossed, prob))
        rows += _paired(p.name, transfer, learned_s, "learned on target", learned_t, crossed, prob)
        if best is not None and best != REFERENCE:
            rows += _paired(p.name, transfer, learned_s, f"{best} (target)", tgt_mats[best], crossed, prob)
        rows += _paired(p.name, transfer, learned_s, REFERENCE, hand_t, crossed, prob)
        if best is not None and best != REFERENCE:  # the target's own verdict, for context
            rows += _paired(p.name, "learned on target", learned_t, f"{best} (target)", tgt_mats[best], crossed, prob)
    return _write(rows, out)


def main(argv: Sequence[str] | None = None) -> Path:
    """Command line (module docstring)."""
    ap = argparse.ArgumentParser(description="Data-efficiency and transfer summaries of issue 25's sweeps.")
    sub = ap.add_subparsers(dest="command", required=True)
    eff = sub.add_parser("efficiency", help="one group per data.train_size of a sweep")
    eff.add_argument("sweep_dir")
    eff.add_argument("--select", nargs="*", default=[], help="overrides every job must have (e.g. test=pdr-P0.4)")
    eff.add_argument("--out", required=True)
    tra = sub.add_parser("transfer", help="the p002 transfer pairs")
    tra.add_argument("--root", default="outputs", help="the directory holding efficiency/ and transfer/")
    tra.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if args.command == "efficiency":
        path = summarize_efficiency(args.sweep_dir, args.out, select=args.select)
    else:
        path = summarize_transfer(args.root, args.out)
    print(path.read_text())
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
