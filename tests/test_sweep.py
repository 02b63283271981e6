"""A multirun over seeds leaves one summary table (experiments.runner.sweep): numbers checked
against independent numpy/scipy computations on synthetic job directories, and end to end with
`experiments/train.py -m seed=...` (the Hydra callback)."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from difffilter.evaluate.evaluation import read_per_run, write_per_run
from difffilter.evaluate.intervals import gap_closed
from experiments.runner.sweep import main, summarize_sweep

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64


def _job(root: Path, num: int, overrides: list[str], per_run: dict[str, dict[str, np.ndarray]], band: float) -> None:
    job = root / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    write_per_run({f: {k: torch.tensor(v, dtype=f64) for k, v in m.items()} for f, m in per_run.items()}, job / "per_run.csv")
    with (job / "results.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["filter", "anees_dof", "anees_step_band_frac", "nees_position_dof", "nees_position_step_band_frac"])
        for f in per_run:
            w.writerow([f, 4.0, band, 2.0, band / 2])


def _rows(path: Path) -> dict[tuple[str, str, str], dict[str, str]]:
    with path.open(newline="") as fh:
        return {(r["group"], r["filter"], r["quantity"]): r for r in csv.DictReader(fh)}


def _t_half(var: float, dof: float) -> float:
    return stats.t.ppf(0.975, dof) * math.sqrt(var)


def test_summary_of_synthetic_sweep_matches_independent_computation(tmp_path):
    rng = np.random.default_rng(0)
    seeds, runs = 5, 30
    run_effect = rng.normal(0, 1.0, runs)
    hand = 10 + run_effect + rng.normal(0, 0.2, runs)
    oracle = 8 + run_effect + rng.normal(0, 0.2, runs)
    learned = 8.6 + run_effect + rng.normal(0, 0.3, (seeds, 1)) + rng.normal(0, 0.2, (seeds, runs))
    nees_l = 4.5 + rng.normal(0, 0.5, (seeds, runs))
    for s in range(seeds):
        per_run = {
            "hand-tuned": {"rmse_pos": hand, "anees": 4 + 0 * hand, "nees_position": 2 + 0 * hand},
            "learned": {"rmse_pos": learned[s], "anees": nees_l[s], "nees_position": nees_l[s] / 2},
            "oracle": {"rmse_pos": oracle, "anees": 4 + 0 * hand, "nees_position": 2 + 0 * hand},
        }
        _job(tmp_path, s, ["experiment=x", f"seed={s}"], per_run, band=0.9 + 0.01 * s)
    # a second group (two other jobs of the same sweep) whose test runs differ between seeds
    for s in range(2):
        per_run = {"hand-tuned": {"rmse_pos": hand + s}, "learned": {"rmse_pos": hand + s - 1.0 - 0.1 * s}}
        _job(tmp_path, 10 + s, ["experiment=y", f"seed={s}"], per_run, band=0.5)
    md_path, csv_path = summarize_sweep(tmp_path, draws=1000)
    rows = _rows(csv_path)
    # hand-tuned does not depend on the seed: t-interval over runs
    r = rows[("experiment=x", "hand-tuned", "rmse_pos")]
    lo, hi = stats.t.interval(0.95, runs - 1, loc=hand.mean(), scale=stats.sem(hand))
    assert (float(r["estimate"]), float(r["lo"]), float(r["hi"]), r["seeds"]) == (
        pytest.approx(hand.mean()),
        pytest.approx(lo),
        pytest.approx(hi),
        "1",
    )
    # learned: seeds x runs crossed interval (seed-mean and run-mean variances, Satterthwaite)
    for key, y in ((("experiment=x", "learned", "rmse_pos")), learned), ((("experiment=x", "learned", "diff")), learned - hand):
        vs, vr = y.mean(1).var(ddof=1) / seeds, y.mean(0).var(ddof=1) / runs
        half = _t_half(vs + vr, (vs + vr) ** 2 / (vs**2 / (seeds - 1) + vr**2 / (runs - 1)))
        r = rows[key]
        assert float(r["estimate"]) == pytest.approx(y.mean()) and float(r["hi"]) == pytest.approx(y.mean() + half)
    pct = rows[("experiment=x", "learned", "diff_pct")]
    assert float(pct["estimate"]) == pytest.approx(100 * (learned - hand).mean() / hand.mean())
    gap = rows[("experiment=x", "learned", "gap_closed")]
    ref = gap_closed(hand, learned, oracle, draws=1000)
    assert float(gap["estimate"]) == pytest.approx((hand.mean() - learned.mean()) / (hand.mean() - oracle.mean()))
    assert (float(gap["lo"]), float(gap["hi"])) == (pytest.approx(ref.lo), pytest.approx(ref.hi))
    # consistency per block: the learned ANEES over seeds x runs against d, band fraction averaged over seeds
    a = rows[("experiment=x", "learned", "anees_all")]
    assert float(a["estimate"]) == pytest.approx(nees_l.mean()) and float(a["reference"]) == 4.0
    assert float(rows[("experiment=x", "learned", "step_band_frac_all")]["estimate"]) == pytest.approx(0.92)
    assert float(rows[("experiment=x", "learned", "anees_position")]["estimate"]) == pytest.approx(nees_l.mean() / 2)
    # group y: different runs per seed -> t over the per-seed means
    y = rows[("experiment=y", "learned", "diff")]
    d = np.array([-1.0, -1.1])
    assert float(y["estimate"]) == pytest.approx(d.mean()) and float(y["hi"]) == pytest.approx(d.mean() + _t_half(d.var(ddof=1) / 2, 1))
    assert ("experiment=y", "learned", "gap_closed") not in rows
    md = md_path.read_text()
    assert "## experiment=x (seeds 0, 1, 2, 3, 4; jobs 0, 1, 2, 3, 4)" in md and "## experiment=y" in md and "different test runs" in md
    # the verdict: the ANEES interval against the 95 % chi-square band of the mean NEES over the N runs
    n_runs = int(rows[("experiment=x", "learned", "rmse_pos")]["runs"])
    band = stats.chi2.ppf([0.025, 0.975], 4 * n_runs) / n_runs
    lo, hi = float(a["lo"]), float(a["hi"])
    want = (
        "consistent"
        if band[0] <= lo and hi <= band[1]
        else "over-confident"
        if lo > band[1]
        else "under-confident"
        if hi < band[0]
        else "undecided"
    )
    assert "| learned | all | 4 | " in md and f"] | {want} | 92 % |" in md
    assert "| hand-tuned | all | 4 | 4 [4, 4] | consistent |" in md  # exactly d on every run: inside the band
    # the command line rebuilds the same summary
    assert main([str(tmp_path), "--draws", "1000"]).read_text() == md


def test_summary_needs_jobs(tmp_path):
    with pytest.raises(FileNotFoundError, match="per_run.csv"):
        summarize_sweep(tmp_path)


def test_multirun_over_seeds_writes_summary(tmp_path):
    """`experiments/train.py -m seed=0,1,2` (smoke size, seeded init perturbation): every job writes
    per_run.csv on the same test runs, the callback writes summary.md/.csv at the sweep root."""
    sweep = tmp_path / "sweep"
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "train.py"),
        "-m",
        "debug=smoke",
        "seed=0,1,2",
        "trainer.max_epochs=1",
        "learner.init_perturbation=0.2",
        "logger=csv",
        f"hydra.sweep.dir={sweep}",
        f"paths.log_dir={tmp_path}/logs",
    ]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    jobs = [read_per_run(sweep / str(k) / "per_run.csv") for k in range(3)]
    for job in jobs[1:]:
        torch.testing.assert_close(job["hand-tuned"]["rmse_pos"], jobs[0]["hand-tuned"]["rmse_pos"], rtol=0, atol=0)  # same test runs
        assert not torch.equal(job["learned"]["rmse_pos"], jobs[0]["learned"]["rmse_pos"])  # other data and start
    rows = _rows(sweep / "summary.csv")
    learned = np.stack([j["learned"]["rmse_pos"].numpy() for j in jobs])
    r = rows[("", "learned", "rmse_pos")]  # one group: no override other than the seed differs
    assert float(r["estimate"]) == pytest.approx(learned.mean()) and r["seeds"] == "3"
    md = (sweep / "summary.md").read_text()
    assert "## all jobs (seeds 0, 1, 2; jobs 0, 1, 2)" in md and "learner.init_perturbation=0.2" in md


def test_extra_test_sets_are_groups_of_their_own(tmp_path):
    # <job>/extra_tests/<name>/per_run.csv: the job's overrides plus test=<name>; the main sets read test=main
    rng = np.random.default_rng(1)
    hand, scripted = 5 + rng.normal(0, 1, 10), 9 + rng.normal(0, 1, 10)
    learned = 4 + rng.normal(0, 0.5, (3, 10))
    for s in range(3):
        _job(tmp_path, s, ["experiment=x", f"seed={s}"], {"hand-tuned": {"rmse_pos": hand}, "learned": {"rmse_pos": learned[s]}}, band=0.9)
        extra = tmp_path / str(s) / "extra_tests" / "scripted"
        extra.mkdir(parents=True)
        runs = {"hand-tuned": {"rmse_pos": torch.tensor(scripted)}, "learned": {"rmse_pos": torch.tensor(scripted - 1.0 - s)}}
        write_per_run(runs, extra / "per_run.csv")
    _, csv_path = summarize_sweep(tmp_path, draws=200)
    rows = _rows(csv_path)
    assert float(rows[("test=main", "learned", "rmse_pos")]["estimate"]) == pytest.approx(learned.mean())
    assert float(rows[("test=scripted", "hand-tuned", "rmse_pos")]["estimate"]) == pytest.approx(scripted.mean())
    assert float(rows[("test=scripted", "learned", "diff")]["estimate"]) == pytest.approx(-2.0)
    md = (tmp_path / "summary.md").read_text()
    assert "## test=scripted (seeds 0, 1, 2; jobs 0, 1, 2)" in md
