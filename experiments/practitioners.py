"""Summary of a practitioners sweep (issue 25, ``results/p00_practitioners.md``).

``python -m experiments.practitioners <sweep_dir>`` writes the sweep's ``summary.md`` /
``summary.csv`` (:func:`experiments.runner.sweep.summarize_sweep`: every filter against the
paper's constants, ``hand-tuned``) and adds to ``summary.csv``, per test set (group):

* the paired difference learned - *best non-learned* (``diff`` and ``diff_pct`` rows of
  ``learned`` whose ``reference`` names the best), where the best is the lowest mean test RMSE
  among the non-learned methods of :data:`experiments.results_tables.NON_LEARNED` that ran, the rule
  pre-declared in ``results/p00_practitioners.md``; the interval is over seeds x runs when the
  seeds share their test runs (the paper's constants then give the same per-run values in every
  seed), else over seed means, as the sweep's own differences;
* ``tuning_cpu_s`` of every row that reports one (mean over seeds in ``estimate``, min and max in
  ``lo``/``hi``): the CPU seconds of its tuning, the learned row's training.

``results/REPORT.md`` reads both (:func:`experiments.results_report.summary_cells`).

``python -m experiments.practitioners --adaptive <sweep_dir> --into <family CSV>`` joins a
*learned adaptive* sweep (``experiment=<family>_learned_adaptive``: Sage-Husa with its forgetting
factor and starting noise learned, a separate training job that also rebuilds the family's
non-learned rows on the same test runs) to the family's data file as the ``learned-adaptive``
rows (:func:`join_learned_adaptive`; ``--name`` writes them under another name, e.g.
``learned-adaptive-k0``).

``python -m experiments.practitioners --merge <sweep_dir> --into <family CSV>`` adds the rows of
a sweep that reran the family's experiment with more non-learned rows (p000's adaptive filters
around a kappa 0 UKF, ``experiment=p000_<family>_practitioners_k0``) to the family's data file
(:func:`merge_rows`), refusing unless the rows it shares with the file are the file's.
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

from experiments.results_tables import FIELDS, NON_LEARNED, REFERENCE  # noqa: E402
from experiments.runner.sweep import Job, _interval, _matrix, load_jobs, summarize_sweep  # noqa: E402

__all__ = ["best_non_learned", "join_learned_adaptive", "main", "merge_rows", "summarize_practitioners"]

LEARNED = "learned"
ADAPTIVE = "learned-adaptive"
#: The learned adaptive job's row of the family's filter at the paper's values (its own
#: ``hand-tuned`` row is the adaptive filter at its start values).
PAPER = "paper-constants"


def best_non_learned(rows: Sequence[dict[str, Any]], group: str, metric: str = "rmse_pos") -> str | None:
    """The non-learned method (a filter name of ``NON_LEARNED``) with the lowest mean ``metric`` in
    ``group`` of a summary's rows, None when none ran."""
    means = {
        r["filter"]: float(r["estimate"])
        for r in rows
        if r["group"] == group and r["quantity"] == metric and not r["reference"] and r["filter"] in NON_LEARNED
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


def summarize_practitioners(sweep_dir: str | Path, *, metric: str = "rmse_pos", oracle: str = "oracle", prob: float = 0.95) -> Path:
    """Summarise ``sweep_dir`` (module docstring); returns the ``summary.csv`` path.  ``oracle``:
    the row the learned filter's gap closed G is measured against (``summarize_sweep``'s; p002's
    in-family walks use ``exact UKF``, the optimal filter of their truth)."""
    _, path = summarize_sweep(sweep_dir, metric=metric, reference=REFERENCE, oracle=oracle, prob=prob)
    with path.open(newline="") as fh:
        rows: list[dict[str, Any]] = list(csv.DictReader(fh))
    jobs = load_jobs(sweep_dir)
    extra: list[dict[str, Any]] = []
    for group in dict.fromkeys(j.group for j in jobs):
        gjobs = [j for j in jobs if j.group == group]
        extra += _tuning_rows(gjobs, group)
        best = best_non_learned(rows, group, metric)
        trained = _matrix(gjobs, LEARNED, metric)
        if best is None or best == REFERENCE or trained is None:
            continue  # against the paper's constants the sweep's own diff rows are the paired ones
        ref, hand = _matrix(gjobs, best, metric), _matrix(gjobs, REFERENCE, metric)
        if ref is None:
            continue
        # the seeds share their test runs when the paper's constants give the same per-run values
        crossed = hand is not None and _same_every_seed(hand)
        diff = _interval(trained - ref, crossed, prob)
        base = float(ref[torch.isfinite(ref)].mean())
        common = {"group": group, "filter": LEARNED, "seeds": trained.shape[0], "runs": trained.shape[1], "reference": best}
        for qty, iv in (("diff", diff), ("diff_pct", diff.scaled(100.0 / base))):
            extra.append({**common, "quantity": qty, "estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi})
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(FIELDS))
        writer.writeheader()
        writer.writerows(rows + extra)
    return path


def _same_every_seed(m: torch.Tensor) -> bool:
    """Whether every seed's row of ``m [seeds, runs]`` equals the first (the seeds share their
    test runs and the filter does not depend on the seed)."""
    return bool(torch.allclose(m, m[:1].expand_as(m), rtol=1e-12, atol=0.0, equal_nan=True))


def _rows(common: dict[str, Any], qty: str, iv: Any, reference: str = "") -> dict[str, Any]:
    return {**common, "quantity": qty, "estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi, "reference": reference}


def join_learned_adaptive(
    sweep_dir: str | Path,
    into: str | Path,
    *,
    metric: str = "rmse_pos",
    prob: float = 0.95,
    rtol: float = 1e-9,
    name: str = ADAPTIVE,
) -> list[str]:
    """Write the ``learned-adaptive`` rows of the learned adaptive sweep ``sweep_dir`` into the
    family's data file ``into`` (its earlier ``learned-adaptive`` rows replaced, every other row
    kept); returns the report lines (printed by :func:`main`).

    Per test set (group) of the sweep, the job's ``learned`` row becomes ``learned-adaptive``:
    its ``metric`` [interval over seeds x runs]; ``diff``/``diff_pct`` against the family's filter
    at the paper's values (the job's ``paper-constants`` row, the data file's ``hand-tuned``);
    the same against the best non-learned row (:func:`best_non_learned` of the data file's rows,
    ``reference`` naming it), paired per test run and seed with that row *as rebuilt in the same
    job*; ``tuning_cpu_s`` (its training).  Pairing needs the job's rows to be the data file's:
    every non-learned row the job rebuilt is compared with the file's ``metric`` estimate, and a
    relative difference above ``rtol`` raises ``ValueError`` (other test runs or another code
    state: rerun the family's practitioners sweep too).  Plain ``learned`` is not rebuilt by the
    job: the lines report learned adaptive - learned as a difference of means, unpaired.  ``name``:
    the rows' filter name (another learned adaptive variant, e.g. ``learned-adaptive-k0``; only
    that name's earlier rows are replaced).
    """
    if name in NON_LEARNED or name in (LEARNED, REFERENCE, PAPER):
        raise ValueError(f"name must be a learned adaptive row's own name, got {name!r}")
    jobs = load_jobs(sweep_dir)
    with Path(into).open(newline="") as fh:
        rows: list[dict[str, Any]] = [r for r in csv.DictReader(fh) if r["filter"] != name]
    names = set(NON_LEARNED) - {REFERENCE}
    extra: list[dict[str, Any]] = []
    lines = []
    for group in dict.fromkeys(j.group for j in jobs):
        gjobs = [j for j in jobs if j.group == group]
        adaptive, paper = _matrix(gjobs, LEARNED, metric), _matrix(gjobs, PAPER, metric)
        if adaptive is None or paper is None:
            raise ValueError(f"{sweep_dir} group {group!r}: every job needs a {LEARNED!r} and a {PAPER!r} row in per_run.csv")
        committed = {
            r["filter"]: float(r["estimate"]) for r in rows if r["group"] == group and r["quantity"] == metric and not r["reference"]
        }
        if not committed:
            raise ValueError(f"{into} has no {metric} rows for group {group!r} (the sweep's test sets must be the family's)")
        crossed = _same_every_seed(paper)
        checked = []
        for job_name, file_name in [(PAPER, REFERENCE), *((n, n) for n in sorted(names))]:
            m = _matrix(gjobs, job_name, metric)
            if m is None or file_name not in committed:
                continue
            varies = not _same_every_seed(m)
            value = _interval(m if varies else m[:1], crossed, prob).estimate
            rel = abs(value - committed[file_name]) / abs(committed[file_name])
            if not rel <= rtol:
                raise ValueError(
                    f"group {group!r}: {job_name!r} rebuilt in {sweep_dir} gives {metric} {value!r}, {into} has {file_name!r} "
                    f"{committed[file_name]!r} (relative difference {rel:.3g} > {rtol:g}): not the same rows, no pairing"
                )
            checked.append(f"{file_name} {rel:.1g}")
        best = best_non_learned(rows, group, metric)
        common = {"group": group, "filter": name, "seeds": adaptive.shape[0], "runs": adaptive.shape[1]}
        iv = _interval(adaptive, crossed, prob)
        diff = _interval(adaptive - paper, crossed, prob)
        base = float(paper[torch.isfinite(paper)].mean())
        extra += [_rows(common, metric, iv), _rows(common, "diff", diff), _rows(common, "diff_pct", diff.scaled(100.0 / base))]
        line = f"{group or 'test'}: {name} {metric} {iv.estimate:.6g} [{iv.lo:.6g}, {iv.hi:.6g}]"
        line += f"; rows reproduced (rel. diff): {', '.join(checked)}"
        if best is not None and best != REFERENCE:
            ref = _matrix(gjobs, best, metric)
            if ref is None:
                raise ValueError(f"{sweep_dir} group {group!r}: the best non-learned row {best!r} is not in the job's per_run.csv")
            d = _interval(adaptive - ref, crossed, prob)
            pct = d.scaled(100.0 / float(ref[torch.isfinite(ref)].mean()))
            extra += [_rows(common, "diff", d, best), _rows(common, "diff_pct", pct, best)]
            line += f"; - {best}: {pct.estimate:.4g} % [{pct.lo:.4g}, {pct.hi:.4g}]"
        elif best == REFERENCE:
            pct = diff.scaled(100.0 / base)
            line += f"; - {REFERENCE} (best): {pct.estimate:.4g} % [{pct.lo:.4g}, {pct.hi:.4g}]"
        if LEARNED in committed:
            line += f"; - {LEARNED} (unpaired, means): {100.0 * (iv.estimate - committed[LEARNED]) / committed[LEARNED]:.4g} %"
        lines.append(line)
        extra += [{**r, "filter": name} for r in _tuning_rows(gjobs, group) if r["filter"] == LEARNED]
    seeds = {j.replicate: j.results.get(LEARNED, {}).get("parameters", "") for j in jobs}
    lines += [f"seed {s}: {p}" for s, p in seeds.items()]
    with Path(into).open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(FIELDS))
        writer.writeheader()
        writer.writerows(rows + extra)
    return lines


def _key(r: dict[str, Any]) -> tuple[str, str, str, str]:
    return (r["group"], r["filter"], r["quantity"], r["reference"])


def _pairing(r: dict[str, Any]) -> bool:
    """A row pairing a learned filter with the best non-learned row (it depends on which rows ran)."""
    return r["quantity"] in ("diff", "diff_pct") and r["reference"] in NON_LEARNED and r["filter"] not in NON_LEARNED


def _same(a: str, b: str, rtol: float) -> bool:
    if a.strip() == b.strip():
        return True
    try:
        x, y = float(a), float(b)
    except ValueError:
        return False
    return (math.isnan(x) and math.isnan(y)) or abs(x - y) <= rtol * max(abs(x), abs(y))


def merge_rows(sweep_dir: str | Path, into: str | Path, *, metric: str = "rmse_pos", prob: float = 0.95, rtol: float = 1e-9) -> list[str]:
    """Add the rows of the filters new to the family's data file ``into`` from the sweep
    ``sweep_dir`` (the family's experiment rerun with more non-learned rows, summarised here by
    :func:`summarize_practitioners`); returns the report lines (printed by :func:`main`).

    Refuses (``ValueError``, nothing written) unless the sweep shares the paper's constants with the
    file and every row of the filters both have (every quantity; estimate, lo and hi) equals the
    file's to ``rtol`` relative, apart from the CPU rows and the learned filters' pairing with the
    best non-learned row; and, when it would add rows, if the file already has learned adaptive
    rows (join those after: they are paired with the best row, which the merge may change).  A
    sweep merged before adds nothing: its rows are checked and the file is left as it is.  Per test set (group), where the
    best non-learned row (:func:`best_non_learned`) of the merged rows is a new one, the learned
    row's pairing rows become the sweep's (learned - that row, paired per test run and seed in the
    sweep, whose learned row was just checked to be the file's); otherwise the file's stay.
    """
    summary = summarize_practitioners(sweep_dir, metric=metric, prob=prob)
    with summary.open(newline="") as fh:
        new: list[dict[str, Any]] = list(csv.DictReader(fh))
    with Path(into).open(newline="") as fh:
        old: list[dict[str, Any]] = list(csv.DictReader(fh))
    shared = {r["filter"] for r in old} & {r["filter"] for r in new}
    added = list(dict.fromkeys(r["filter"] for r in new if r["filter"] not in shared))
    if REFERENCE not in shared:
        raise ValueError(f"{sweep_dir} must share {REFERENCE!r} with {into} (the same test runs); it shares {sorted(shared)}")
    if added and any(r["filter"].startswith(ADAPTIVE) for r in old):
        raise ValueError(f"{into} has learned adaptive rows: merge first, then join those (they pair with the best row)")

    def checked(rows: list[dict[str, Any]]) -> dict[tuple[str, str, str, str], dict[str, Any]]:
        return {_key(r): r for r in rows if r["filter"] in shared and r["quantity"] != "tuning_cpu_s" and not _pairing(r)}

    mine, theirs = checked(new), checked(old)
    if set(mine) != set(theirs):
        raise ValueError(f"{sweep_dir} and {into} differ in their shared rows: {sorted(set(mine) ^ set(theirs))[:6]}")
    worst = 0.0
    for key, r in mine.items():
        for col in ("estimate", "lo", "hi"):
            if not _same(r[col], theirs[key][col], rtol):
                raise ValueError(
                    f"group {key[0]!r}: {key[1]!r} {key[2]} {key[3]} {col} {r[col]} in {sweep_dir}, {theirs[key][col]} in {into} "
                    f"(not equal to {rtol:g} relative): not the same rows, nothing merged"
                )
            if r[col].strip() and theirs[key][col].strip():
                x, y = float(r[col]), float(theirs[key][col])
                if math.isfinite(x) and math.isfinite(y) and max(abs(x), abs(y)) > 0:
                    worst = max(worst, abs(x - y) / max(abs(x), abs(y)))
    lines = [f"shared rows reproduced: {len(mine)} ({', '.join(sorted(shared))}), largest relative difference {worst:.2g}"]
    if not added:  # merged before: the check above was the whole job
        return [*lines, f"nothing new in {sweep_dir}: {into} unchanged"]
    rows = [*old, *(r for r in new if r["filter"] in added)]
    for group in dict.fromkeys(r["group"] for r in new):
        best = best_non_learned(rows, group, metric)
        lines.append(f"{group or 'test'}: best non-learned {best}")
        if best in added:
            rows = [r for r in rows if not (r["group"] == group and _pairing(r) and r["filter"] not in added)]
            rows += [r for r in new if r["group"] == group and _pairing(r) and r["filter"] in shared and r["reference"] == best]
            for r in new:
                if r["group"] == group and _pairing(r) and r["reference"] == best and r["quantity"] == "diff_pct":
                    est, lo, hi = (float(r[c]) for c in ("estimate", "lo", "hi"))
                    lines.append(f"{group or 'test'}: {r['filter']} - {best}: {est:.4g} % [{lo:.4g}, {hi:.4g}]")
    with Path(into).open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(FIELDS))
        writer.writeheader()
        writer.writerows(rows)
    return lines


def main(argv: Sequence[str] | None = None) -> Path:
    """Command line: ``python -m experiments.practitioners <sweep_dir> [--metric rmse_pos] [--oracle NAME]``, or
    ``python -m experiments.practitioners --adaptive <sweep_dir> [--name NAME] --into <family CSV>``, or
    ``python -m experiments.practitioners --merge <sweep_dir> --into <family CSV>``."""
    ap = argparse.ArgumentParser(description="Summarise a practitioners sweep: paired learned - best non-learned, tuning CPU.")
    ap.add_argument("sweep_dir", nargs="?")
    ap.add_argument("--metric", default="rmse_pos")
    ap.add_argument("--oracle", default="oracle", help="the row G is measured against (default: oracle)")
    ap.add_argument("--adaptive", help="a learned adaptive sweep to join to --into as the learned-adaptive rows")
    ap.add_argument("--name", default=ADAPTIVE, help=f"with --adaptive: the rows' filter name (default {ADAPTIVE})")
    ap.add_argument("--merge", help="a sweep whose new non-learned rows to add to --into (its shared rows must be the file's)")
    ap.add_argument("--into", help="the family's data file, results/data/<family>_practitioners.csv")
    args = ap.parse_args(argv)
    if args.adaptive or args.merge:
        if not args.into or args.sweep_dir or (args.adaptive and args.merge):
            ap.error("--adaptive or --merge takes --into <family CSV> and no sweep_dir")
        if args.merge:
            print("\n".join(merge_rows(args.merge, args.into, metric=args.metric)))
        else:
            print("\n".join(join_learned_adaptive(args.adaptive, args.into, metric=args.metric, name=args.name)))
        return Path(args.into)
    if not args.sweep_dir:
        ap.error("give a sweep_dir (or --adaptive with --into)")
    path = summarize_practitioners(args.sweep_dir, metric=args.metric, oracle=args.oracle)
    print(path.read_text())
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
