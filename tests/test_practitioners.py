"""The practitioners overlays (issue 25, results/p00_practitioners.md) and their summary.

Fast: each overlay composes to its family's experiment plus baselines only (so the family's own
rows are unchanged), and ``experiments.practitioners`` pairs learned with the best non-learned
row of a synthetic sweep (checked against the hand-computed mean difference).  Slow: every
overlay runs end to end under ``debug=smoke``."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from difffilter.evaluate.intervals import crossed_interval
from experiments import results_report
from experiments.practitioners import best_non_learned, summarize_practitioners
from experiments.results_report import METHODS, Family, build_report, summary_cells
from experiments.results_tables import fmt_ci, read_rows
from tests.smoke_helpers import run_train_smoke

ROOT = Path(__file__).resolve().parents[1]
OVERLAYS = sorted(p.stem for p in (ROOT / "experiments" / "papers").glob("*/conf/experiment/*_practitioners.yaml"))
PRACTITIONER_ROWS = {"validation-search", "sage-husa", "vb-akf"}  # and `textbook` where a rule exists
#: The family experiment (and overrides) each overlay extends, where its name is not ``<family>_practitioners``.
FAMILY_OF = {
    "p002_disturbed_practitioners": ("p002_pdr", "scenario=p002_disturbed"),
    "p000_gyro_practitioners": ("p000_gpsdr", "scenario=p000_gyro"),
    "p000_gps_practitioners": ("p000_gpsdr", "scenario=p000_gps"),
    "p000_odometer_practitioners": ("p000_gpsdr", "scenario=p000_odometer"),
    "p000_nominal_practitioners": ("p000_gpsdr", "scenario=p000_random"),
    # p003's family sweeps start every replicate from perturbed values (experiments/reproduce.py)
    "p003_physical_practitioners": ("p003_physical", "learner.init_perturbation=0.3"),
    "p003_modes_practitioners": ("p003_modes", "learner.init_perturbation=0.3"),
    "p003_imm_sins_practitioners": ("p003_imm_sins", "learner.init_perturbation=0.3"),
}


def _compose(experiment: str, *overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={experiment}", *overrides])
    return OmegaConf.to_container(cfg, resolve=False)  # type: ignore[return-value]


def test_there_are_overlays():
    assert {"p001_elevation_practitioners", "p004_urban_practitioners", "p002_disturbed_practitioners"} <= set(OVERLAYS)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_overlay_only_adds_baselines_to_its_family(overlay):
    family, *overrides = FAMILY_OF.get(overlay, (overlay.removesuffix("_practitioners"),))
    base, new = _compose(family, *overrides), _compose(overlay)
    added = new["experiment"].pop("baselines")
    kept = base["experiment"].pop("baselines") or {}
    assert new["experiment"].pop("name") == overlay and base["experiment"].pop("name") == family
    assert new == base  # data, model, filter, training, test: the family's own
    assert {k: added[k] for k in kept} == kept  # the family's baselines untouched
    assert PRACTITIONER_ROWS <= set(added) - set(kept)


def _write_sweep(root: Path, per_seed: dict[str, list[list[float]]], cpu: dict[str, list[float]]) -> None:
    for seed in range(len(next(iter(per_seed.values())))):
        job = root / str(seed)
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(f"- seed={seed}\n")
        with (job / "per_run.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["filter", "run", "rmse_pos"])
            for name, seeds in per_seed.items():
                w.writerows([name, run, v] for run, v in enumerate(seeds[seed]))
        with (job / "results.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["filter", "rmse_pos", "tuning_cpu_s"])
            for name in per_seed:
                w.writerow([name, 0.0, cpu[name][seed] if name in cpu else "nan"])


def test_summary_pairs_learned_with_the_best_non_learned_row(tmp_path):
    gen = torch.Generator().manual_seed(0)
    runs, seeds = 12, 5
    hand = (2.0 + torch.rand(runs, generator=gen, dtype=torch.float64)).tolist()
    textbook = [h - 0.5 for h in hand]  # the best non-learned row, the same in every seed
    learned = [[t - 0.1 * (s + 1) + 0.01 * r for r, t in enumerate(textbook)] for s in range(seeds)]
    search = [[h - 0.2 for h in hand] for _ in range(seeds)]
    per_seed = {"hand-tuned": [hand] * seeds, "learned": learned, "textbook": [textbook] * seeds, "validation-search": search}
    cpu = {"learned": [10.0, 11.0, 12.0, 13.0, 14.0], "validation-search": [1.0, 2.0, 3.0, 4.0, 5.0]}
    _write_sweep(tmp_path, per_seed, cpu)
    rows = read_rows(summarize_practitioners(tmp_path))
    with (tmp_path / "summary.csv").open(newline="") as fh:
        assert best_non_learned(list(csv.DictReader(fh)), "") == "textbook"
    diff = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned", "diff", "textbook"))
    pct = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned", "diff_pct", "textbook"))
    expect = sum(learned[s][r] - textbook[r] for s in range(seeds) for r in range(runs)) / (seeds * runs)
    assert diff.estimate == pytest.approx(expect, rel=1e-12)
    assert pct.estimate == pytest.approx(100 * expect / (sum(textbook) / runs), rel=1e-12)
    iv = crossed_interval(torch.tensor(learned, dtype=torch.float64) - torch.tensor(textbook, dtype=torch.float64), 0.95)
    assert (diff.lo, diff.hi) == pytest.approx((iv.lo, iv.hi), rel=1e-12) and diff.hi < 0
    tuning = {r.filter: r for r in rows if r.quantity == "tuning_cpu_s"}
    assert set(tuning) == {"learned", "validation-search"}
    assert (tuning["validation-search"].estimate, tuning["validation-search"].lo, tuning["validation-search"].hi) == (3.0, 1.0, 5.0)
    # REPORT's row: best = textbook, the paired cell from the row above, CPU-s in the cells
    (tmp_path / "data").mkdir()
    cells = summary_cells(Family("x", "p00x", "mis-specified", "synthetic", "x.md", str(tmp_path)), rows)
    assert cells[3 + len(METHODS)] == "textbook rule" and cells[5].endswith("; 3 CPU-s")
    row = dict(zip(results_report._HEADER, cells, strict=True))
    assert row["learned - best non-learned, % [95 %]"] == fmt_ci(pct.estimate, pct.lo, pct.hi) and row["verdict"] == "win"
    assert not any(r.reference == "hand-tuned" for r in rows) and not math.isnan(diff.lo)


def test_gap_closed_is_measured_against_the_named_oracle_row(tmp_path):
    # p002_infamily_exactref: G against "exact UKF", not against the row called "oracle"
    hand, exact, oracle = [3.0, 4.0, 5.0, 6.0], [1.0, 2.0, 3.0, 2.0], [2.0, 3.0, 4.0, 5.0]
    learned = [[e + 0.5 for e in exact], [e + 1.0 for e in exact]]
    per_seed = {"hand-tuned": [hand] * 2, "learned": learned, "exact UKF": [exact] * 2, "oracle": [oracle] * 2}
    _write_sweep(tmp_path, per_seed, {})
    gap = next(r for r in read_rows(summarize_practitioners(tmp_path, oracle="exact UKF")) if r.quantity == "gap_closed")
    mean = sum(map(sum, learned)) / 8
    assert gap.estimate == pytest.approx((sum(hand) / 4 - mean) / (sum(hand) / 4 - sum(exact) / 4), rel=1e-12)
    default = next(r for r in read_rows(summarize_practitioners(tmp_path)) if r.quantity == "gap_closed")
    assert default.estimate == pytest.approx((sum(hand) / 4 - mean) / (sum(hand) / 4 - sum(oracle) / 4), rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_overlay_runs_end_to_end(tmp_path, overlay):
    rows, _ = run_train_smoke(tmp_path, overlay)
    by_name = {r["filter"]: r for r in rows}
    assert PRACTITIONER_ROWS <= set(by_name)
    for name in PRACTITIONER_ROWS:
        assert math.isfinite(float(by_name[name]["rmse_pos"])), name
    for name in PRACTITIONER_ROWS:  # tuned on validation: a CPU cost
        assert float(by_name[name]["tuning_cpu_s"]) > 0, name


def test_report_row_of_a_family_with_practitioners_comes_from_their_sweep(tmp_path):
    data = tmp_path / "results" / "data"
    data.mkdir(parents=True)
    header = "group,filter,quantity,estimate,lo,hi,seeds,runs,reference\n"
    (data / "x.csv").write_text(header + ",hand-tuned,rmse_pos,2.0,1.9,2.1,1,10,\n,learned,rmse_pos,1.5,1.4,1.6,5,10,\n")
    (data / "x_practitioners.csv").write_text(
        header
        + ",hand-tuned,rmse_pos,2.5,2.4,2.6,1,10,\n,learned,rmse_pos,1.6,1.5,1.7,5,10,\n"
        + ",textbook,rmse_pos,1.7,1.6,1.8,1,10,\n,learned,diff_pct,-5.0,-8.0,-2.0,5,10,textbook\n"
    )
    fam = Family("x", "p00x", "mis-specified", "synthetic", "x.md", "outputs/x", practitioners=True)
    report = build_report((fam,), tmp_path)
    row = next(line for line in report.splitlines() if line.startswith("| p00x"))
    assert "synthetic, practitioners' rows" in row and "| 2.5 [2.4, 2.6] | 1.7 [1.6, 1.8] |" in row
    assert "| textbook rule |" in row and "| -5 [-8, -2] | win |" in row
    assert "detail/x_practitioners.md" in report and "detail/x.md" in report
    assert fam.practitioners_family().sweep == "outputs/practitioners/x"
