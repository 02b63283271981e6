"""Collect the papers' experiment results into one markdown report, next to the published numbers.

    python experiments/report.py                                           # results/*.md -> results/REPORT.md
    python experiments/report.py 'runs=[outputs/train/runs/<run>]'         # add run directories (results.csv)
    python experiments/report.py print=true write=false                    # only print the report
    python experiments/report.py 'runs=[outputs/train/multiruns/<sweep>]'  # add a seed sweep's summary.md

Options in conf/report.yaml (a Hydra app like every entry point; :func:`collect` is the function).

Inputs: the per-experiment sections ``results/<name>.md`` (written by hand after the full-size
runs: command, table, wall time, interpretation) and/or Hydra run directories holding the
``results.csv`` that ``experiments/train.py`` writes (a ``.md`` or ``.csv`` path works too), and/or
multirun directories holding the ``summary.md`` of a sweep over seeds (:mod:`experiments.runner.sweep`),
included as sections.
The report opens with a summary (one line per experiment: hand-tuned, learned and oracle RMSE,
learned ANEES with its 95 % t-interval over test runs against the value of a consistent filter
and the fraction of steps inside the per-step chi-square band, the paper's claim), then each run's table with a ``paper``
column holding the published number of the matching filter, then the collected sections.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import hydra
from omegaconf import DictConfig

__all__ = [
    "PUBLISHED",
    "Published",
    "build_report",
    "collect",
    "load_run",
    "load_sweep",
    "main",
    "normalise_table",
    "parse_markdown_tables",
    "summary_row",
]

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Published:
    """What a paper published: its claim and, per filter row name, the number it reported."""

    title: str
    claim: str
    numbers: dict[str, str] = field(default_factory=dict)


#: The papers' published results (see /work/shared/papers/*.md), keyed by paper id; ``numbers``
#: maps our row names (``filter`` column) to the published figure for the matching filter.
PUBLISHED: dict[str, Published] = {
    "p000": Published(
        "Yang & Zhang, UKF for GPS/DR vehicle positioning",
        "UKF position RMSE several times below EKF (straight line, 30 runs x 500 s); with g = 1.5 the EKF is biased, the UKF not",
        {
            "ekf-paper-ca": "EKF: 8.83 m E / 4.30 m N (mean RMSE)",
            "ukf-paper-ca": "UKF: 1.12 m E / 1.12 m N",
            "ekf": "EKF: 8.83 m E / 4.30 m N",
            "hand-tuned": "UKF: 1.12 m E / 1.12 m N",
        },
    ),
    "p001": Published(
        "Zou, Zhao & Ding, UKF with coloured measurement noise",
        "coloured-noise UKF much better than the standard UKF, whose error accumulates (numbers lost in extraction)",
    ),
    "p002": Published(
        "Niu & Lian, GPS+PDR with residual-constrained UKF",
        "RC-UKF < UKF < GPS only / PDR only; position RMSE (m) at blockage P = 0.8/0.6/0.4/0.2/0.05",
        {
            "GPS only": "12.17 / 9.42 / 5.83 / 2.88 / 2.67 m",
            "PDR only": "8.31 / 7.98 / 8.16 / 8.23 / 7.96 m",
            "UKF": "7.38 / 7.19 / 4.46 / 3.97 / 2.41 m",
            "hand-tuned": "RC-UKF: 6.78 / 6.42 / 3.12 / 2.60 / 1.94 m",
        },
    ),
    "p003": Published(
        "Yang & Xue, simplified-UKF IMM for GPS/SINS",
        "simplified-UKF IMM as accurate as the standard-UKF IMM, cheaper; mode switch in 5 vs 7 steps (up) and 5 vs 8 (down)",
        {"hand-tuned": "simplified-UKF IMM: switch in 5 (up) / 5 (down) steps", "IMM standard UKF": "switch in 7 / 8 steps"},
    ),
    "p004": Published(
        "Li, Zhu, Wang & Lyu, adaptive EKF/UKF blend for GNSS/IMU",
        "blend < UKF < EKF: position RMSE 2.36 / 5.68 / 9.53 cm (50 runs x 400 s)",
        {"ekf": "9.53 cm", "ukf": "5.68 cm", "hand-tuned": "2.36 cm (blend, delta = 0.85)"},
    ),
}

_SHOWN = ("rmse_pos", "anees", "anees_dof", "anees_run_ci_lo", "anees_run_ci_hi", "anees_step_band_frac", "nis", "nll", "time_per_step_ms")


def paper_id(name: str) -> str | None:
    """``"p004"`` for an experiment named ``p004_blend`` (``None`` for other names)."""
    m = re.match(r"(p\d{3})", name)
    return m.group(1) if m else None


def _float(value: str | float | None) -> float:
    """A number, or the leading number of a cell such as ``"3.82 [6.78]"`` (NaN if none)."""
    if isinstance(value, int | float):
        return float(value)
    m = re.match(r"\s*\**\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", value or "")
    return float(m.group(1)) if m else math.nan


def _fmt(value: str | float | None) -> str:
    v = _float(value)
    if math.isnan(v):
        return "" if value is None else str(value)
    return f"{v:.4g}"


def parse_markdown_tables(text: str) -> list[list[dict[str, str]]]:
    """Every pipe table of a markdown text as a list of ``{column: cell}`` rows."""
    tables: list[list[dict[str, str]]] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines) - 1:
        head, rule = lines[i].strip(), lines[i + 1].strip()
        if head.startswith("|") and re.fullmatch(r"\|?(\s*:?-{3,}:?\s*\|)+\s*:?-*:?\s*\|?", rule):
            cols = [c.strip() for c in head.strip("|").split("|")]
            rows = []
            i += 2
            while i < len(lines) and lines[i].strip().startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                rows.append(dict(zip(cols, cells, strict=False)))
                i += 1
            tables.append(rows)
        else:
            i += 1
    return tables


def _column_key(header: str) -> str:
    """``"rmse_pos (m)"`` -> ``"rmse_pos"``: a header's first word, lower case."""
    return re.split(r"[\s(\[]", header.strip().lower(), maxsplit=1)[0]


def normalise_table(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """Rows keyed by their headers' first words (bold marks dropped).  A band written in a header
    (``anees (band lo-hi)``, the runs x steps chi-square band of older sections) is not read: it
    treated correlated steps as independent."""
    out = []
    for r in rows:
        new: dict[str, str] = {}
        for header, cell in r.items():
            new.setdefault(_column_key(header), cell.replace("**", "").strip())
        out.append(new)
    return out


def results_table(rows_list: list[list[dict[str, str]]]) -> list[dict[str, str]] | None:
    """The first table with ``filter`` and ``rmse_pos`` columns, normalised."""
    for rows in rows_list:
        norm = normalise_table(rows)
        if norm and "filter" in norm[0] and "rmse_pos" in norm[0]:
            return norm
    return None


def _role_row(rows: list[dict[str, str]], role: str) -> dict[str, str] | None:
    """The row named ``role``, else the first whose name has it as a word; for ``"learned"`` the
    last such row: a results file puts the rerun of a learned row (e.g. the logit-space starts of
    results/p00_bounded_starts.md) below the row it supersedes, so the summary shows what the
    current code reproduces."""
    exact = [r for r in rows if r.get("filter", "") == role]
    if exact:
        return exact[0]
    word = re.compile(rf"(^|[\s,(]){re.escape(role)}($|[\s,)])")
    order = reversed(rows) if role == "learned" else rows
    return next((r for r in order if word.search(r.get("filter", "").lower())), None)


@dataclass
class Run:
    """One experiment's results: its name, rows (``results.csv``) and where they came from."""

    name: str
    rows: list[dict[str, str]]
    source: Path
    text: str = ""


def _run_name(directory: Path) -> str:
    md = directory / "results.md"
    if md.exists():
        m = re.search(r"^# difffilter results: *(\S+)", md.read_text(), re.M)
        if m:
            return m.group(1)
    cfg = directory / ".hydra" / "config.yaml"
    if cfg.exists():
        m = re.search(r"^experiment:\s*\n(?:\s+.*\n)*?\s+name:\s*(\S+)", cfg.read_text(), re.M)
        if m:
            return m.group(1)
    return directory.name


def load_run(path: str | Path) -> Run:
    """A run from a run directory / its ``results.csv`` (rows) or a results ``.md`` section."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.csv" if (p / "results.csv").exists() else p / "results.md"
    if not p.exists():
        raise FileNotFoundError(f"no results.csv or results.md at {path}")
    if p.suffix == ".csv":
        with p.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        return Run(_run_name(p.parent), rows, p)
    text = p.read_text()
    name = _run_name(p.parent) if p.name == "results.md" else p.stem
    return Run(name, results_table(parse_markdown_tables(text)) or [], p, text)


def load_sweep(directory: str | Path) -> Run:
    """A seed sweep's ``summary.md`` as a section named ``sweep <experiment>`` (no summary row: the
    sweep's own tables carry the intervals over seeds)."""
    root = Path(directory)
    jobs = sorted(p.parent for p in root.rglob("results.md"))
    name = _run_name(jobs[0]) if jobs else root.name
    text = re.sub(r"^# Sweep summary", f"# Sweep summary: {name}", (root / "summary.md").read_text(), count=1, flags=re.M)
    return Run(f"sweep {name}", [], root / "summary.md", text)


def summary_row(run: Run) -> str:
    """One summary line: hand-tuned / learned / oracle RMSE, learned ANEES with its run-level
    interval and per-step band fraction (when the row has them), claim."""
    by = {k: _role_row(run.rows, k) for k in ("hand-tuned", "learned", "oracle")}
    rmse = {k: _float(r.get("rmse_pos")) if r else math.nan for k, r in by.items()}
    gain = (rmse["learned"] / rmse["hand-tuned"] - 1.0) * 100.0 if rmse["hand-tuned"] > 0 else math.nan
    learned = by["learned"] or {}
    anees, lo, hi, dof, frac = (
        _float(learned.get(k)) for k in ("anees", "anees_run_ci_lo", "anees_run_ci_hi", "anees_dof", "anees_step_band_frac")
    )
    if math.isnan(anees):
        band = ""
    elif math.isnan(lo) or math.isnan(hi) or math.isnan(dof):
        band = f"{anees:.4g}"
    else:
        band = f"{anees:.4g} [{lo:.4g}, {hi:.4g}] (d = {dof:.4g})" + (" in" if lo <= dof <= hi else " out")
        if not math.isnan(frac):
            band += f"; {100 * frac:.0f} % steps in band"
    pub = PUBLISHED.get(paper_id(run.name) or "")
    cells = [
        run.name,
        *(_fmt(rmse[k]) if not math.isnan(rmse[k]) else "-" for k in ("hand-tuned", "learned", "oracle")),
        "-" if math.isnan(gain) else f"{gain:+.1f} %",
        band or "-",
        pub.claim if pub else "",
    ]
    return "| " + " | ".join(cells) + " |"


def _published_number(pub: Published | None, name: str) -> str:
    if pub is None:
        return ""
    numbers = {k.lower(): v for k, v in pub.numbers.items()}
    return numbers.get(name.lower(), "")


def run_table(run: Run) -> str:
    """The run's rows with the paper's published number beside each matching filter."""
    pub = PUBLISHED.get(paper_id(run.name) or "")
    cols = [c for c in _SHOWN if any(c in r for r in run.rows)]
    lines = ["| filter | " + " | ".join(cols) + " | paper |", "|---|" + "---|" * (len(cols) + 1)]
    for r in run.rows:
        name = r.get("filter", "")
        paper = _published_number(pub, name)
        lines.append("| " + " | ".join([name, *(_fmt(r.get(c)) for c in cols), paper]) + " |")
    return "\n".join(lines)


def _nest_headings(text: str) -> str:
    """One more ``#`` on every markdown heading of ``text`` (nested under the report's), leaving
    lines inside fenced code blocks alone (a shell comment there is not a heading)."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        out.append("#" + line if line.startswith("#") and not fenced else line)
    return "\n".join(out)


def build_report(runs: Sequence[Run], *, sections: Sequence[Run] = ()) -> str:
    """The report: summary of every run and section, the run tables, then the sections' text."""
    out = [
        "# difffilter: the papers' experiments",
        "",
        "Learned vs hand-tuned (the paper's settings) vs oracle on held-out test trajectories; "
        "RMSE in the truth's units; ANEES [95 % t-interval over test runs] (d: its value for a consistent filter; in/out: d inside"
        " the interval or not) and the fraction of steps whose mean over runs lies in the per-step 95 % chi-square band"
        " (rows without them come from older sections whose band treated correlated steps as independent: value only)."
        " Generated by `experiments/report.py`.",
        "",
        "| experiment | hand-tuned rmse | learned rmse | oracle rmse | learned vs hand-tuned "
        "| learned ANEES [run CI] (d) | paper's claim |",
        "|---|---|---|---|---|---|---|",
    ]
    # a section repeating a run's experiment is summarised once, from the run (its csv has the intervals)
    names = {r.name for r in runs}
    out += [summary_row(r) for r in [*runs, *(s for s in sections if s.name not in names)] if r.rows]
    for run in runs:
        pub = PUBLISHED.get(paper_id(run.name) or "")
        out += ["", f"## {run.name} (run `{run.source.parent}`)", ""]
        if pub:
            out += [f"Paper: {pub.title}. Published: {pub.claim}.", ""]
        out.append(run_table(run))
    for sec in sections:
        body = _nest_headings(sec.text.strip())
        origin = str(sec.source) if sec.source.name == "summary.md" else f"results/{sec.source.name}"
        out += [""] + ([] if body.startswith("## ") else [f"## {sec.name}", ""]) + [body, "", f"(from `{origin}`)"]
    return "\n".join(out) + "\n"


def collect(
    runs: Sequence[str | Path] = (),
    *,
    results_dir: str | Path | None = None,
    output: str | Path | None = None,
    show: bool = False,
    write: bool = True,
) -> str:
    """The report of ``runs`` (run directories, results files, sweep directories) and the
    sections in ``results_dir`` (default: the project's ``results/``); written to ``output``
    (default ``<results_dir>/REPORT.md``) when ``write``, printed when ``show`` or not ``write``."""
    results = Path(results_dir) if results_dir is not None else ROOT / "results"
    out = Path(output) if output is not None else results / "REPORT.md"
    sections = [load_run(p) for p in sorted(results.glob("*.md")) if p.resolve() != out.resolve()] if results.is_dir() else []
    sweeps = [Path(p) for p in runs if (Path(p) / "summary.md").exists()]
    loaded = [load_run(p) for p in runs if Path(p) not in sweeps]
    sections += [load_sweep(p) for p in sweeps]
    text = build_report(loaded, sections=sections)
    if write:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    if show or not write:
        print(text)
    return text


@hydra.main(version_base="1.3", config_path="../conf", config_name="report")
def main(cfg: DictConfig) -> str:
    """Command line (module docstring; options in conf/report.yaml); returns the report text."""
    return collect(list(cfg.runs), results_dir=cfg.results_dir, output=cfg.output, show=bool(cfg.print), write=bool(cfg.write))


if __name__ == "__main__":
    main()
