"""The results tables are rendered from committed CSVs: the check catches a hand edit, the renderer
is deterministic, and the verdict rules give win / tie / loss / undecided on synthetic rows."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import pytest

from experiments import results_report, results_tables
from experiments.results_report import Family, check, render, summary_cells
from experiments.results_tables import FIELDS, anees_band, anees_verdict, check_text, paired_verdict, read_rows, render_text

ROOT = Path(__file__).resolve().parents[1]


def _copy_results(tmp_path: Path) -> Path:
    """The committed results/ (markdown, data, detail) under a temporary project root."""
    shutil.copytree(ROOT / "results", tmp_path / "results", ignore=shutil.ignore_patterns("*.png"))
    return tmp_path


def _write(path: Path, rows: list[dict[str, object]]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        w.writerows([{k: r.get(k, "") for k in FIELDS} for r in rows])
    return path


def test_committed_results_equal_what_their_csvs_give():
    assert check(ROOT) == []


def test_report_is_short_and_leads_with_the_realistic_families():
    text = (ROOT / "results" / "REPORT.md").read_text()
    assert len(text.splitlines()) <= 300
    kinds = [line.split(" | ")[1] for line in text.splitlines() if line.startswith("| p00") and line.count(" | ") > 10]
    assert kinds and kinds == sorted(kinds, key=lambda k: k == "in-family")  # every in-family row after the others
    assert len(kinds) == len(results_report.FAMILIES)


def test_a_hand_edit_of_a_generated_table_fails_the_check(tmp_path):
    root = _copy_results(tmp_path)
    assert check(root) == []
    path = root / "results" / "p000_gpsdr.md"
    text = path.read_text()
    assert "| learned | 5 x 30 | 1.5 [1.36, 1.641] |" in text
    path.write_text(text.replace("| learned | 5 x 30 | 1.5 [1.36, 1.641] |", "| learned | 5 x 30 | 1.4 [1.36, 1.641] |", 1))
    problems = check(root)
    assert problems == ["results/p000_gpsdr.md: table p000_infamily_rmse: differs from results/data/p000_infamily.csv"]
    # rendering restores it from the CSV
    render(root)
    assert path.read_text() == text and check(root) == []


def test_a_hand_edit_of_report_or_detail_and_an_unmarked_table_fail_the_check(tmp_path):
    root = _copy_results(tmp_path)
    report = root / "results" / "REPORT.md"
    report.write_text(report.read_text().replace("| tie |", "| win |", 1))
    detail = root / "results" / "detail" / "p004_urban.md"
    detail.write_text(detail.read_text() + "\nextra\n")
    notes = root / "results" / "p003_protocol.md"
    notes.write_text(notes.read_text() + "\n| a | b |\n|---|---|\n| 1 | 2 |\n")
    problems = check(root)
    assert "results/REPORT.md: differs from what results/data gives" in problems
    assert "results/detail/p004_urban.md: differs from what results/data gives" in problems
    assert any(p.startswith("results/p003_protocol.md: line ") and "outside" in p for p in problems)


def test_a_changed_csv_fails_the_check_until_rendered(tmp_path):
    root = _copy_results(tmp_path)
    data = root / "results" / "data" / "p003_modes.csv"
    data.write_text(data.read_text().replace("0.9613", "0.9612", 1))
    problems = check(root)
    assert "results/p003_imm_sins.md: table p003_modes_rmse: differs from results/data/p003_modes.csv" in problems
    # REPORT's p003_modes row reads the family's practitioners file; its own detail page reads this one
    assert "results/detail/p003_modes.md: differs from what results/data gives" in problems
    changed = render(root)
    assert check(root) == [] and root / "results" / "detail" / "p003_modes.md" in changed
    assert "0.9612 [0.8548, 1.068]" in (root / "results" / "p003_imm_sins.md").read_text()


def test_renderer_is_deterministic(tmp_path):
    root = _copy_results(tmp_path)
    first = results_report.generated_files(root)
    again = results_report.generated_files(root)
    assert first == again
    text = (root / "results" / "p000_gpsdr.md").read_text()
    assert render_text(text, root) == render_text(render_text(text, root), root) == text
    assert render(root) == []  # nothing to change in the committed tree


def test_marker_errors_are_reported_not_raised(tmp_path):
    _write(tmp_path / "d.csv", [{"filter": "hand-tuned", "quantity": "rmse_pos", "estimate": 1.0}])
    bad = "<!-- table: t renderer=nope source=d.csv -->\n| x |\n|---|\n<!-- /table -->\n"
    want = "table t: marker 'renderer=nope source=d.csv': renderer must be one of ['anees', 'metric', 'paired', 'targets', 'times']"
    assert check_text(bad, tmp_path) == [want]
    missing = "<!-- table: t renderer=metric source=gone.csv -->\n<!-- /table -->\n"
    assert check_text(missing, tmp_path)[0].startswith("table t: [Errno 2]")
    with pytest.raises(ValueError, match="columns must be"):
        (tmp_path / "e.csv").write_text("a,b\n1,2\n")
        read_rows(tmp_path / "e.csv")


@pytest.mark.parametrize(
    ("lo", "hi", "verdict"),
    [(-3.0, -0.5, "win"), (-3.0, 0.5, "tie"), (0.2, 1.0, "loss"), (-1.0, 0.0, "tie"), (math.nan, 1.0, "no interval")],
)
def test_paired_verdict(lo, hi, verdict):
    assert paired_verdict(lo, hi) == verdict


def test_anees_band_is_the_chi_square_band_in_closed_form():
    # chi2 with 2 degrees of freedom is exponential: ppf(p) = -2 ln(1 - p)
    lo, hi = anees_band(2, 1)
    assert lo == pytest.approx(-2 * math.log(0.975), rel=1e-9) and hi == pytest.approx(-2 * math.log(0.025), rel=1e-9)
    # mean over N runs of d-dimensional NEES: chi2(N d) / N, so the band narrows around d as N grows
    wide, narrow = anees_band(8, 10), anees_band(8, 1000)
    assert wide[0] < narrow[0] < 8 < narrow[1] < wide[1]
    with pytest.raises(ValueError, match="dof and runs"):
        anees_band(0, 10)


@pytest.mark.parametrize(
    ("lo", "hi", "verdict"),
    [
        (-289.6, 1021.0, "undecided"),  # p000's in-family learned ANEES: the interval straddles the band
        (7.9, 8.1, "consistent"),
        (12.0, 14.0, "over-confident"),
        (3.0, 4.0, "under-confident"),
        (7.0, 12.0, "undecided"),  # contains d but is wider than the band
        (math.nan, math.nan, "undecided"),
    ],
)
def test_anees_verdict(lo, hi, verdict):
    assert anees_verdict(lo, hi, 8.0, 30) == verdict
    assert anees_band(8, 30)[0] < 7.0 < anees_band(8, 30)[1] < 12.0  # the cases above sit where they claim


def _family_rows(learned_pct: tuple[float, float, float], extra: list[dict[str, object]] = ()) -> list[dict[str, object]]:
    est, lo, hi = learned_pct
    return [
        {"filter": "hand-tuned", "quantity": "rmse_pos", "estimate": 2.0, "lo": 1.9, "hi": 2.1, "seeds": 1, "runs": 30},
        {"filter": "learned", "quantity": "rmse_pos", "estimate": 2.0 * (1 + est / 100), "lo": 1.5, "hi": 2.5, "seeds": 5, "runs": 30},
        {"filter": "learned", "quantity": "diff_pct", "estimate": est, "lo": lo, "hi": hi, "seeds": 5, "runs": 30},
        {"filter": "learned", "quantity": "anees_all", "estimate": 8.1, "lo": 7.9, "hi": 8.3, "reference": 8},
        *extra,
    ]


@pytest.mark.parametrize(("pct", "verdict"), [((-10.0, -12.0, -8.0), "win"), ((-1.0, -3.0, 1.0), "tie"), ((2.0, 1.0, 3.0), "loss")])
def test_summary_row_verdict_on_synthetic_rows(tmp_path, pct, verdict):
    fam = Family("x", "p009", "mis-specified", "synthetic", "x.md", "outputs/x")
    cells = summary_cells(fam, read_rows(_write(tmp_path / "x.csv", _family_rows(pct))))
    header = results_report._HEADER
    row = dict(zip(header, cells, strict=True))
    assert row["verdict"] == verdict and row["best non-learned"] == "paper's constants"
    assert row["EM"] == row["Sage-Husa"] == row["VB-AKF"] == row["learned adaptive"] == "not run"
    assert row["ANEES verdict"] == "consistent" and row["learned ANEES [95 %] (d; band)"].startswith("8.1 [7.9, 8.3] (d 8; band ")


def test_learned_adaptive_cell_says_a_job_left_no_row_and_yields_to_a_row(tmp_path):
    fam = Family("x", "p009", "mis-specified", "synthetic", "x.md", "outputs/x", adaptive_outcome="ran, no row: diverged")
    rows = _family_rows((-10.0, -12.0, -8.0))
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "x.csv", rows))), strict=True))
    assert row["learned adaptive"] == row["learned adaptive - best non-learned, % [95 %] (verdict)"] == "ran, no row: diverged"
    la = {"filter": "learned-adaptive", "quantity": "rmse_pos", "estimate": 2.5, "lo": 2.4, "hi": 2.6, "seeds": 5, "runs": 30}
    pct = {"filter": "learned-adaptive", "quantity": "diff_pct", "estimate": 25.0, "lo": 20.0, "hi": 30.0, "seeds": 5, "runs": 30}
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "y.csv", [*rows, la, pct]))), strict=True))
    assert row["learned adaptive"] == "2.5 [2.4, 2.6]"
    assert row["learned adaptive - best non-learned, % [95 %] (verdict)"] == "25 [20, 30] (loss)"


def test_summary_row_against_a_better_non_learned_method(tmp_path):
    fam = Family("x", "p009", "mis-specified", "synthetic", "x.md", "outputs/x")
    em = {"filter": "em", "quantity": "rmse_pos", "estimate": 1.5, "lo": 1.4, "hi": 1.6, "seeds": 5, "runs": 30}
    rows = _family_rows((-10.0, -12.0, -8.0), [em])
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "x.csv", rows))), strict=True))
    # EM beats the paper's constants; learning's paired interval against EM is not in the data: no verdict
    assert row["best non-learned"] == "EM" and row["verdict"] == "-" and row["learned - best non-learned, % [95 %]"] == "no paired interval"
    paired = {"filter": "learned", "quantity": "diff_pct", "estimate": 20.0, "lo": 15.0, "hi": 25.0, "reference": "em"}
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "y.csv", [*rows, paired]))), strict=True))
    assert row["verdict"] == "loss" and row["learned - best non-learned, % [95 %]"] == "20 [15, 25]"


def test_rendered_metric_table_from_synthetic_rows(tmp_path):
    rows = read_rows(_write(tmp_path / "x.csv", _family_rows((-10.0, -12.0, -8.0))))
    text = results_tables.render_metric(rows, {})
    assert text.splitlines()[2] == "| hand-tuned | 1 x 30 | 2 [1.9, 2.1] |  |  |  |  |"
    assert text.splitlines()[3] == "| learned | 5 x 30 | 1.8 [1.5, 2.5] |  | -10 [-12, -8] | win |  |"


def test_collect_takes_a_sweeps_summary_csv_and_the_check_passes_after_rendering(tmp_path):
    root = _copy_results(tmp_path)
    sweep = root / "outputs" / "p003_final" / "p003_modes"
    sweep.mkdir(parents=True)
    data = root / "results" / "data" / "p003_modes.csv"
    (sweep / "summary.csv").write_text(data.read_text().replace("0.9613", "0.9611", 1))
    assert results_report.collect(root) == [sweep / "summary.csv"]
    assert "0.9611" in data.read_text() and check(root) != []
    render(root)
    assert check(root) == [] and "0.9611 [0.8548, 1.068]" in (root / "results" / "detail" / "p003_modes.md").read_text()
    (sweep / "summary.csv").write_text("group,filter\n,x\n")  # not a summary.csv: nothing is overwritten
    with pytest.raises(ValueError, match="columns must be"):
        results_report.collect(root)
    assert "0.9611" in data.read_text()


def test_a_whole_file_generator_must_be_a_committed_script(tmp_path):
    root = _copy_results(tmp_path)
    (root / "experiments").mkdir()
    (root / "experiments" / "bench_x.py").write_text("")
    table = "| a | b |\n|---|---|\n| 1 | 2 |\n"
    (root / "results" / "x.md").write_text("<!-- generated file: python experiments/bench_x.py --out results/x.md -->\n# x\n\n" + table)
    assert not [p for p in check(root) if "x.md" in p]
    missing = "<!-- generated file: python experiments/nothing.py -->\n"
    (root / "results" / "y.md").write_text(missing + "# y\n\n" + table)
    assert [p for p in check(root) if "y.md" in p] == [
        "results/y.md: its generator 'python experiments/nothing.py' names no committed script"
    ]
    (root / "results" / "z.md").write_text("# z\n\n<!-- generated file: python experiments/bench_x.py -->\n" + table)  # not the first line
    assert any("z.md: line" in p and "outside" in p for p in check(root))


def test_summary_row_learned_adaptive_column_pairs_with_the_best_non_learned_row(tmp_path):
    fam = Family("x", "p009", "mis-specified", "synthetic", "x.md", "outputs/x")
    rows = _family_rows((-10.0, -12.0, -8.0))
    column = "learned adaptive - best non-learned, % [95 %] (verdict)"
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "x.csv", rows))), strict=True))
    assert row[column] == "not run"
    la = {"filter": "learned-adaptive", "quantity": "rmse_pos", "estimate": 2.2, "lo": 2.1, "hi": 2.3, "seeds": 5, "runs": 30}
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "y.csv", [*rows, la]))), strict=True))
    assert row[column] == "no paired interval"  # the data have no diff_pct row for it
    # best non-learned = the paper's constants (the sweep's reference): its diff_pct row has no reference
    pct = {"filter": "learned-adaptive", "quantity": "diff_pct", "estimate": 10.0, "lo": 4.0, "hi": 16.0}
    row = dict(zip(results_report._HEADER, summary_cells(fam, read_rows(_write(tmp_path / "z.csv", [*rows, la, pct]))), strict=True))
    assert row[column] == "10 [4, 16] (loss)" and row["verdict"] == "win"


def test_times_renderer_tables_a_reproduce_run(tmp_path):
    """``renderer=times``: one row per job of reproduce.py's times.tsv, the run's total in minutes;
    a file that is not one is refused with its path (and line)."""
    tsv = "job\tstatus\twall_s\tcpu_s\np003_modes\t0\t600.4\t590.6\np000_gyro\t1\t100.0\t98.0\nall\t1 failed\t720.0\t688.6\n"
    (tmp_path / "t.tsv").write_text(tsv)
    text = "<!-- table: t renderer=times source=t.tsv -->\n<!-- /table -->\n"
    got = render_text(text, tmp_path).splitlines()
    assert got[1:6] == [
        "| job | status | wall (s) | CPU (s) |",
        "|---|---|---|---|",
        "| p003_modes | ok | 600 | 591 |",
        "| p000_gyro | exit 1 | 100 | 98 |",
        "| **all 2 jobs** (1 failed) |  | **12.0 min** | **11.5 min** |",
    ]
    assert check_text(render_text(text, tmp_path), tmp_path) == []
    (tmp_path / "bad.tsv").write_text("job,status\n")
    assert "not a reproduce.py times.tsv" in check_text(text.replace("t.tsv", "bad.tsv"), tmp_path)[0]
    (tmp_path / "short.tsv").write_text("job\tstatus\twall_s\tcpu_s\nx\t0\t1\n")
    assert "short.tsv:2: expected 4 tab-separated fields" in check_text(text.replace("t.tsv", "short.tsv"), tmp_path)[0]


def test_targets_renderer_tables_a_benchmark_run(tmp_path):
    """``renderer=targets``: the targets a benchmark run measured (its ``n/a`` rows left out), with
    the run's folder; a file that is not a targets.csv is refused."""
    run = tmp_path / "bench_2026-12-07"
    run.mkdir()
    csv_text = (
        "target,measured,goal,met\n"
        "UKF train B=256: difffilter (plain call) / dynamax throughput,7.2345,>= 5,yes\n"
        "UKF train B=256: difffilter-fused / dynamax throughput,,>= 2,n/a\n"
        "UKF cold first forward + training step: CPU s,41.26,<= 30,NO\n"
    )
    (run / "targets.csv").write_text(csv_text)
    text = "<!-- table: t renderer=targets source=bench_2026-12-07/targets.csv -->\n<!-- /table -->\n"
    got = render_text(text, tmp_path).splitlines()
    assert got[1:5] == [
        "| target | measured | goal | met | run |",
        "|---|---|---|---|---|",
        "| UKF train B=256: difffilter (plain call) / dynamax throughput | 7.23 | >= 5 | yes | bench_2026-12-07 |",
        "| UKF cold first forward + training step: CPU s | 41.3 | <= 30 | NO | bench_2026-12-07 |",
    ]
    assert len(got) == 6 and check_text(render_text(text, tmp_path), tmp_path) == []
    (run / "bad.csv").write_text("job,status\n")
    assert "not a benchmark targets.csv" in check_text(text.replace("targets.csv", "bad.csv"), tmp_path)[0]
