"""The learned parameter values of every job of a seed sweep, next to the hand-tuned and oracle ones.

    python experiments/learned_values.py sweep_dir=outputs/train/multiruns/<sweep>     # markdown to stdout
    python experiments/learned_values.py sweep_dir=outputs/train/multiruns/<sweep> filter=oracle

Options in conf/learned_values.yaml.

Reads each job's ``results.csv`` (its ``parameter_values`` column, else ``parameters``, written by
``experiments/train.py`` for the parameters named in ``learn``) and groups the jobs as the sweep summary does
(:func:`experiments.runner.sweep.load_jobs`): per group, one row per seed with the learned values,
then the mean over seeds of every value, then the hand-tuned and oracle rows of the first job.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import ast  # noqa: E402
import re  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.runner.sweep import load_jobs  # noqa: E402

__all__ = ["main", "parse_parameters", "values_table"]


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"


def _square(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(r, list) and len(r) == len(value) for r in value)


def parse_parameters(text: str) -> dict[str, list[float]]:
    """A results row's parameter text -> ``{name: values}``.

    Reads both columns ``experiments/train.py`` writes: ``parameter_values`` (full nested lists,
    ``"psi=[0.7, 0.69]; R=[[9, 0], [0, 9]]; delta=0.85"``: a square matrix gives its diagonal) and
    the short ``parameters`` (``"psi=[0.7, 0.69]; R=diag[9, 9]; delta=0.85"``).
    """
    out: dict[str, list[float]] = {}
    for item in (text or "").split(";"):
        name, sep, value = item.strip().partition("=")
        if not sep or not re.fullmatch(r"[\w.\[\],]+", name):
            continue
        try:
            parsed = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            parsed = None
        if _square(parsed):
            out[name] = [float(parsed[i][i]) for i in range(len(parsed))]
        else:
            out[name] = [float(v) for v in re.findall(_NUMBER, value)]
    return out


def _cell(values: list[float]) -> str:
    if len(values) == 1 or all(v == values[0] for v in values):
        return f"{values[0]:.4g}"
    return f"{sum(values) / len(values):.4g} ({min(values):.4g}-{max(values):.4g})"


def _text(row: dict[str, str]) -> str:
    # full values where the run wrote them (parameter_values), else the short column
    return row.get("parameter_values") or row.get("parameters", "")


def values_table(sweep_dir: str | Path, *, learned: str = "learned", others: Sequence[str] = ("hand-tuned", "oracle")) -> str:
    """Markdown: per group of the sweep, the ``learned`` row's parameters per seed and their mean,
    then the ``others`` rows of the group's first job.  A vector parameter shows its mean and range."""
    jobs = load_jobs(sweep_dir)
    if not jobs:
        raise FileNotFoundError(f"no finished job below {sweep_dir}")
    lines: list[str] = []
    for group in dict.fromkeys(j.group for j in jobs):
        members = [j for j in jobs if j.group == group]
        rows = {j.replicate: parse_parameters(_text(j.results.get(learned, {}))) for j in members}
        names = list(dict.fromkeys(n for r in rows.values() for n in r))
        lines += ["", f"### {group or 'all jobs'}", "", "| row | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for seed, values in rows.items():
            lines.append(f"| {learned}, seed {seed} | " + " | ".join(_cell(values[n]) if n in values else "" for n in names) + " |")
        means = {n: [sum(r[n]) / len(r[n]) for r in rows.values() if n in r] for n in names}
        lines.append(f"| {learned}, mean over seeds | " + " | ".join(f"{sum(v) / len(v):.4g}" if v else "" for v in means.values()) + " |")
        for other in others:
            values = parse_parameters(_text(members[0].results.get(other, {})))
            if values:
                lines.append(f"| {other} | " + " | ".join(_cell(values[n]) if n in values else "" for n in names) + " |")
    return "\n".join(lines).lstrip() + "\n"


@hydra.main(version_base="1.3", config_path="../conf", config_name="learned_values")
def main(cfg: DictConfig) -> str:
    """Print (and return) the markdown of ``cfg.sweep_dir``."""
    text = values_table(str(cfg.sweep_dir), learned=str(cfg.filter))
    print(text)
    return text


if __name__ == "__main__":
    main()
