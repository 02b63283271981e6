"""p002's table from a seed sweep: position RMSE by filter and outage probability P.

    python experiments/train.py -m experiment=p002_pdr seed=0,1,2,3,4 scenario=p002_pdr,p002_disturbed \\
        filter=p002_rcukf,p002_ukf hydra/launcher=joblib hydra.sweep.dir=outputs/p002_sweep
    python -m difffilter.papers.p002.report outputs/p002_sweep
    python -m difffilter.papers.p002.report outputs/final/p002_pdr_rcukf outputs/final/p002_pdr_ukf   # one sweep per filter


The sweep's ``summary.csv`` (:mod:`difffilter.learn.sweep`) holds, per group (``filter``,
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

__all__ = ["PAPER_RMSE", "sweep_table"]

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


def main(argv: Sequence[str] | None = None) -> str:
    """``python -m difffilter.papers.p002.report <sweep dir> [<sweep dir> ...] [metric]``: print :func:`sweep_table`."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        raise SystemExit("usage: python -m difffilter.papers.p002.report <sweep dir> [<sweep dir> ...] [metric]")
    metric = "rmse_pos"
    if len(args) > 1 and not Path(args[-1]).is_dir():
        metric = args.pop()
    text = sweep_table(args, metric=metric)
    print(text)
    return text


if __name__ == "__main__":  # pragma: no cover - command-line helper
    main()
