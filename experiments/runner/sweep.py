"""One summary table per sweep: aggregate the jobs of a Hydra multirun over training seeds.

    python experiments/train.py experiment=p004_blend -m seed=0,1,2,3,4   # writes summary.md/.csv at the sweep root
    python -m experiments.runner.sweep outputs/train/multiruns/<date>       # (re)build the summary of a sweep

Every job of ``experiments/train.py`` writes ``per_run.csv`` (each filter's metrics on each test
run, :mod:`difffilter.evaluate.evaluation`) and ``results.csv``.  :func:`summarize_sweep` groups
the jobs by their overrides other than the replicate key (``seed``): a sweep
``experiment=a,b seed=0,1,2,3,4`` gives two groups of five replicates.  Within a group, every
seed is tested on the same runs (the test seed is fixed, :mod:`difffilter.learn.replicates`),
so the per-run metrics form a seeds x runs matrix per filter and:

* each filter's metric is its mean over seeds and runs with a
  :func:`~difffilter.evaluate.intervals.crossed_interval` (a filter that does not depend on the
  seed, like the hand-tuned one, reduces to the t-interval over runs);
* the paired difference filter - reference (``hand-tuned``) per run and seed, same interval;
* the gap closed ``G`` of the learned filter where an ``oracle`` row exists
  (:func:`~difffilter.evaluate.intervals.gap_closed`);
* consistency: ANEES of the compared state and of every state block, run-level mean over seeds
  and runs with its interval, against the value of a consistent filter, and the fraction of
  steps inside the per-step chi-square band (mean over seeds).

If the reference filter's per-run values differ between seeds, the seeds were tested on
different runs: the intervals are then over the per-seed means (t over seeds) and ``G`` is not
computed.  :class:`SweepSummary` is the Hydra callback (``conf/hydra/callbacks/sweep_summary.yaml``)
that runs :func:`summarize_sweep` when a multirun ends; it works for any sweep of
``experiments/train.py`` (a sweep without seeds gives one row group per job).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from difffilter.evaluate.evaluation import EXTRA_TESTS_DIR, PER_RUN_FILE, read_per_run
from difffilter.evaluate.intervals import GapClosed, Interval, crossed_interval, gap_closed, nested_interval
from experiments.results_tables import anees_verdict

from .liveness import assess

__all__ = ["SUMMARY_CSV", "SUMMARY_MD", "SweepSummary", "load_jobs", "main", "summarize_sweep", "unfinished_jobs"]

log = logging.getLogger(__name__)

SUMMARY_MD, SUMMARY_CSV = "summary.md", "summary.csv"


@dataclass
class Job:
    """One finished job: its directory, overrides other than the replicate key, replicate value,
    per-run metrics ``{filter: {metric: [N]}}``, ``results.csv`` rows by filter, and its group
    (the overrides that differ between the sweep's jobs, replicate key aside)."""

    directory: Path
    overrides: list[str]
    replicate: str
    per_run: dict[str, dict[str, Tensor]]
    results: dict[str, dict[str, str]] = field(default_factory=dict)
    group: str = ""


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def load_jobs(sweep_dir: str | Path, *, replicate_key: str = "seed") -> list[Job]:
    """Every job below ``sweep_dir`` that wrote a ``per_run.csv``, in directory order, grouped by
    the overrides that differ between jobs (the replicate key aside).  A run's extra test sets
    (``<run>/extra_tests/<name>/per_run.csv``) are jobs of their own with the run's overrides plus
    ``test=<name>``; when a sweep has them, the main test sets read ``test=<experiment.test_name>``
    (default ``main``)."""
    root = Path(sweep_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"no sweep directory {root}")
    jobs = []
    paths = sorted(root.rglob(PER_RUN_FILE), key=lambda p: [int(s) if s.isdigit() else s for s in p.parent.relative_to(root).parts])
    extra = any(p.parent.parent.name == EXTRA_TESTS_DIR for p in paths)
    for path in paths:
        job_dir = path.parent
        test = ""
        if job_dir.parent.name == EXTRA_TESTS_DIR:  # an extra test set of the run two levels up
            test, job_dir = job_dir.name, job_dir.parent.parent
        elif extra:
            config = job_dir / ".hydra" / "config.yaml"
            label = OmegaConf.select(OmegaConf.load(config), "experiment.test_name", default=None) if config.exists() else None
            test = str(label or "main")
        overrides_file = job_dir / ".hydra" / "overrides.yaml"
        overrides = [str(o) for o in OmegaConf.load(overrides_file)] if overrides_file.exists() else []
        rest = sorted(o for o in overrides if _key(o) != replicate_key) + ([f"test={test}"] if test else [])
        rep = [o.split("=", 1)[1] for o in overrides if _key(o) == replicate_key]
        if not rep:
            config = job_dir / ".hydra" / "config.yaml"
            value = OmegaConf.load(config).get(replicate_key) if config.exists() else None
            rep = [str(value) if value is not None else job_dir.name]
        results: dict[str, dict[str, str]] = {}
        if (path.parent / "results.csv").exists():
            with (path.parent / "results.csv").open(newline="") as fh:
                results = {r["filter"]: r for r in csv.DictReader(fh)}
        jobs.append(Job(job_dir, rest, rep[0], read_per_run(path), results))
    common = set.intersection(*(set(j.overrides) for j in jobs)) if jobs else set()
    for j in jobs:
        j.group = " ".join(o for o in j.overrides if o not in common)
    return jobs


def unfinished_jobs(sweep_dir: str | Path) -> list[tuple[Path, str]]:
    """Job directories of a sweep whose ``status.json`` says failed, interrupted or still
    running (:func:`experiments.runner.runs.run_status`), with the reason."""
    out = []
    for status_file in sorted(Path(sweep_dir).rglob("status.json")):
        state = assess(json.loads(status_file.read_text()))  # a killed run's "running" reads as killed
        if state.get("status") != "completed":
            why = (
                state.get("error")
                or state.get("reason")
                or (f"{state.get('signal')}; checkpoint {state.get('checkpoint')}" if state.get("signal") else "")
            )
            out.append((status_file.parent, f"{state.get('status')}" + (f" ({why})" if why else "")))
    return out


def _float(text: str | None) -> float:
    try:
        return float(text) if text not in (None, "") else math.nan
    except ValueError:
        return math.nan


def _fmt(v: float) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.4g}"


def _ci(iv: Interval) -> str:
    if not math.isfinite(iv.estimate):
        return "-"
    if not (math.isfinite(iv.lo) and math.isfinite(iv.hi)):
        return _fmt(iv.estimate)
    return f"{_fmt(iv.estimate)} [{_fmt(iv.lo)}, {_fmt(iv.hi)}]"


def _matrix(jobs: Sequence[Job], name: str, metric: str) -> Tensor | None:
    rows = [j.per_run.get(name, {}).get(metric) for j in jobs]
    if any(r is None for r in rows) or len({int(r.numel()) for r in rows if r is not None}) != 1:
        return None
    return torch.stack([r for r in rows if r is not None])


def _interval(m: Tensor, crossed: bool, prob: float) -> Interval:
    if crossed or m.shape[0] == 1:
        return crossed_interval(m, prob)
    means = torch.stack([r[torch.isfinite(r)].mean() for r in m])
    return nested_interval(means, prob)


@dataclass
class _Group:
    name: str
    jobs: list[Job]
    rows: list[dict[str, Any]] = field(default_factory=list)
    blocks: list[dict[str, Any]] = field(default_factory=list)
    note: str = ""


def _summarize_group(group: _Group, *, metric: str, reference: str, learned: str, oracle: str, prob: float, draws: int) -> None:
    jobs = group.jobs
    filters = list(dict.fromkeys(f for j in jobs for f in j.per_run))
    ref = _matrix(jobs, reference, metric)
    crossed = ref is not None and bool(torch.allclose(ref, ref[:1].expand_as(ref), rtol=1e-12, atol=0.0, equal_nan=True))
    if ref is not None and not crossed:
        group.note = f"the {reference!r} filter's per-run {metric} differs between seeds: different test runs, intervals over seed means"
    gap: GapClosed | None = None
    mats = {f: _matrix(jobs, f, metric) for f in filters}
    if crossed and ref is not None and mats.get(learned) is not None and mats.get(oracle) is not None:
        gap = gap_closed(ref[0], mats[learned], mats[oracle][0], prob=prob, draws=draws)
    for name in filters:
        m = mats[name]
        if m is None:
            continue
        varies = not bool(torch.allclose(m, m[:1].expand_as(m), rtol=1e-12, atol=0.0, equal_nan=True))
        row: dict[str, Any] = {
            "filter": name,
            "seeds": m.shape[0] if varies else 1,
            "runs": m.shape[1],
            metric: _interval(m if varies else m[:1], crossed, prob),
        }
        if ref is not None and name != reference:
            diff = _interval(m - ref, crossed, prob)
            base = float(ref[torch.isfinite(ref)].mean())
            row["diff"], row["diff_pct"] = diff, diff.scaled(100.0 / base) if base else None
        if name == learned and gap is not None:
            row["gap"] = gap
        group.rows.append(row)
        for key in [k for k in next(iter(j.per_run[name] for j in jobs)) if k == "anees" or k.startswith("nees_")]:
            bm = _matrix(jobs, name, key)
            if bm is None:
                continue
            res = [j.results.get(name, {}) for j in jobs]
            dof = _float(res[0].get(f"{key}_dof"))
            frac = [_float(r.get(f"{key}_step_band_frac")) for r in res]
            frac_ok = [x for x in frac if math.isfinite(x)]
            group.blocks.append(
                {
                    "filter": name,
                    "block": "all" if key == "anees" else key.removeprefix("nees_"),
                    "dof": dof,
                    "anees": _interval(bm if varies else bm[:1], crossed, prob),
                    "band_frac": sum(frac_ok) / len(frac_ok) if frac_ok else math.nan,
                    "runs": int(bm.shape[1]),
                }
            )


def _markdown(groups: Sequence[_Group], *, metric: str, reference: str, learned: str, oracle: str, prob: float) -> str:
    pct = f"{100 * prob:g} %"
    common = sorted(set.intersection(*(set(j.overrides) for g in groups for j in g.jobs)))
    out = [
        "# Sweep summary",
        "",
        f"Overrides of every job: `{' '.join(common) or '(none)'}`.",
        "",
        f"`{metric}`: mean over training seeds and test runs of the per-run value, [{pct} interval over seeds x runs];"
        f" difference: paired per run and seed, filter - `{reference}`; G = (e_hand - e_learned) / (e_hand - e_oracle)"
        " with a bootstrap interval over runs and seeds (undefined when hand-tuned and oracle tie).",
        f"Consistency: ANEES run-level mean [{pct} interval] against the value of a consistent filter (d), and the mean"
        f" over seeds of the fraction of steps inside the per-step {pct} chi-square band; verdict: the interval inside /"
        " above / below the 95 % chi-square band of a consistent filter's mean NEES over the N runs, else undecided"
        " (experiments.results_tables.anees_verdict).",
    ]
    for g in groups:
        seeds = sorted({j.replicate for j in g.jobs}, key=lambda s: (len(s), s))
        out += ["", f"## {g.name or 'all jobs'} (seeds {', '.join(seeds)}; jobs {', '.join(j.directory.name for j in g.jobs)})", ""]
        if g.note:
            out += [f"Note: {g.note}.", ""]
        out += [f"| filter | seeds | runs | {metric} | filter - {reference} | in % of {reference} | G |", "|---|---|---|---|---|---|---|"]
        for r in g.rows:
            gap = r.get("gap")
            g_cell = (
                ""
                if gap is None
                else (f"{_fmt(gap.value)} [{_fmt(gap.lo)}, {_fmt(gap.hi)}]" if gap.defined else f"undefined: {gap.reason}")
            )
            cells = [
                r["filter"],
                str(r["seeds"]),
                str(r["runs"]),
                _ci(r[metric]),
                _ci(r["diff"]) if "diff" in r else "",
                _ci(r["diff_pct"]) if r.get("diff_pct") else "",
                g_cell,
            ]
            out.append("| " + " | ".join(cells) + " |")
        if g.blocks:
            out += ["", "| filter | block | d | ANEES [interval] | verdict (band rule) | steps in band |", "|---|---|---|---|---|---|"]
            for b in g.blocks:
                iv = b["anees"]
                verdict = anees_verdict(iv.lo, iv.hi, b["dof"], b["runs"])
                frac = "" if not math.isfinite(b["band_frac"]) else f"{100 * b['band_frac']:.0f} %"
                out.append(f"| {b['filter']} | {b['block']} | {_fmt(b['dof'])} | {_ci(iv)} | {verdict} | {frac} |")
    return "\n".join(out) + "\n"


def _csv_rows(groups: Sequence[_Group], metric: str) -> list[dict[str, Any]]:
    rows = []
    for g in groups:
        for r in g.rows:
            for qty, iv in ((metric, r[metric]), ("diff", r.get("diff")), ("diff_pct", r.get("diff_pct"))):
                if isinstance(iv, Interval):
                    rows.append(
                        {
                            "group": g.name,
                            "filter": r["filter"],
                            "quantity": qty,
                            "estimate": iv.estimate,
                            "lo": iv.lo,
                            "hi": iv.hi,
                            "seeds": r["seeds"],
                            "runs": r["runs"],
                            "reference": "",
                        }
                    )
            gap = r.get("gap")
            if gap is not None:
                rows.append(
                    {
                        "group": g.name,
                        "filter": r["filter"],
                        "quantity": "gap_closed",
                        "estimate": gap.value,
                        "lo": gap.lo,
                        "hi": gap.hi,
                        "seeds": r["seeds"],
                        "runs": r["runs"],
                        "reference": gap.reason,
                    }
                )
        for b in g.blocks:
            iv = b["anees"]
            rows.append(
                {
                    "group": g.name,
                    "filter": b["filter"],
                    "quantity": f"anees_{b['block']}",
                    "estimate": iv.estimate,
                    "lo": iv.lo,
                    "hi": iv.hi,
                    "seeds": "",
                    "runs": "",
                    "reference": b["dof"],
                }
            )
            rows.append(
                {
                    "group": g.name,
                    "filter": b["filter"],
                    "quantity": f"step_band_frac_{b['block']}",
                    "estimate": b["band_frac"],
                    "lo": "",
                    "hi": "",
                    "seeds": "",
                    "runs": "",
                    "reference": "",
                }
            )
    return rows


def summarize_sweep(
    sweep_dir: str | Path,
    *,
    replicate_key: str = "seed",
    metric: str = "rmse_pos",
    reference: str = "hand-tuned",
    learned: str = "learned",
    oracle: str = "oracle",
    prob: float = 0.95,
    draws: int = 4000,
) -> tuple[Path, Path]:
    """Write ``summary.md`` and ``summary.csv`` to ``sweep_dir`` from its jobs' ``per_run.csv``
    (module docstring); returns their paths.

    Args:
        sweep_dir: the multirun directory (``hydra.sweep.dir``).
        replicate_key: the override that numbers replicates (jobs differing only in it are pooled).
        metric: per-run metric compared (a ``per_run.csv`` column; lower is better for ``G``).
        reference, learned, oracle: filter names of the hand-tuned, learned and oracle rows.
        prob: coverage of every interval.
        draws: bootstrap resamples for ``G``.
    """
    jobs = load_jobs(sweep_dir, replicate_key=replicate_key)
    if not jobs:
        raise FileNotFoundError(f"no {PER_RUN_FILE} below {sweep_dir}: no finished job of experiments/train.py")
    names = list(dict.fromkeys(j.group for j in jobs))
    groups = [_Group(n, [j for j in jobs if j.group == n]) for n in names]
    for g in groups:
        _summarize_group(g, metric=metric, reference=reference, learned=learned, oracle=oracle, prob=prob, draws=draws)
    root = Path(sweep_dir)
    md = root / SUMMARY_MD
    text = _markdown(groups, metric=metric, reference=reference, learned=learned, oracle=oracle, prob=prob)
    missing = unfinished_jobs(root)
    if missing:
        text += "\n## Jobs left out (no results)\n\n" + "\n".join(f"- `{d.relative_to(root)}`: {why}" for d, why in missing) + "\n"
    md.write_text(text)
    rows = _csv_rows(groups, metric)
    path = root / SUMMARY_CSV
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=["group", "filter", "quantity", "estimate", "lo", "hi", "seeds", "runs", "reference"])
        writer.writeheader()
        writer.writerows(rows)
    return md, path


class SweepSummary(Callback):
    """Hydra callback: when a multirun ends, :func:`summarize_sweep` its directory.

    Keyword arguments are passed to :func:`summarize_sweep`.  A sweep whose jobs wrote no
    ``per_run.csv`` (another entry point) is left alone; a failure is logged, not raised, since
    every job's own results are already on disk and ``python -m experiments.runner.sweep`` can
    rebuild the summary.
    """

    def __init__(self, **options: Any) -> None:
        self.options = options

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not any(sweep_dir.rglob(PER_RUN_FILE)):
            return
        try:
            md, _ = summarize_sweep(sweep_dir, **self.options)
        except Exception:  # noqa: BLE001 - the jobs' results are safe; report and carry on
            log.exception("could not summarise the sweep %s", sweep_dir)
            return
        log.info("sweep summary written to %s", md)
        print(md.read_text())


def main(argv: Sequence[str] | None = None) -> Path:
    """Command line (module docstring); returns the ``summary.md`` path."""
    ap = argparse.ArgumentParser(description="Summarise a multirun of experiments/train.py over seeds.")
    ap.add_argument("sweep_dir")
    ap.add_argument("--replicate-key", default="seed")
    ap.add_argument("--metric", default="rmse_pos")
    ap.add_argument("--reference", default="hand-tuned")
    ap.add_argument("--draws", type=int, default=4000)
    args = ap.parse_args(argv)
    md, _ = summarize_sweep(
        args.sweep_dir, replicate_key=args.replicate_key, metric=args.metric, reference=args.reference, draws=args.draws
    )
    print(md.read_text())
    return md


if __name__ == "__main__":
    main(sys.argv[1:])
