"""The tables of ``results/*.md`` rendered from committed CSVs, and the check that they still are.

    python experiments/report.py --render     # rewrite every generated table (and REPORT.md, results/detail/)
    python experiments/report.py --check      # exit 1 and name each table that differs from its CSVs

A generated table sits between two HTML comments that name where it comes from::

    <!-- table: p000_gyro_rmse renderer=metric source=results/data/p000_gyro.csv -->
    | filter | ... |
    <!-- /table -->

``source`` is a CSV in the schema of a sweep's ``summary.csv`` (:mod:`experiments.runner.sweep`:
``group, filter, quantity, estimate, lo, hi, seeds, runs, reference``); the other ``key=value``
words select and label what is shown (``group=a,b``, ``filters=x,y``, ``blocks=all,position``,
``metric=rmse_pos``, ``unit=m``).  A table whose numbers have no committed CSV is wrapped in
``<!-- table: <id> not generated: <why> -->`` … ``<!-- /table -->`` and left as written: the check
then only asks that every pipe table of a results file sits inside one marker or the other, so a
new hand-written table has to say why it is not generated.

Verdicts (one rule for every table, :func:`paired_verdict`, :func:`anees_verdict`):

* paired difference (filter - reference, lower is better): *win* when its 95 % interval lies below
  zero, *loss* when above, *tie* when it contains zero;
* ANEES of a filter tested on N runs with d states: the 95 % chi-square band of a consistent
  filter's mean NEES over N runs, ``[chi2_0.025(N d) / N, chi2_0.975(N d) / N]``; *consistent* when
  the ANEES interval lies inside the band, *over-confident* / *under-confident* when it lies
  entirely above / below it, *undecided* otherwise (it straddles an edge of the band, or has no
  interval): the interval must be narrow enough to decide.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from scipy.stats import chi2

__all__ = [
    "FIELDS",
    "METHODS",
    "NON_LEARNED",
    "REFERENCE",
    "VARIANTS",
    "Row",
    "anees_band",
    "anees_verdict",
    "check_text",
    "fmt",
    "fmt_ci",
    "paired_verdict",
    "parse_args",
    "read_rows",
    "render_anees",
    "render_metric",
    "render_paired",
    "render_table",
    "render_text",
    "render_times",
    "unmarked_tables",
]

#: Summary columns of the non-learned methods (column title, filter name in the CSVs).
METHODS: tuple[tuple[str, str], ...] = (
    ("paper's constants", "hand-tuned"),
    ("textbook rule", "textbook"),
    ("validation search", "validation-search"),
    ("EM", "em"),
    ("Sage-Husa", "sage-husa"),
    ("VB-AKF", "vb-akf"),
    ("covariance matching", "covariance-matching"),
)
#: Non-learned rows shown inside another method's column (title, filter name, the column's filter
#: name): the adaptive filters around p000's UKF with Julier kappa 0 (issue 25, results/p00_practitioners.md,
#: "Adaptive rows around a kappa 0 UKF"), candidates for the best non-learned row like the columns' own.
VARIANTS: tuple[tuple[str, str, str], ...] = (
    ("Sage-Husa, kappa 0", "sage-husa-k0", "sage-husa"),
    ("VB-AKF, kappa 0", "vb-akf-k0", "vb-akf"),
    ("covariance matching, kappa 0", "covariance-matching-k0", "covariance-matching"),
)
#: Every non-learned row (filter name) the best non-learned row is chosen from.
NON_LEARNED: tuple[str, ...] = (*(n for _, n in METHODS), *(n for _, n, _ in VARIANTS))
#: The row every sweep pairs its differences with (the paper's constants).
REFERENCE = "hand-tuned"

ROOT = Path(__file__).resolve().parents[1]

#: Columns of a data file: those of a sweep's ``summary.csv``.
FIELDS = ("group", "filter", "quantity", "estimate", "lo", "hi", "seeds", "runs", "reference")

MARKER = re.compile(r"^<!-- table: (?P<id>\S+) (?P<args>[^\n]*?) -->\n(?P<body>.*?)^<!-- /table -->$", re.S | re.M)
_PIPE_RULE = re.compile(r"^\|?(\s*:?-{3,}:?\s*\|)+\s*(:?-*:?\s*)?\|?\s*$")


@dataclass(frozen=True)
class Row:
    """One line of a data file (:data:`FIELDS`); numbers NaN where the cell is empty."""

    group: str
    filter: str
    quantity: str
    estimate: float
    lo: float
    hi: float
    seeds: str
    runs: str
    reference: str


def _num(text: str | None) -> float:
    try:
        return float(text) if text not in (None, "") else math.nan
    except ValueError:
        return math.nan


def read_rows(path: str | Path) -> list[Row]:
    """The rows of a data file.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: its header is not :data:`FIELDS`.
    """
    p = Path(path)
    with p.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != FIELDS:
            raise ValueError(f"{p}: columns must be {', '.join(FIELDS)}, got {reader.fieldnames}")
        return [
            Row(
                r["group"],
                r["filter"],
                r["quantity"],
                _num(r["estimate"]),
                _num(r["lo"]),
                _num(r["hi"]),
                r["seeds"],
                r["runs"],
                r["reference"],
            )
            for r in reader
        ]


def fmt(v: float) -> str:
    """Four significant digits (the sweeps' ``summary.md``); ``-`` for a missing value."""
    return "-" if not math.isfinite(v) else f"{v:.4g}"


def fmt_ci(est: float, lo: float, hi: float) -> str:
    """``estimate [lo, hi]``, or the estimate alone when the interval is missing."""
    if not math.isfinite(est):
        return "-"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return fmt(est)
    return f"{fmt(est)} [{fmt(lo)}, {fmt(hi)}]"


def paired_verdict(lo: float, hi: float) -> str:
    """``win`` / ``loss`` / ``tie`` for a paired difference (filter - reference, lower is better)
    with interval ``[lo, hi]``; ``no interval`` when either end is missing."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "no interval"
    if hi < 0:
        return "win"
    if lo > 0:
        return "loss"
    return "tie"


def anees_band(dof: float, runs: int, prob: float = 0.95) -> tuple[float, float]:
    """The ``prob`` chi-square band of a consistent filter's mean NEES over ``runs`` runs, ``dof`` states each.

    Raises:
        ValueError: ``dof`` or ``runs`` not positive.
    """
    if not (dof > 0 and runs > 0):
        raise ValueError(f"dof and runs must be positive, got dof={dof}, runs={runs}")
    k = dof * runs
    return float(chi2.ppf((1 - prob) / 2, k)) / runs, float(chi2.ppf((1 + prob) / 2, k)) / runs


def anees_verdict(lo: float, hi: float, dof: float, runs: int | None) -> str:
    """``consistent`` / ``over-confident`` / ``under-confident`` when the ANEES interval ``[lo, hi]``
    lies inside / above / below :func:`anees_band`; ``undecided`` otherwise (module docstring)."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or not runs or not (dof > 0):
        return "undecided"
    band_lo, band_hi = anees_band(dof, runs)
    if band_lo <= lo and hi <= band_hi:
        return "consistent"
    if lo > band_hi:
        return "over-confident"
    if hi < band_lo:
        return "under-confident"
    return "undecided"


def _runs(rows: Sequence[Row], group: str, name: str) -> int | None:
    """The number of test runs of ``name`` in ``group`` (its metric row's ``runs``)."""
    for r in rows:
        if r.group == group and r.filter == name and r.runs.strip().isdigit():
            return int(r.runs)
    return None


def _pick(rows: Sequence[Row], group: str, name: str, quantity: str) -> Row | None:
    return next((r for r in rows if r.group == group and r.filter == name and r.quantity == quantity and not r.reference), None)


def _groups(rows: Sequence[Row], opts: dict[str, str]) -> list[str]:
    present = list(dict.fromkeys(r.group for r in rows))
    if "group" not in opts:
        return present
    wanted = opts["group"].split(",")
    missing = [g for g in wanted if g not in present]
    if missing:
        raise ValueError(f"group {missing} not in the data (groups: {present})")
    return wanted


def _filters(rows: Sequence[Row], group: str, opts: dict[str, str], quantity: str) -> list[str]:
    """The filters of ``group`` with a ``quantity`` row (a prefix when it ends in ``_``), in data order."""
    present = list(
        dict.fromkeys(
            r.filter
            for r in rows
            if r.group == group and (r.quantity == quantity or (quantity.endswith("_") and r.quantity.startswith(quantity)))
        )
    )
    return [f for f in opts["filters"].split(",") if f in present] if "filters" in opts else present


def _table(header: Sequence[str], lines: Sequence[Sequence[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(cells) + " |" for cells in lines]
    return "\n".join(out)


def _group_label(group: str) -> str:
    return group.split("=", 1)[-1] if group else "all"


def render_metric(rows: Sequence[Row], opts: dict[str, str]) -> str:
    """Each filter's metric [interval], its paired difference to the reference in the metric's
    unit and in %, the verdict, and G where the data has it; a ``test`` column when several groups."""
    metric, unit = opts.get("metric", "rmse_pos"), opts.get("unit", "m")
    groups = _groups(rows, opts)
    multi = len(groups) > 1
    header = [*(["test"] if multi else []), "filter", "seeds x runs", f"{metric} ({unit})", f"- reference ({unit})", "in %", "verdict", "G"]
    lines = []
    for g in groups:
        for name in _filters(rows, g, opts, metric):
            m = _pick(rows, g, name, metric)
            d, p, gap = (_pick(rows, g, name, q) for q in ("diff", "diff_pct", "gap_closed"))
            size = f"{m.seeds or '?'} x {m.runs or '?'}" if m else ""
            diff = fmt_ci(d.estimate, d.lo, d.hi) if d else ""
            pct = fmt_ci(p.estimate, p.lo, p.hi) if p else ""
            ref = p or d
            verdict = paired_verdict(ref.lo, ref.hi) if ref and ref.estimate != 0 else ""
            g_cell = "" if gap is None else fmt_ci(gap.estimate, gap.lo, gap.hi)
            cells = [name, size, fmt_ci(m.estimate, m.lo, m.hi) if m else "-", diff, pct, verdict, g_cell]
            lines.append([_group_label(g), *cells] if multi else cells)
    return _table(header, lines)


def render_anees(rows: Sequence[Row], opts: dict[str, str]) -> str:
    """Each filter's ANEES per state block with its interval, d, the band of :func:`anees_band`
    for its N test runs, the verdict of :func:`anees_verdict` and the steps inside the per-step band."""
    groups = _groups(rows, opts)
    multi = len(groups) > 1
    header = [*(["test"] if multi else []), "filter", "block", "d", "ANEES [95 %]", "band (N runs)", "verdict", "steps in band"]
    blocks = opts["blocks"].split(",") if "blocks" in opts else None
    lines = []
    for g in groups:
        for name in _filters(rows, g, opts, "anees_"):
            n = _runs(rows, g, name)
            for r in [r for r in rows if r.group == g and r.filter == name and r.quantity.startswith("anees_")]:
                block = r.quantity.removeprefix("anees_")
                if blocks is not None and block not in blocks:
                    continue
                dof = _num(r.reference)
                band = f"{fmt(anees_band(dof, n)[0])}-{fmt(anees_band(dof, n)[1])} ({n})" if n and dof > 0 else "-"
                frac = _pick(rows, g, name, f"step_band_frac_{block}")
                in_band = f"{100 * frac.estimate:.0f} %" if frac and math.isfinite(frac.estimate) else ""
                cells = [name, block, fmt(dof), fmt_ci(r.estimate, r.lo, r.hi), band, anees_verdict(r.lo, r.hi, dof, n), in_band]
                lines.append([_group_label(g), *cells] if multi else cells)
    return _table(header, lines)


def render_paired(rows: Sequence[Row], opts: dict[str, str]) -> str:
    """Per group (a training size, a transfer pair), each filter's metric [interval] and its tuning
    CPU seconds (mean over seeds, where the data has them), then one line per paired difference
    against a *named* reference (rows whose ``reference`` is a filter name:
    :mod:`experiments.efficiency_transfer`): the difference in the metric's unit and in %, and the
    verdict of :func:`paired_verdict`."""
    metric, unit = opts.get("metric", "rmse_pos"), opts.get("unit", "m")
    header = [opts.get("group_title", "group"), "filter", "seeds x runs", f"{metric} ({unit})", "tuning CPU-s"]
    header += ["paired against", f"difference ({unit})", "in %", "verdict"]
    lines = []
    for g in _groups(rows, opts):
        for name in _filters(rows, g, opts, metric):
            m = _pick(rows, g, name, metric)
            cpu = _pick(rows, g, name, "tuning_cpu_s")
            first = [g, name, f"{m.seeds or '?'} x {m.runs or '?'}" if m else "", fmt_ci(m.estimate, m.lo, m.hi) if m else "-"]
            first.append(fmt(cpu.estimate) if cpu else "")
            paired = [r for r in rows if r.group == g and r.filter == name and r.quantity == "diff_pct" and r.reference]
            if not paired:
                lines.append([*first, "", "", "", ""])
            for k, p in enumerate(paired):
                d = next((r for r in rows if (r.group, r.filter, r.quantity, r.reference) == (g, name, "diff", p.reference)), None)
                diff = fmt_ci(d.estimate, d.lo, d.hi) if d else ""
                cells = [p.reference, diff, fmt_ci(p.estimate, p.lo, p.hi), paired_verdict(p.lo, p.hi)]
                lines.append([*(first if k == 0 else [g, name, "", "", ""]), *cells])
    return _table(header, lines)


def render_times(paths: Sequence[Path]) -> str:
    """The jobs of ``experiments/reproduce.py``'s ``times.tsv`` files (``job, status, wall_s,
    cpu_s``; its closing ``all`` line is the run's total): one row per job, the total last in
    minutes.

    Raises:
        ValueError: a file without that header, or a line that is not four tab-separated fields.
    """
    lines, total = [], None
    for path in paths:
        with open(path) as fh:
            rows = list(csv.reader(fh, delimiter="\t"))
        if not rows or rows[0] != ["job", "status", "wall_s", "cpu_s"]:
            raise ValueError(f"{path}: not a reproduce.py times.tsv (header job, status, wall_s, cpu_s)")
        for n, row in enumerate(rows[1:], start=2):
            if len(row) != 4:
                raise ValueError(f"{path}:{n}: expected 4 tab-separated fields, got {len(row)}")
            if row[0] == "all":
                total = row
            elif row[0] != "job":  # a resumed run appends another header
                lines.append([row[0], "ok" if row[1] == "0" else f"exit {row[1]}", f"{float(row[2]):.0f}", f"{float(row[3]):.0f}"])
    if total is not None:
        wall, cpu = (f"**{float(v) / 60:.1f} min**" for v in total[2:])
        lines.append([f"**all {len(lines)} jobs** ({total[1]})", "", wall, cpu])
    return _table(["job", "status", "wall (s)", "CPU (s)"], lines)


def render_targets(paths: Sequence[Path]) -> str:
    """The performance targets of ``experiments/benchmark.py``'s ``targets.csv`` files (``target,
    measured, goal, met``): one row per target that the run measured (``met`` is ``n/a`` for the
    targets of cases it did not run, and those are left out), the file's name beside it.

    Raises:
        ValueError: a file without that header.
    """
    lines = []
    for path in paths:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            if reader.fieldnames is None or list(reader.fieldnames)[:4] != ["target", "measured", "goal", "met"]:
                raise ValueError(f"{path}: not a benchmark targets.csv (header target, measured, goal, met)")
            for row in reader:
                if row["met"] == "n/a":
                    continue
                v = float(row["measured"])
                lines.append([row["target"], f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}", row["goal"], row["met"], path.parent.name])
    return _table(["target", "measured", "goal", "met", "run"], lines)


RENDERERS = {"metric": render_metric, "anees": render_anees, "paired": render_paired}
#: renderers of files other than summary CSVs: they take the source paths
FILE_RENDERERS = {"times": render_times, "targets": render_targets}


def parse_args(args: str) -> tuple[list[str], dict[str, str]]:
    """The ``source=`` paths and the other ``key=value`` options of a marker."""
    sources, opts = [], {}
    for word in args.split():
        key, _, value = word.partition("=")
        if not value:
            raise ValueError(f"marker option {word!r} is not key=value")
        if key == "source":
            sources.append(value)
        else:
            opts[key] = value
    return sources, opts


def render_table(args: str, root: Path = ROOT) -> str:
    """The markdown table a marker's options give.

    Raises:
        ValueError: no ``source``, an unknown ``renderer``, or a selection the data lacks.
    """
    sources, opts = parse_args(args)
    if not sources:
        raise ValueError(f"marker {args!r}: no source=")
    if opts.get("renderer") in FILE_RENDERERS:
        return FILE_RENDERERS[opts["renderer"]]([root / s for s in sources])
    renderer = RENDERERS.get(opts.get("renderer", ""))
    if renderer is None:
        raise ValueError(f"marker {args!r}: renderer must be one of {sorted([*RENDERERS, *FILE_RENDERERS])}")
    rows = [r for s in sources for r in read_rows(root / s)]
    return renderer(rows, opts)


def render_text(text: str, root: Path = ROOT) -> str:
    """``text`` with every generated table replaced by what its CSVs give (``not generated`` ones kept)."""

    def sub(m: re.Match[str]) -> str:
        if m["args"].startswith("not generated:"):
            return m.group(0)
        return f"<!-- table: {m['id']} {m['args']} -->\n{render_table(m['args'], root)}\n<!-- /table -->"

    return MARKER.sub(sub, text)


def unmarked_tables(text: str) -> list[int]:
    """Line numbers (1-based) of pipe tables outside every marker."""
    spans = [(text.count("\n", 0, m.start()), text.count("\n", 0, m.end())) for m in MARKER.finditer(text)]
    lines = text.splitlines()
    out, fenced = [], False
    for i, line in enumerate(lines[:-1]):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if fenced or not line.strip().startswith("|") or not _PIPE_RULE.match(lines[i + 1].strip()):
            continue
        if not any(a <= i <= b for a, b in spans):
            out.append(i + 1)
    return out


def check_text(text: str, root: Path = ROOT) -> list[str]:
    """What is wrong with a results file: each generated table that differs from its CSVs (by id),
    each marker whose table cannot be rendered, and each pipe table outside a marker."""
    problems = []
    for m in MARKER.finditer(text):
        if m["args"].startswith("not generated:"):
            continue
        try:
            want = render_table(m["args"], root)
        except (OSError, ValueError) as err:
            problems.append(f"table {m['id']}: {err}")
            continue
        if m["body"].rstrip("\n") != want:
            problems.append(f"table {m['id']}: differs from {', '.join(parse_args(m['args'])[0])}")
    problems += [f"line {n}: pipe table outside a <!-- table: ... --> marker" for n in unmarked_tables(text)]
    return problems
