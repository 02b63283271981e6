"""experiments/report.py: collects results/<name>.md sections and run directories' results.csv
into results/REPORT.md with the papers' published numbers beside ours."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.runner.experiment import write_results

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report():
    spec = importlib.util.spec_from_file_location("difffilter_report", ROOT / "experiments" / "report.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(spec.name, None)


def _row(name, rmse, anees=8.0):
    return {
        "filter": name,
        "rmse_pos": rmse,
        "anees": anees,
        "anees_dof": 8.0,
        "anees_run_ci_lo": anees - 0.5,
        "anees_run_ci_hi": anees + 0.5,
        "anees_step_band_frac": 0.9,
        "nis": 2.0,
        "nll": 1.0,
        "time_per_step_ms": 3.0,
    }


def test_markdown_tables_are_parsed(report):
    text = "# t\n\nintro\n\n| filter | rmse_pos | paper |\n|---|---|---|\n| hand-tuned | 0.12 | 2.36 cm |\n| learned | 0.11 |  |\n\ntext\n"
    tables = report.parse_markdown_tables(text)
    assert tables == [
        [{"filter": "hand-tuned", "rmse_pos": "0.12", "paper": "2.36 cm"}, {"filter": "learned", "rmse_pos": "0.11", "paper": ""}]
    ]
    assert report.parse_markdown_tables("| a | b |\nno rule\n") == []


def test_report_from_run_directory_and_sections(report, tmp_path):
    # a run directory as experiments/train.py writes it
    run = tmp_path / "run"
    rows = [_row("hand-tuned", 0.125, 7.0), _row("learned", 0.100), _row("oracle", 0.099), _row("ekf", 0.126), _row("ukf", 0.127)]
    write_results(rows, run, title="difffilter results: p004_blend")
    # a hand-written section in results/ (an older one: its runs x steps band columns are ignored)
    results = tmp_path / "results"
    results.mkdir()
    section = "# p000_gpsdr\n\n| filter | rmse_pos | anees | anees_lo | anees_hi |\n|---|---|---|---|---|\n"
    section += "| hand-tuned | 6.0 | 44 | 7.98 | 8.02 |\n| learned | 4.5 | 9.0 | 7.98 | 8.02 |\n"
    (results / "p000_gpsdr.md").write_text(section)
    text = report.collect([str(run)], results_dir=results)
    written = (results / "REPORT.md").read_text()
    assert written == text
    lines = text.splitlines()
    # summary: one line per experiment, learned vs hand-tuned in percent, ANEES with its run-level
    # interval against d and the per-step band fraction; an old section's band is not a verdict
    p004 = next(x for x in lines if x.startswith("| p004_blend |"))
    assert "| 0.125 | 0.1 | 0.099 | -20.0 % | 8 [7.5, 8.5] (d = 8) in; 90 % steps in band |" in p004 and "9.53" in p004
    p000 = next(x for x in lines if x.startswith("| p000_gpsdr |"))
    assert "| 6 | 4.5 | - | -25.0 % | 9 |" in p000 and "7.98" not in p000
    # the run's table shows the new consistency columns, never the old band
    assert "| filter | rmse_pos | anees | anees_dof | anees_run_ci_lo | anees_run_ci_hi | anees_step_band_frac |" in text
    assert "anees_lo" not in text.split("## p000_gpsdr")[0]
    # the run's table puts each published number beside the matching filter
    assert any(x.startswith("| ekf | 0.126 |") and x.endswith("| 9.53 cm |") for x in lines)
    assert any(x.startswith("| ukf | 0.127 |") and x.endswith("| 5.68 cm |") for x in lines)
    assert any(x.startswith("| learned | 0.1 |") and x.endswith("|  |") for x in lines)
    # the section is included with its headings nested below the report's
    assert "\n## p000_gpsdr\n" in text and "(from `results/p000_gpsdr.md`)" in text and "\n# p000_gpsdr" not in text
    # a section without a heading gets one; an experiment given as run and section is summarised once
    (results / "p004_blend.md").write_text("| filter | rmse_pos |\n|---|---|\n| hand-tuned | 0.2 |\n| learned | 0.1 |\n")
    text = report.collect([str(run)], results_dir=results, write=False)
    assert sum(x.startswith("| p004_blend |") for x in text.splitlines()) == 1 and "\n## p004_blend\n" in text
    # hand-written tables: units and (ignored) bands in the headers, roles inside longer names, bold cells
    table = "| filter (4 runs) | rmse_pos (m) | anees (band 19.85-20.15) |\n|---|---|---|\n"
    table += "| IMM, hand-tuned | 3.500 [3.9] | 218 |\n| **IMM, learned** | **3.150** | 20.0 |\n| IMM, oracle | 3.0 | 20.1 |\n"
    (results / "p003_imm.md").write_text("## p003\n\n" + table)
    text = report.collect(results_dir=results, write=False)
    p003 = next(x for x in text.splitlines() if x.startswith("| p003_imm |"))
    assert "| 3.5 | 3.15 | 3 | -10.0 % | 20 |" in p003 and "5 vs 7 steps" in p003
    # a rerun row below a learned row supersedes it in the summary; the other roles keep the first match
    table = "| filter | rmse_pos |\n|---|---|\n| RC-UKF hand-tuned | 3.0 |\n| RC-UKF learned | 1.7 |\n"
    table += "| RC-UKF learned, rerun | 1.5 |\n| UKF hand-tuned | 1.6 |\n"
    (results / "p002_pdr.md").write_text("## p002\n\n" + table)
    p002 = next(x for x in report.collect(results_dir=results, write=False).splitlines() if x.startswith("| p002_pdr |"))
    assert "| 3 | 1.5 | - | -50.0 % |" in p002
    # a second run does not read its own REPORT.md back as a section
    again = report.collect(results_dir=results, write=False)
    assert "REPORT" not in again


def test_missing_run_is_an_error(report, tmp_path):
    with pytest.raises(FileNotFoundError):
        report.load_run(tmp_path / "nothing")


def test_sweep_summary_is_included_as_a_section(report, tmp_path):
    sweep = tmp_path / "sweep"
    for k in range(2):
        write_results([_row("hand-tuned", 0.125), _row("learned", 0.1 + 0.01 * k)], sweep / str(k), title="difffilter results: p004_blend")
    (sweep / "summary.md").write_text(
        "# Sweep summary\n\n## all jobs (seeds 0, 1; jobs 0, 1)\n\n| filter | seeds |\n|---|---|\n| learned | 2 |\n"
    )
    text = report.collect([str(sweep)], results_dir=tmp_path / "none", write=False)
    assert "\n## Sweep summary: p004_blend\n" in text and "\n### all jobs (seeds 0, 1; jobs 0, 1)\n" in text
    assert f"(from `{sweep / 'summary.md'}`)" in text and "## p004_blend (run" not in text


def test_command_line_is_a_hydra_app(tmp_path):
    run = tmp_path / "run"
    write_results([_row("hand-tuned", 0.125), _row("learned", 0.1)], run, title="difffilter results: p004_blend")
    results = tmp_path / "results"
    cmd = [sys.executable, str(ROOT / "experiments" / "report.py"), f"runs=[{run}]", f"results_dir={results}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| p004_blend | 0.125 | 0.1 |" in (results / "REPORT.md").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results", "run"]  # no outputs/ or .hydra/ left behind


def test_comments_in_a_sections_code_blocks_stay_comments(report, tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    section = "# p002_pdr\n\n### family\n\n```\n# a shell comment, not a heading\npython x.py\n```\n\n"
    section += "| filter | rmse_pos |\n|---|---|\n| hand-tuned | 2 |\n"
    (results / "p002_pdr.md").write_text(section)
    text = report.collect(results_dir=results, write=False)
    assert "\n## p002_pdr\n" in text and "\n#### family\n" in text
    assert "\n# a shell comment, not a heading\n" in text and "## a shell comment" not in text
