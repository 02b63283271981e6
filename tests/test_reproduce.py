"""experiments/reproduce.py: its commands are the ones written in the results files, and it runs jobs."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("difffilter_reproduce", ROOT / "experiments" / "reproduce.py")
reproduce = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = reproduce  # dataclasses resolve annotations through sys.modules
assert _spec.loader is not None
_spec.loader.exec_module(reproduce)


def _normalise(command: str) -> str:
    """One command as a comparable line: no `nice`, no trailing comment, single spaces."""
    command = re.sub(r"^\s*nice -n \d+ ", "", command.strip())
    command = re.sub(r"\s+#.*$", "", command)
    command = re.sub(r"^mkdir -p \S+ && ", "", command)  # results files sometimes link/copy into an existing folder
    return " ".join(command.split())


def _written_commands(path: Path) -> set[str]:
    """Every line of a results file that runs something (continuation lines joined), and every
    command quoted inline in its prose."""
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    lines = {_normalise(line) for line in text.splitlines() if re.search(r"python |^\s*(for s in|cp |mkdir )", line)}
    return lines | {_normalise(c) for c in re.findall(r"`(python [^`]+)`", text)}


@pytest.mark.parametrize("job", reproduce.JOBS, ids=lambda j: j.name)
def test_every_command_is_written_in_its_results_file(job):
    written = _written_commands(ROOT / "results" / job.results)
    for command in job.commands:
        assert _normalise(command) in written, f"{job.name}: not in results/{job.results}: {command}"


def test_selection_orders_longest_first_and_rejects_unknown_prefixes():
    chosen = reproduce.select_jobs(["p001", "p004_mems"])
    assert {j.name for j in chosen} == {j.name for j in reproduce.JOBS if j.name.startswith(("p001", "p004_mems"))}
    assert "p004_mems" in {j.name for j in chosen}
    assert [j.cpu_s for j in chosen] == sorted((j.cpu_s for j in chosen), reverse=True)
    with pytest.raises(ValueError, match="--only: 'p9' matches no job"):
        reproduce.select_jobs(["p9"])
    names = [j.name for j in reproduce.JOBS]
    assert len(names) == len(set(names))


def test_runs_jobs_records_times_and_reports_a_failure(tmp_path, capsys):
    jobs = (
        reproduce.Job("a_ok", "x.md", 2.0, (f"echo first > {tmp_path}/a.txt", "python -c 'print(sum(range(10**7)))'")),
        reproduce.Job("b_fails", "x.md", 1.0, ("exit 3", "echo never")),
    )
    out = tmp_path / "out"
    status = reproduce.main(["--out", str(out), "-j", "2"], jobs=jobs)
    assert status == 1
    rows = [line.split("\t") for line in (out / "times.tsv").read_text().splitlines()]
    assert rows[0] == ["job", "status", "wall_s", "cpu_s"]
    by_job = {r[0]: r for r in rows[1:]}
    assert by_job["a_ok"][1] == "0" and by_job["b_fails"][1] == "3"
    assert float(by_job["a_ok"][3]) >= 0.1  # the child python's CPU time is counted
    assert by_job["all"][1] == "1 failed"
    assert "49999995000000" in (out / "a_ok.log").read_text()
    assert "never" not in (out / "b_fails.log").read_text()
    assert "failed: b_fails" in capsys.readouterr().err
    assert (tmp_path / "a.txt").read_text() == "first\n"


def test_dry_run_lists_every_command(capsys):
    assert reproduce.main(["--dry-run", "--only", "p002"]) == 0
    printed = capsys.readouterr().out
    for job in reproduce.JOBS:
        if job.name.startswith("p002"):
            assert all(c in printed for c in job.commands)
    assert "p001" not in printed


def test_bad_job_count_is_an_error():
    with pytest.raises(SystemExit):
        reproduce.main(["-j", "0", "--dry-run"])
