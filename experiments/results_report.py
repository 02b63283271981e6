"""``results/REPORT.md`` and ``results/detail/*.md``, generated from the committed CSVs of ``results/data/``.

The report is a summary: one row per paper family, the realistic families (mis-specified, the
paper's own conditions) first, the designed in-family ones after.  Each row shows every
non-learned method the family's CSV has a row for (today only the paper's constants; the columns
of the textbook rule, validation search, EM, Sage-Husa, VB-AKF and covariance matching say "not run" until their rows
exist), the best of them, the learned filter(s), learned - best non-learned as a paired difference
in % with its 95 % interval and the verdict of :func:`~experiments.results_tables.paired_verdict`,
and the learned filter's ANEES with the verdict of :func:`~experiments.results_tables.anees_verdict`.
The per-family detail (every test set, every filter, every state block) is in
``results/detail/<family>.md``.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import shutil  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import dataclass, replace  # noqa: E402

from experiments.efficiency_transfer import DATA_FILES  # noqa: E402
from experiments.practitioners import join_learned_adaptive, merge_rows  # noqa: E402
from experiments.results_tables import (  # noqa: E402
    METHODS,
    REFERENCE,
    ROOT,
    VARIANTS,
    Row,
    anees_band,
    anees_verdict,
    check_text,
    fmt,
    fmt_ci,
    paired_verdict,
    read_rows,
    render_anees,
    render_metric,
    render_text,
)

__all__ = [
    "FAMILIES",
    "METHODS",
    "Family",
    "build_detail",
    "build_report",
    "check",
    "collect",
    "generated_files",
    "main",
    "render",
    "results_files",
    "summary_cells",
]


@dataclass(frozen=True)
class Family:
    """One paper family of the summary.

    Attributes:
        name: data file stem (``results/data/<name>.csv``) and detail page stem.
        paper: ``p000`` ... ``p004``.
        kind: ``mis-specified``, ``paper's own`` or ``in-family``.
        label: what the family is, in a few words.
        results: the hand-written results file that discusses it.
        sweep: the sweep directory whose ``summary.csv`` the data file is (``experiments/reproduce.py``).
        group: the test set the summary row shows ("" when the sweep has one).
        practitioners: whether the family also ran with the practitioners' rows (issue 25,
            ``results/p00_practitioners.md``): its summary row then comes from
            ``results/data/<name>_practitioners.csv`` (sweep ``outputs/practitioners/<name>``).
        adaptive_outcome: what the learned adaptive cell says when its job ran but left no row
            (e.g. training diverged); "" shows *not run*.
    """

    name: str
    paper: str
    kind: str
    label: str
    results: str
    sweep: str
    group: str = ""
    practitioners: bool = False
    adaptive_outcome: str = ""

    def practitioners_family(self) -> Family:
        """The family's practitioners sweep as a family of its own (its data file and detail page)."""
        return replace(
            self,
            name=f"{self.name}_practitioners",
            label=f"{self.label}, practitioners' rows",
            results="p00_practitioners.md",
            sweep=f"{PRACTITIONERS_ROOT}/{self.name}",
            practitioners=False,
        )


_R = "outputs/rerun_logit"
#: Where the practitioners sweeps (``experiments/reproduce.py`` jobs ``<family>_practitioners``) write.
PRACTITIONERS_ROOT = "outputs/practitioners"
#: the learned adaptive jobs that ran and left no row (results/p00_practitioners.md, session la25c)
_DIVERGED = "ran, no row: training diverged in every seed"
FAMILIES: tuple[Family, ...] = (
    Family(
        "p000_gyro",
        "p000",
        "mis-specified",
        "MEMS gyro bias",
        "p000_gpsdr.md",
        "outputs/final/p000_gyro",
        "test=scripted",
        practitioners=True,
        adaptive_outcome=_DIVERGED,
    ),
    Family(
        "p000_gps",
        "p000",
        "mis-specified",
        "GPS multipath/NLOS/outages",
        "p000_gpsdr.md",
        "outputs/final/p000_gps",
        "test=scripted",
        practitioners=True,
        adaptive_outcome=_DIVERGED,
    ),
    Family(
        "p000_odometer",
        "p000",
        "mis-specified",
        "odometer scale/slip",
        "p000_gpsdr.md",
        "outputs/final/p000_odometer",
        "test=scripted",
        practitioners=True,
        adaptive_outcome=_DIVERGED,
    ),
    Family(
        "p001_elevation",
        "p001",
        "mis-specified",
        "elevation-dependent noise",
        "p001_elevation.md",
        f"{_R}/p001_elevation",
        practitioners=True,
    ),
    Family(
        "p002_disturbed_rcukf",
        "p002",
        "mis-specified",
        "compass bursts + turn transients, RC-UKF",
        "p002_pdr.md",
        f"{_R}/p002_disturbed_rcukf",
        "test=P=0.4",
        practitioners=True,
    ),
    Family(
        "p003_physical",
        "p003",
        "mis-specified",
        "vibration, C/N0 shading",
        "p003_imm_sins.md",
        "outputs/p003_final/p003_physical",
        practitioners=True,
    ),
    Family("p004_urban", "p004", "mis-specified", "urban-canyon GNSS", "p004_urban.md", f"{_R}/p004_urban", practitioners=True),
    Family(
        "p000_nominal",
        "p000",
        "paper's own",
        "paper's sensors, kinematic truth",
        "p000_gpsdr.md",
        "outputs/final/p000_nominal",
        "test=scripted",
        practitioners=True,
        adaptive_outcome=_DIVERGED,
    ),
    Family(
        "p001_colored",
        "p001",
        "paper's own",
        "coloured noise at the paper's values",
        "p001_colored.md",
        f"{_R}/p001_colored",
        practitioners=True,
    ),
    Family(
        "p002_pdr_rcukf",
        "p002",
        "paper's own",
        "paper conditions, RC-UKF",
        "p002_pdr.md",
        f"{_R}/p002_pdr_rcukf",
        "test=P=0.4",
        practitioners=True,
    ),
    Family(
        "p003_imm_sins",
        "p003",
        "paper's own",
        "paper-faithful IMM",
        "p003_imm_sins.md",
        "outputs/p003_final/p003_imm_sins",
        practitioners=True,
    ),
    Family("p004_blend", "p004", "paper's own", "the paper's blend and values", "p004_blend.md", f"{_R}/p004_blend", practitioners=True),
    Family(
        "p004_outage",
        "p004",
        "paper's own",
        "cold start (no GNSS 0-30 s)",
        "p004_blend.md",
        f"{_R}/p004_outage",
        practitioners=True,
    ),
    Family(
        "p000_infamily",
        "p000",
        "in-family",
        "CA truth, q and R off",
        "p000_gpsdr.md",
        "outputs/final/p000_infamily",
        practitioners=True,
        adaptive_outcome="ran, no row: one seed diverged, the join refused the other four",
    ),
    Family(
        "p001_multipath",
        "p001",
        "in-family",
        "coloured multipath, per-channel Psi",
        "p001_multipath.md",
        f"{_R}/p001_multipath",
        practitioners=True,
    ),
    Family(
        "p001_multipath_shared",
        "p001",
        "in-family",
        "coloured multipath, one shared Psi",
        "p001_multipath.md",
        f"{_R}/p001_multipath_shared",
        practitioners=True,
    ),
    Family(
        "p002_infamily_exactref",
        "p002",
        "in-family",
        "in-family walks (G vs exact UKF)",
        "p002_pdr.md",
        f"{_R}/p002_infamily_exactref",
        practitioners=True,
    ),
    Family(
        "p003_modes", "p003", "in-family", "two-level noise modes", "p003_imm_sins.md", "outputs/p003_final/p003_modes", practitioners=True
    ),
    Family("p004_mems", "p004", "in-family", "MEMS IMU noise", "p004_mems.md", f"{_R}/p004_mems", practitioners=True),
)

LEARNED: tuple[tuple[str, str], ...] = (("learned", "learned"), ("learned adaptive", "learned-adaptive"))
#: The learned adaptive filter around p000's UKF with Julier kappa 0 (issue 25, "Adaptive rows around a
#: kappa 0 UKF"), a learned row shown in the learned adaptive cells after "; kappa 0: "
ADAPTIVE_K0 = "learned-adaptive-k0"
#: What a cell shows before a kappa 0 row's value
K0_LABEL = "; kappa 0: "


def _get(rows: Sequence[Row], group: str, name: str, quantity: str, reference: str = "") -> Row | None:
    return next((r for r in rows if (r.group, r.filter, r.quantity, r.reference) == (group, name, quantity, reference)), None)


def _paired(rows: Sequence[Row], group: str, name: str, best: str) -> Row | None:
    """``name`` - ``best`` in %: the sweep's ``diff_pct`` when ``best`` is the sweep's reference,
    else a ``diff_pct`` row whose ``reference`` names ``best``."""
    return _get(rows, group, name, "diff_pct") if best == REFERENCE else _get(rows, group, name, "diff_pct", best)


def _adaptive_cell(rows: Sequence[Row], group: str, name: str, best: str) -> str:
    """A learned adaptive row - the best non-learned row, % [95 %] (verdict)."""
    la = _paired(rows, group, name, best) if best else None
    return "no paired interval" if la is None else f"{fmt_ci(la.estimate, la.lo, la.hi)} ({paired_verdict(la.lo, la.hi)})"


def _cell(rows: Sequence[Row], group: str, name: str, value: Row | None) -> str:
    """A method's RMSE cell; with its tuning (or training) CPU seconds when the data have them."""
    if value is None:
        return "not run"
    cpu = _get(rows, group, name, "tuning_cpu_s")
    return fmt_ci(value.estimate, value.lo, value.hi) + (f"; {fmt(cpu.estimate)} CPU-s" if cpu else "")


def summary_cells(fam: Family, rows: Sequence[Row], metric: str = "rmse_pos") -> list[str]:
    """The summary row of one family (columns of :func:`build_report`'s table)."""
    g = fam.group
    value = {name: _get(rows, g, name, metric) for _, name in (*METHODS, *LEARNED)}
    shown = [_cell(rows, g, name, value[name]) for _, name in (*METHODS, *LEARNED)]
    ran = [(title, name) for title, name in METHODS if value[name] is not None]
    columns = [name for _, name in METHODS]
    for title, name, column in VARIANTS:  # shown inside their column's cell, candidates for the best
        variant = _get(rows, g, name, metric)
        if variant is not None:
            value[name] = variant
            ran.append((title, name))
            shown[columns.index(column)] += K0_LABEL + _cell(rows, g, name, variant)
    best_title, best = min(ran, key=lambda tn: value[tn[1]].estimate) if ran else ("-", "")
    learned = value["learned"]
    diff = _paired(rows, g, "learned", best) if learned and best else None
    if diff is None:
        diff_cell, verdict = "no paired interval", "-"
    else:
        diff_cell, verdict = fmt_ci(diff.estimate, diff.lo, diff.hi), paired_verdict(diff.lo, diff.hi)
    adaptive_cell = fam.adaptive_outcome or "not run"
    if value["learned-adaptive"] is None:
        shown[-1] = adaptive_cell
    else:
        adaptive_cell = _adaptive_cell(rows, g, "learned-adaptive", best)
    k0 = _get(rows, g, ADAPTIVE_K0, metric)
    if k0 is not None:
        shown[-1] += K0_LABEL + _cell(rows, g, ADAPTIVE_K0, k0)
        adaptive_cell += K0_LABEL + _adaptive_cell(rows, g, ADAPTIVE_K0, best)
    anees = _get(rows, g, "learned", "anees_all", _get_dof(rows, g))
    if anees is None:
        anees_cell, anees_v = "not in the data", "-"
    else:
        dof, runs = float(anees.reference), _runs(learned)
        band = f"; band {fmt(anees_band(dof, runs)[0])}-{fmt(anees_band(dof, runs)[1])}" if runs else ""
        anees_cell, anees_v = (
            f"{fmt_ci(anees.estimate, anees.lo, anees.hi)} (d {fmt(dof)}{band})",
            anees_verdict(anees.lo, anees.hi, dof, runs),
        )
    test = g.split("=", 1)[-1] if g else "-"
    link = f"[{fam.name}](detail/{fam.name}.md)"
    return [
        f"{fam.paper} {fam.label}",
        fam.kind,
        test,
        *shown[: len(METHODS)],
        best_title,
        *shown[len(METHODS) :],
        diff_cell,
        verdict,
        adaptive_cell,
        anees_cell,
        anees_v,
        link,
    ]


def _get_dof(rows: Sequence[Row], group: str) -> str:
    """The ``reference`` (d) of the learned filter's all-state ANEES row in ``group`` ("" if none)."""
    r = next((r for r in rows if r.group == group and r.filter == "learned" and r.quantity == "anees_all"), None)
    return r.reference if r else ""


def _runs(row: Row | None) -> int | None:
    return int(row.runs) if row is not None and row.runs.strip().isdigit() else None


_HEADER = [
    "family",
    "kind",
    "test set",
    *(t for t, _ in METHODS),
    "best non-learned",
    *(t for t, _ in LEARNED),
    "learned - best non-learned, % [95 %]",
    "verdict",
    "learned adaptive - best non-learned, % [95 %] (verdict)",
    "learned ANEES [95 %] (d; band)",
    "ANEES verdict",
    "detail",
]


def _source(fam: Family, root: Path) -> Path:
    return root / "results" / "data" / f"{fam.name}.csv"


def build_report(families: Sequence[Family] = FAMILIES, root: Path = ROOT) -> str:
    """The text of ``results/REPORT.md``."""
    out = [
        "# difffilter: the papers' experiments, summary",
        "",
        "<!-- generated by `python experiments/report.py --render` from results/data/*.csv; do not edit by hand -->",
        "",
        "One row per paper family, the realistic families first (mis-specified: the truth has something the paper's",
        "model lacks; paper's own: the paper's conditions), the designed in-family families after (the truth is the",
        "filter's own model at values placed away from the paper's, so a win there is expected by construction).",
        "Position RMSE in m, mean over seeds x test runs [95 % interval over seeds x runs].  Verdicts, one rule for",
        "every row (`experiments/results_tables.py`):",
        "",
        "- learned - best non-learned: the paired difference per test run and seed, in % of the reference; **win**",
        "  when its 95 % interval lies below zero, **loss** when above, **tie** when it contains zero.  The best",
        "  non-learned method is the lowest-RMSE row among the seven non-learned columns that were run and, on p000,",
        "  the three adaptive filters around a UKF with Julier kappa 0 (shown in their kappa -5 column's cell after",
        "  `kappa 0:`); a method without a row in the family's CSV says *not run*.  A paired interval exists only",
        "  against the row the sweep pairs with (the paper's constants) or a `diff_pct` row whose `reference` names",
        "  the best method.  The learned adaptive filter (Sage-Husa with its forgetting factor and noise learned, a",
        "  separate training job) gets the same paired comparison and rule in its own column where it ran (on p000",
        "  also around the kappa 0 UKF, after `kappa 0:`).",
        "- ANEES of the learned filter (all states, d of them) against the 95 % chi-square band of a consistent",
        "  filter's mean NEES over the N test runs, `[chi2_0.025(N d) / N, chi2_0.975(N d) / N]`: **consistent** when",
        "  the ANEES interval lies inside the band, **over-** / **under-confident** when entirely above / below it,",
        "  **undecided** when it straddles a band edge or has no interval (too wide to decide).",
        "",
        "Each family shows one test set (named); every test set, filter and state block is in its detail page.",
        "The numbers come from `results/data/<family>.csv` (the schema of a sweep's `summary.csv`); where they",
        "were transcribed rather than copied from a sweep, `results/data/SOURCES.md` says so.  A family labelled",
        "*practitioners' rows* shows its sweep with the practitioners' methods (issue 25, pre-declared in",
        "[p00_practitioners.md](p00_practitioners.md)): the family's experiment rerun with the current code plus",
        "those rows, so its paper's-constants and learned cells are that sweep's (the family's earlier numbers stay",
        "in its own detail page); `; N CPU-s` after a cell is the row's tuning cost (learned: its training), mean",
        "over seeds.  Data efficiency (1, 4, 16 training trajectories) and transfer between families are in",
        "[p00_efficiency_transfer.md](p00_efficiency_transfer.md); real data in [smartloc_real.md](smartloc_real.md) and",
        "[librsf_w3500.md](librsf_w3500.md); the reliability battery in [reliability_battery.md](reliability_battery.md).",
        "",
        "| " + " | ".join(_HEADER) + " |",
        "|" + "---|" * len(_HEADER),
    ]
    tally: dict[str, dict[str, int]] = {}
    adaptive: list[str] = []
    adaptive_k0: list[str] = []
    no_row: list[str] = []
    for fam in families:
        shown = fam.practitioners_family() if fam.practitioners else fam
        cells = summary_cells(shown, read_rows(_source(shown, root)))
        out.append("| " + " | ".join(cells) + " |")
        kind = tally.setdefault(fam.kind, {})
        kind[cells[_HEADER.index("verdict")]] = kind.get(cells[_HEADER.index("verdict")], 0) + 1
        la_cell, _, k0_cell = cells[_HEADER.index("learned adaptive - best non-learned, % [95 %] (verdict)")].partition(K0_LABEL)
        if la_cell.endswith(")"):
            adaptive.append(f"{fam.name} {la_cell.rsplit('(', 1)[1].rstrip(')')}")
        elif fam.adaptive_outcome and la_cell == fam.adaptive_outcome:
            no_row.append(f"{fam.name} ({fam.adaptive_outcome.removeprefix('ran, no row: ')})")
        if k0_cell.endswith(")"):
            adaptive_k0.append(f"{fam.name} {k0_cell.rsplit('(', 1)[1].rstrip(')')}")
    out += [""] + [
        f"Verdicts of learned against the best non-learned method, {kind} families: "
        + ", ".join(f"{n} {v}" for v, n in sorted(counts.items()))
        + "."
        for kind, counts in tally.items()
    ]
    if adaptive:
        out.append(
            "Verdicts of the learned adaptive filter against the best non-learned method, where it ran: " + ", ".join(adaptive) + "."
        )
    if no_row:
        out.append("Learned adaptive jobs that ran and left no row: " + ", ".join(no_row) + ".")
    if adaptive_k0:
        out.append(
            "Verdicts of the learned adaptive filter around a kappa 0 UKF against the best non-learned method: "
            + ", ".join(adaptive_k0)
            + "."
        )
    out += [
        "",
        "Not in the table: the real drive (smartLoc Berlin, `results/smartloc_real.md`: median/RMS error per fold,",
        "no committed CSV), p000's sigma_a sweep and smoothing run, p002's plain-UKF sweeps and p003's cross-family",
        "switching test (their results files), and the engine benchmarks (`results/benchmark_engine.md`).",
        "",
        "## Detail and discussion",
        "",
        "| family | detail (generated) | discussion (results file) | sweep (`experiments/reproduce.py`) |",
        "|---|---|---|---|",
    ]
    for fam in (f for g in families for f in _with_practitioners(g)):
        out.append(f"| {fam.name} | [detail/{fam.name}.md](detail/{fam.name}.md) | [{fam.results}]({fam.results}) | `{fam.sweep}` |")
    return "\n".join(out) + "\n"


def build_detail(fam: Family, root: Path = ROOT) -> str:
    """The text of ``results/detail/<family>.md``: every test set, filter and block of the family's CSV."""
    rows = read_rows(_source(fam, root))
    has_anees = any(r.quantity.startswith("anees_") for r in rows)
    src = f"results/data/{fam.name}.csv"
    out = [
        f"# {fam.name}: {fam.paper}, {fam.label} ({fam.kind})",
        "",
        f"<!-- generated by `python experiments/report.py --render` from {src}; do not edit by hand -->",
        "",
        f"Sweep `{fam.sweep}` (`experiments/reproduce.py`); discussion in [{fam.results}](../{fam.results});"
        " summary in [REPORT.md](../REPORT.md).  Paired differences: filter - hand-tuned (the paper's constants).",
        "",
        render_metric(rows, {}),
    ]
    paired = [r for r in rows if r.filter in {ADAPTIVE_K0, *(n for _, n in LEARNED)} and r.quantity == "diff_pct" and r.reference]
    cpu = [r for r in rows if r.quantity == "tuning_cpu_s"]
    if paired:
        out += ["", "Learned - best non-learned (paired per test run and seed, % of the best's mean):", ""]
        out += [
            f"- {r.group or 'test'}: {r.filter} - {r.reference}: {fmt_ci(r.estimate, r.lo, r.hi)} ({paired_verdict(r.lo, r.hi)})"
            for r in paired
        ]
    if cpu:
        out += ["", "Tuning CPU seconds per row (learned: training), mean [min, max] over seeds:", ""]
        out += [f"- {r.group + ' ' if r.group else ''}{r.filter}: {fmt_ci(r.estimate, r.lo, r.hi)}" for r in cpu]
    if has_anees:
        out += ["", "ANEES per state block (verdict rule in REPORT.md):", "", render_anees(rows, {})]
    return "\n".join(out) + "\n"


def _with_practitioners(fam: Family) -> tuple[Family, ...]:
    return (fam, fam.practitioners_family()) if fam.practitioners else (fam,)


def generated_files(root: Path = ROOT) -> dict[Path, str]:
    """Every wholly generated file (REPORT.md, the detail pages) and its text."""
    files = {root / "results" / "REPORT.md": build_report(FAMILIES, root)}
    every = [f for fam in FAMILIES for f in _with_practitioners(fam)]
    files.update({root / "results" / "detail" / f"{fam.name}.md": build_detail(fam, root) for fam in every})
    return files


def results_files(root: Path = ROOT) -> list[Path]:
    """The hand-written results files whose marked tables are rendered (every ``results/*.md`` but REPORT.md)."""
    return sorted(p for p in (root / "results").glob("*.md") if p.name != "REPORT.md")


def check(root: Path = ROOT) -> list[str]:
    """Every difference between the committed results and what the CSVs give ([] when none)."""
    problems = []
    for path, text in generated_files(root).items():
        rel = path.relative_to(root)
        if not path.exists():
            problems.append(f"{rel}: missing (python experiments/report.py --render)")
        elif path.read_text() != text:
            problems.append(f"{rel}: differs from what results/data gives")
    for p in results_files(root):
        text = p.read_text()
        command = whole_file_generator(text)
        if command is None:
            problems += [f"{p.relative_to(root)}: {msg}" for msg in check_text(text, root)]
        elif not any((base / command.split()[1]).is_file() for base in (root, ROOT)):
            problems.append(f"{p.relative_to(root)}: its generator {command!r} names no committed script")
    return problems


#: First line of a results file written whole by one committed command (a benchmark, a real-data
#: protocol): its tables come from that command's own run, not from results/data, so the table
#: check leaves them to the command (rerun it to regenerate the file).
WHOLE_FILE = re.compile(r"^<!-- generated file: (python \S+\.py[^>]*?) -->$", re.M)


def whole_file_generator(text: str) -> str | None:
    """The command named by a results file's ``<!-- generated file: python ... -->`` line, or None."""
    match = WHOLE_FILE.search(text.split("\n", 1)[0])
    return match.group(1).strip() if match else None


def render(root: Path = ROOT) -> list[Path]:
    """Rewrite every generated table and file; returns the files that changed."""
    changed = []
    for path, text in generated_files(root).items():
        if not path.exists() or path.read_text() != text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            changed.append(path)
    for path in results_files(root):
        old = path.read_text()
        new = render_text(old, root)
        if new != old:
            path.write_text(new)
            changed.append(path)
    return changed


def _rejoin_learned_adaptive(fam: Family, root: Path) -> None:
    """A practitioners data file just copied from its sweep gets its rows from the sweeps beside it
    again, where they ran (issue 25): the kappa 0 rows (``<sweep>_k0``, :func:`merge_rows`), then the
    ``learned-adaptive`` rows (``<sweep>_learned_adaptive``) and the ``learned-adaptive-k0`` rows
    (``<sweep>_learned_adaptive_k0``); each join checks that its sweep's shared rows are the file's."""
    if not fam.sweep.startswith(PRACTITIONERS_ROOT):
        return
    if (root / f"{fam.sweep}_k0").is_dir():
        merge_rows(root / f"{fam.sweep}_k0", _source(fam, root))
    for suffix, name in (("_learned_adaptive", "learned-adaptive"), ("_learned_adaptive_k0", ADAPTIVE_K0)):
        sweep = root / f"{fam.sweep}{suffix}"
        if sweep.is_dir():
            join_learned_adaptive(sweep, _source(fam, root), name=name)


def collect(root: Path = ROOT) -> list[Path]:
    """Copy each family's ``<sweep>/summary.csv``, where a run of ``experiments/reproduce.py`` left
    one, over its data file (the committed numbers then come from the run), join the practitioners
    families' kappa 0 and learned adaptive sweeps that ran to their data files (:func:`_rejoin_learned_adaptive`;
    to the committed file where the family's own sweep did not run), and copy each summary of
    :data:`experiments.efficiency_transfer.DATA_FILES` over its data file; returns those copied."""
    copied = []
    for fam in (f for g in FAMILIES for f in _with_practitioners(g)):
        src = root / fam.sweep / "summary.csv"
        if src.exists():
            rows = read_rows(src)  # the schema is checked before anything is overwritten
            if rows:
                shutil.copyfile(src, _source(fam, root))
                copied.append(src)
                _rejoin_learned_adaptive(fam, root)
        elif _source(fam, root).exists():
            # the family's own sweep did not run (reproduce.py --only): its kappa 0 and learned
            # adaptive sweeps, where they ran, join the committed file (each join checks its rows)
            _rejoin_learned_adaptive(fam, root)
    for source, data in DATA_FILES:  # issue 25's efficiency and transfer summaries
        if (root / source).exists() and read_rows(root / source):
            shutil.copyfile(root / source, root / data)
            copied.append(root / source)
    return copied


def main(argv: Sequence[str] | None = None) -> int:
    """``--render`` / ``--check`` / ``--collect`` (module docstring of :mod:`experiments.results_tables`); exit status."""
    ap = argparse.ArgumentParser(description="Render or check the results tables from results/data/*.csv.")
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--render", action="store_true", help="rewrite every generated table, REPORT.md and results/detail/")
    mode.add_argument("--check", action="store_true", help="exit 1 when a table differs from its CSVs")
    mode.add_argument("--collect", action="store_true", help="copy the sweeps' summary.csv into results/data, then render")
    ap.add_argument("--root", type=Path, default=ROOT, help="project root (default: this checkout)")
    args = ap.parse_args(argv)
    if args.check:
        problems = check(args.root)
        for p in problems:
            print(p, file=sys.stderr)
        print(f"results check: {len(problems)} problem(s)" if problems else "results check: every table equals its CSVs")
        return 1 if problems else 0
    if args.collect:
        for src in collect(args.root):
            print(f"collected {src}")
    for path in render(args.root):
        print(f"rendered {path.relative_to(args.root)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
