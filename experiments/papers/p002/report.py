"""p002's table from a seed sweep: position RMSE by filter and outage probability P.

    python experiments/train.py -m experiment=p002_pdr seed=0,1,2,3,4 scenario=p002_pdr,p002_disturbed \\
        filter=p002_rcukf,p002_ukf hydra/launcher=joblib hydra.sweep.dir=outputs/p002_sweep
    python -m experiments.papers.p002.report outputs/p002_sweep
    python -m experiments.papers.p002.report outputs/final/p002_pdr_rcukf outputs/final/p002_pdr_ukf   # one sweep per filter


The sweep's ``summary.csv`` (:mod:`experiments.runner.sweep`) holds, per group (``filter``,
``scenario`` and test set ``test=P=...``), each filter's RMSE as the mean over seeds and test runs
with its 95 % interval and the paired difference to the group's hand-tuned filter.
:func:`sweep_table` arranges them as p002's table (rows GPS only, PDR only, UKF and RC-UKF
hand-tuned and learned; columns P) with p002's published value in brackets, and a second table of
paired differences with their intervals.  Several sweep directories may be given (e.g. one per
filter): a sweep whose jobs all share ``filter=``/``scenario=`` keeps them only in the
"Overrides of every job" line of its ``summary.md``; they are read from there.
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from difffilter.evaluate.intervals import crossed_interval

from ...runner.sweep import load_jobs

__all__ = ["PAPER_RMSE", "between_sweeps", "sweep_table"]

#: p002's position RMSE table (m), by row and outage probability P.
PAPER_RMSE: dict[str, dict[float, float]] = {
    "GPS only": {0.8: 12.17, 0.6: 9.42, 0.4: 5.83, 0.2: 2.88, 0.05: 2.67},
    "PDR only": {0.8: 8.31, 0.6: 7.98, 0.4: 8.16, 0.2: 8.23, 0.05: 7.96},
    "UKF": {0.8: 7.38, 0.6: 7.19, 0.4: 4.46, 0.2: 3.97, 0.05: 2.41},
    "RC-UKF": {0.8: 6.78, 0.6: 6.42, 0.4: 3.12, 0.2: 2.60, 0.05: 1.94},
}

_FILTERS = {"p002_rcukf": "RC-UKF", "p002_ukf": "UKF"}


def _group_keys(group: str) -> dict[str, str]:
    out = {}
    for part in group.split():
        key, _, value = part.partition("=")
        out[key.lstrip("+~")] = value
    return out


def _cell(row: dict[str, str] | None, *, pct: bool = False) -> str:
    if row is None:
        return "-"
    est, lo, hi = (float(row[k]) if row[k] not in ("", None) else math.nan for k in ("estimate", "lo", "hi"))
    unit = " %" if pct else ""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"{est:.3g}{unit}"
    return f"{est:.3g} [{lo:.3g}, {hi:.3g}]{unit}"


def _common_overrides(sweep_dir: Path) -> dict[str, str]:
    """``filter=``/``scenario=`` shared by every job of a sweep (the "Overrides of every job" line of its ``summary.md``)."""
    md = sweep_dir / "summary.md"
    if not md.exists():
        return {}
    for line in md.read_text().splitlines():
        if line.startswith("Overrides of every job:"):
            keys = _group_keys(line.split(":", 1)[1].strip().strip(".").strip("`"))
            return {k: v for k, v in keys.items() if k in ("filter", "scenario")}
    return {}


def _summary_rows(sweep_dir: Path) -> list[dict[str, str]]:
    with (sweep_dir / "summary.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    common = _common_overrides(sweep_dir)
    return [{**r, "_keys": {**common, **_group_keys(r["group"])}} for r in rows]  # type: ignore[dict-item]


def sweep_table(sweep_dir: str | Path | Sequence[str | Path], *, metric: str = "rmse_pos") -> str:
    """Markdown tables per scenario family from ``<sweep_dir>/summary.csv`` (module docstring); a
    sequence of sweep directories is read as one sweep."""
    dirs = [sweep_dir] if isinstance(sweep_dir, str | Path) else list(sweep_dir)
    rows = [r for d in dirs for r in _summary_rows(Path(d))]
    index: dict[tuple[str, str, str, str, str], dict[str, str]] = {}
    families: list[str] = []
    probs: set[float] = set()
    for r in rows:
        keys: dict[str, str] = r["_keys"]  # type: ignore[assignment]
        family, test = keys.get("scenario", ""), keys.get("test", "")
        filt = _FILTERS.get(keys.get("filter", "p002_rcukf"), keys.get("filter", ""))
        if not test.startswith("P="):
            continue
        if family not in families:
            families.append(family)
        probs.add(float(test[2:]))
        index[(family, test, filt, r["filter"], r["quantity"])] = r
    cols = sorted(probs, reverse=True)
    out: list[str] = []
    for family in families:

        def get(filt: str, row: str, quantity: str, p: float, family: str = family) -> dict[str, str] | None:
            return index.get((family, f"P={p:g}", filt, row, quantity))

        head = f"| {metric} (m) [p002] | " + " | ".join(f"P={p:g}" for p in cols) + " |"
        out += [f"### scenario={family or '(default)'}", "", head, "|---|" + "---|" * len(cols)]
        lines = [
            ("GPS only", "RC-UKF", "GPS only", "GPS only"),
            ("PDR only", "RC-UKF", "PDR only", "PDR only"),
            ("UKF hand-tuned", "UKF", "hand-tuned", "UKF"),
            ("UKF learned", "UKF", "learned", ""),
            ("RC-UKF hand-tuned", "RC-UKF", "hand-tuned", "RC-UKF"),
            ("RC-UKF learned", "RC-UKF", "learned", ""),
        ]
        for label, filt, row, paper in lines:
            cells = []
            for p in cols:
                cell = _cell(get(filt, row, metric, p))
                if paper and p in PAPER_RMSE[paper]:
                    cell += f" [{PAPER_RMSE[paper][p]:.2f}]"
                cells.append(cell)
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        out += ["", "Paired differences (same test runs; mean over seeds x runs [95 % interval], m and % of the reference):", ""]
        out += ["| difference | " + " | ".join(f"P={p:g}" for p in cols) + " |", "|---|" + "---|" * len(cols)]
        diffs = [
            ("RC-UKF learned - RC-UKF hand-tuned", "RC-UKF", "learned"),
            ("UKF learned - UKF hand-tuned", "UKF", "learned"),
            ("UKF hand-tuned - RC-UKF hand-tuned", "RC-UKF", "UKF"),
        ]
        for label, filt, row in diffs:
            cells = [f"{_cell(get(filt, row, 'diff', p))}; {_cell(get(filt, row, 'diff_pct', p), pct=True)}" for p in cols]
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def _by_test(sweep_dir: str | Path, row: str, metric: str) -> dict[str, dict[str, torch.Tensor]]:
    """``{test set: {seed: per-run metric [N]}}`` of filter ``row`` in a sweep."""
    out: dict[str, dict[str, torch.Tensor]] = {}
    for job in load_jobs(sweep_dir):
        test = next((o.split("=", 1)[1] for o in job.overrides if o.startswith("test=")), "main")
        out.setdefault(test, {})[job.replicate] = job.per_run[row][metric]
    return out


def between_sweeps(
    sweep_a: str | Path, sweep_b: str | Path, *, row_a: str = "learned", row_b: str = "learned", metric: str = "rmse_pos"
) -> str:
    """Paired difference ``row_a`` of ``sweep_a`` minus ``row_b`` of ``sweep_b`` per test set: both
    sweeps' seeds tested on the same runs (fixed test seed), so the differences form a seeds x runs
    matrix with the crossed interval of :mod:`experiments.runner.sweep`.  Markdown table."""
    a, b = _by_test(sweep_a, row_a, metric), _by_test(sweep_b, row_b, metric)
    lines = [f"| test | {row_a} ({Path(sweep_a).name}) - {row_b} ({Path(sweep_b).name}) | in % of the second |", "|---|---|---|"]
    for test in sorted(set(a) & set(b), key=lambda t: -float(t[2:]) if t.startswith("P=") else 0.0):
        seeds = sorted(set(a[test]) & set(b[test]))
        if set(a[test]) != set(b[test]):
            raise ValueError(f"the sweeps have different seeds on {test}: {sorted(a[test])} vs {sorted(b[test])}")
        sizes = {int(m[s].numel()) for m in (a[test], b[test]) for s in seeds}
        if len(sizes) != 1:
            raise ValueError(f"the sweeps have different test runs on {test}: run counts {sorted(sizes)}")
        ma, mb = torch.stack([a[test][s] for s in seeds]), torch.stack([b[test][s] for s in seeds])
        d, pct = crossed_interval(ma - mb), crossed_interval(100.0 * (ma - mb) / mb.mean(0, keepdim=True))
        lines.append(f"| {test} | {d.estimate:.3g} [{d.lo:.3g}, {d.hi:.3g}] | {pct.estimate:.3g} [{pct.lo:.3g}, {pct.hi:.3g}] |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> str:
    """``python -m experiments.papers.p002.report <sweep dir> [<sweep dir> ...] [metric]``: print :func:`sweep_table`;
    ``--between <sweep a> <sweep b>``: print :func:`between_sweeps` (learned of a - learned of b)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["--between"]:  # --between <sweep a> <sweep b>: learned of a - learned of b, paired
        text = between_sweeps(args[1], args[2])
        print(text)
        return text
    if not args:
        raise SystemExit("usage: python -m experiments.papers.p002.report <sweep dir> [<sweep dir> ...] [metric]")
    metric = "rmse_pos"
    if len(args) > 1 and not Path(args[-1]).is_dir():
        metric = args.pop()
    text = sweep_table(args, metric=metric)
    print(text)
    return text


if __name__ == "__main__":  # pragma: no cover - command-line helper
    main()
