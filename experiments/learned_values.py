"""The learned parameter values of every job of a seed sweep, next to the hand-tuned and oracle ones.

    python experiments/learned_values.py outputs/train/multiruns/<sweep>            # markdown to stdout
    python experiments/learned_values.py outputs/train/multiruns/<sweep> --filter oracle

Reads each job's ``results.csv`` (its ``parameters`` column, written by ``experiments/train.py``
for the parameters named in ``learn``) and groups the jobs as the sweep summary does
(:func:`difffilter.learn.sweep.load_jobs`): per group, one row per seed with the learned values,
then the mean over seeds of every value, then the hand-tuned and oracle rows of the first job.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from difffilter.learn.sweep import load_jobs

__all__ = ["main", "parse_parameters", "values_table"]


def parse_parameters(text: str) -> dict[str, list[float]]:
    """``"psi=[0.7, 0.69]; R=[9]"`` -> ``{"psi": [0.7, 0.69], "R": [9.0]}``."""
    out: dict[str, list[float]] = {}
    for name, values in re.findall(r"([\w.]+)=\[([^\]]*)\]", text or ""):
        out[name] = [float(v) for v in values.split(",") if v.strip()]
    return out


def _cell(values: list[float]) -> str:
    if len(values) == 1 or all(v == values[0] for v in values):
        return f"{values[0]:.4g}"
    return f"{sum(values) / len(values):.4g} ({min(values):.4g}-{max(values):.4g})"


def values_table(sweep_dir: str | Path, *, learned: str = "learned", others: Sequence[str] = ("hand-tuned", "oracle")) -> str:
    """Markdown: per group of the sweep, the ``learned`` row's parameters per seed and their mean,
    then the ``others`` rows of the group's first job.  A vector parameter shows its mean and range."""
    jobs = load_jobs(sweep_dir)
    if not jobs:
        raise FileNotFoundError(f"no finished job below {sweep_dir}")
    lines: list[str] = []
    for group in dict.fromkeys(j.group for j in jobs):
        members = [j for j in jobs if j.group == group]
        rows = {j.replicate: parse_parameters(j.results.get(learned, {}).get("parameters", "")) for j in members}
        names = list(dict.fromkeys(n for r in rows.values() for n in r))
        lines += ["", f"### {group or 'all jobs'}", "", "| row | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for seed, values in rows.items():
            lines.append(f"| {learned}, seed {seed} | " + " | ".join(_cell(values[n]) if n in values else "" for n in names) + " |")
        means = {n: [sum(r[n]) / len(r[n]) for r in rows.values() if n in r] for n in names}
        lines.append(f"| {learned}, mean over seeds | " + " | ".join(f"{sum(v) / len(v):.4g}" if v else "" for v in means.values()) + " |")
        for other in others:
            values = parse_parameters(members[0].results.get(other, {}).get("parameters", ""))
            if values:
                lines.append(f"| {other} | " + " | ".join(_cell(values[n]) if n in values else "" for n in names) + " |")
    return "\n".join(lines).lstrip() + "\n"


def main(argv: Sequence[str] | None = None) -> str:
    """Command line (module docstring); returns the markdown it prints."""
    ap = argparse.ArgumentParser(description="Learned parameter values per seed of a sweep of experiments/train.py.")
    ap.add_argument("sweep_dir")
    ap.add_argument("--filter", default="learned", help="the row whose values vary by seed (default: learned)")
    args = ap.parse_args(argv)
    text = values_table(args.sweep_dir, learned=args.filter)
    print(text)
    return text


if __name__ == "__main__":
    main(sys.argv[1:])
