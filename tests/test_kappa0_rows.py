"""p000's adaptive rows around a UKF with Julier kappa 0 (issue 25, results/p00_practitioners.md,
"Adaptive rows around a kappa 0 UKF"): the overlays are the declared rows, ``--merge`` adds a
sweep's new non-learned rows to a family's data file only when its shared rows are the file's,
the kappa 0 rows count for the best non-learned row, and ``learned-adaptive-k0`` joins under
its own name."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

from difffilter.evaluate.intervals import crossed_interval
from experiments import results_report
from experiments.practitioners import join_learned_adaptive, main, merge_rows, summarize_practitioners
from experiments.results_report import Family, build_report, summary_cells
from experiments.results_tables import read_rows
from tests.test_learned_adaptive import _compose
from tests.test_practitioners import _write_sweep

FAMILIES = ("nominal", "odometer", "gps", "gyro", "infamily")
K0_ROWS = {"sage-husa-k0": "sage-husa", "vb-akf-k0": "vb-akf", "covariance-matching-k0": "covariance-matching"}


def _kappa(row: dict) -> float:
    return row["filter"]["inner"]["sigma_points"]["kappa"]


@pytest.mark.parametrize("family", FAMILIES)
def test_k0_overlay_is_the_familys_experiment_with_the_practitioners_rows_at_kappa_0(family):
    prac, k0 = _compose(f"p000_{family}_practitioners"), _compose(f"p000_{family}_practitioners_k0")
    rows, declared = k0["experiment"].pop("baselines"), prac["experiment"].pop("baselines")
    assert k0["experiment"].pop("name") == f"p000_{family}_practitioners_k0"
    prac["experiment"].pop("name")
    assert k0 == prac  # data, seeds, filter, training, test runs: the family's own
    assert set(rows) == set(K0_ROWS)
    for name, kappa5 in K0_ROWS.items():
        assert _kappa(rows[name]) == 0.0 and _kappa(declared[kappa5]) == -5.0
        want = copy.deepcopy(declared[kappa5])
        want["filter"]["inner"]["sigma_points"]["kappa"] = 0.0
        assert rows[name] == want, name  # same wrapper, start, grid; only kappa differs


@pytest.mark.parametrize("family", FAMILIES)
def test_learned_adaptive_k0_overlay_is_the_learned_adaptive_job_around_the_kappa_0_ukf(family):
    old, new = _compose(f"p000_{family}_learned_adaptive"), _compose(f"p000_{family}_learned_adaptive_k0")
    k0_rows = _compose(f"p000_{family}_practitioners_k0")["experiment"]["baselines"]
    assert _kappa(old) == -5.0 and new["filter"]["inner"] == k0_rows["sage-husa-k0"]["filter"]["inner"]
    old["filter"]["inner"]["sigma_points"]["kappa"] = 0.0
    assert new["filter"] == old["filter"] and new["learn"] == old["learn"]
    exp, old_exp = new.pop("experiment"), old.pop("experiment")
    new.pop("filter"), old.pop("filter")
    assert new == old  # data, training, learner, seeds
    for key in set(exp) | set(old_exp):
        if key not in ("baselines", "name", "learned_adaptive"):
            assert exp.get(key) == old_exp.get(key), key
    rebuilt = {"paper-constants", "validation-search", *K0_ROWS} | ({"sage-husa"} if family == "infamily" else set())
    assert set(exp["baselines"]) == rebuilt
    for name in rebuilt:
        want = k0_rows[name] if name in K0_ROWS else old_exp["baselines"][name]
        assert exp["baselines"][name] == want, name


def _data(tmp_path: Path, hand: list[float], learned: list[list[float]], others: dict[str, list[list[float]]]) -> Path:
    """A family's data file as the practitioners' summary writes it."""
    sweep = tmp_path / "practitioners"
    _write_sweep(sweep, {"hand-tuned": [hand] * len(learned), "learned": learned, **others}, {"learned": [10.0] * len(learned)})
    data = tmp_path / "family.csv"
    data.write_text(summarize_practitioners(sweep).read_text())
    return data


def _k0_sweep(tmp_path: Path, hand: list[float], learned: list[list[float]], k0: list[list[float]]) -> Path:
    sweep = tmp_path / "k0"
    per_seed = {"hand-tuned": [hand] * len(learned), "learned": learned, "sage-husa-k0": k0}
    _write_sweep(sweep, per_seed, {"learned": [10.0] * len(learned), "sage-husa-k0": [1.0, 2.0, 3.0][: len(learned)]})
    return sweep


HAND = [3.0, 3.4, 2.8, 3.9, 3.1, 3.6]
SEARCH = [[h - 0.3 - 0.01 * s for h in HAND] for s in range(3)]  # the file's best row
LEARNED = [[h - 0.25 + 0.02 * s + 0.01 * r for r, h in enumerate(HAND)] for s in range(3)]


def test_merge_adds_the_new_rows_and_pairs_learned_with_a_new_best(tmp_path):
    data = _data(tmp_path, HAND, LEARNED, {"validation-search": SEARCH, "sage-husa": [[1e40] * 6] * 3})
    before = read_rows(data)
    assert any((r.filter, r.quantity, r.reference) == ("learned", "diff_pct", "validation-search") for r in before)
    k0 = [[h - 0.5 + 0.03 * s for h in HAND] for s in range(3)]  # better than the search: the new best
    lines = merge_rows(_k0_sweep(tmp_path, HAND, LEARNED, k0), data)
    rows = read_rows(data)
    assert "best non-learned sage-husa-k0" in lines[1] and "largest relative difference 0" in lines[0]
    # the file's rows are kept, apart from learned's pairing with the old best
    kept = [r for r in before if r.reference != "validation-search"]
    assert [r for r in rows if r.filter != "sage-husa-k0" and r.reference != "sage-husa-k0"] == kept
    mine = {(r.quantity, r.reference): r for r in rows if r.filter == "sage-husa-k0"}
    assert mine[("rmse_pos", "")].estimate == pytest.approx(sum(map(sum, k0)) / 18, rel=1e-12)
    assert mine[("tuning_cpu_s", "")].estimate == pytest.approx(2.0, rel=1e-12)
    pair = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned", "diff", "sage-husa-k0"))
    iv = crossed_interval(torch.tensor(LEARNED, dtype=torch.float64) - torch.tensor(k0, dtype=torch.float64), 0.95)
    assert (pair.estimate, pair.lo, pair.hi) == pytest.approx((iv.estimate, iv.lo, iv.hi), rel=1e-12) and pair.lo > 0
    # merged again (a rerun): the rows are checked, the file is left as it is
    text = data.read_text()
    assert "unchanged" in merge_rows(tmp_path / "k0", data)[-1] and data.read_text() == text


def test_merge_keeps_the_files_pairing_when_the_new_rows_are_not_the_best(tmp_path):
    data = _data(tmp_path, HAND, LEARNED, {"validation-search": SEARCH})
    before = read_rows(data)
    k0 = [[h + 0.5 for h in HAND]] * 3
    lines = merge_rows(_k0_sweep(tmp_path, HAND, LEARNED, k0), data)
    rows = read_rows(data)
    assert "best non-learned validation-search" in lines[1]
    assert rows[: len(before)] == before and {r.filter for r in rows[len(before) :]} == {"sage-husa-k0"}


def test_merge_refuses_a_sweep_whose_shared_rows_are_not_the_files(tmp_path):
    data = _data(tmp_path, HAND, LEARNED, {"validation-search": SEARCH})
    text = data.read_text()
    retrained = [[v * (1 + 1e-7) for v in seed] for seed in LEARNED]  # another code state moved learned
    with pytest.raises(ValueError, match="'learned' rmse_pos  estimate 3.095.*nothing merged"):
        merge_rows(_k0_sweep(tmp_path, HAND, retrained, [[h - 0.5 for h in HAND]] * 3), data)
    assert data.read_text() == text
    with pytest.raises(SystemExit):  # --merge needs --into
        main(["--merge", str(tmp_path / "k0")])


def _adaptive_sweep(tmp_path: Path, rows: dict[str, list[list[float]]]) -> Path:
    sweep = tmp_path / "la_k0"
    _write_sweep(sweep, {"hand-tuned": [[h + 1.0 for h in HAND]] * 3, **rows}, {"learned": [20.0, 21.0, 22.0]})
    return sweep


def test_learned_adaptive_k0_joins_under_its_name_paired_with_a_kappa_0_best(tmp_path):
    data = _data(tmp_path, HAND, LEARNED, {"validation-search": SEARCH})
    k0 = [[h - 0.5 for h in HAND]] * 3
    merge_rows(_k0_sweep(tmp_path, HAND, LEARNED, k0), data)
    adaptive = [[h - 0.6 - 0.01 * s for h in HAND] for s in range(3)]
    job = {"learned": adaptive, "paper-constants": [HAND] * 3, "validation-search": SEARCH, "sage-husa-k0": k0}
    sweep = _adaptive_sweep(tmp_path, job)
    with pytest.raises(ValueError, match="learned adaptive row's own name"):
        join_learned_adaptive(sweep, data, name="sage-husa-k0")
    main(["--adaptive", str(sweep), "--name", "learned-adaptive-k0", "--into", str(data)])
    rows = read_rows(data)
    assert not any(r.filter == "learned-adaptive" for r in rows)
    pair = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned-adaptive-k0", "diff", "sage-husa-k0"))
    iv = crossed_interval(torch.tensor(adaptive, dtype=torch.float64) - torch.tensor(k0, dtype=torch.float64), 0.95)
    assert pair.estimate == pytest.approx(iv.estimate, rel=1e-12) and pair.hi < 0
    # a kappa 0 row rebuilt differently in the learned adaptive job: refused
    moved = {**job, "sage-husa-k0": [[v + 1e-6 for v in k0[0]]] * 3}
    with pytest.raises(ValueError, match="'sage-husa-k0'.*no pairing"):
        join_learned_adaptive(_adaptive_sweep(tmp_path / "moved", moved), data, name="learned-adaptive-k0")
    # the kappa 0 sweep merged again after the join (a rerun): checked, nothing changed; new rows refused
    text = data.read_text()
    merge_rows(tmp_path / "k0", data)
    assert data.read_text() == text
    _write_sweep(tmp_path / "more", {"hand-tuned": [HAND] * 3, "learned": LEARNED, "vb-akf-k0": k0}, {})
    with pytest.raises(ValueError, match="learned adaptive rows: merge first"):
        merge_rows(tmp_path / "more", data)


def test_report_counts_the_kappa_0_rows_for_the_best_and_shows_them_in_their_columns(tmp_path):
    data = tmp_path / "results" / "data"
    data.mkdir(parents=True)
    header = "group,filter,quantity,estimate,lo,hi,seeds,runs,reference\n"
    (data / "x_practitioners.csv").write_text(
        header
        + ",hand-tuned,rmse_pos,4.2,4.1,4.3,1,30,\n,learned,rmse_pos,4.19,4.1,4.3,5,30,\n"
        + ",validation-search,rmse_pos,4.08,4.0,4.1,5,30,\n,sage-husa,rmse_pos,7e42,-8e42,2e43,5,30,\n"
        + ",sage-husa-k0,rmse_pos,4.0,3.9,4.1,5,30,\n,sage-husa-k0,tuning_cpu_s,1.5,1.0,2.0,5,,\n"
        + ",learned,diff_pct,4.75,4.0,5.5,5,30,sage-husa-k0\n"
        + ",learned-adaptive-k0,rmse_pos,3.9,3.8,4.0,5,30,\n,learned-adaptive-k0,diff_pct,-2.5,-3.0,-2.0,5,30,sage-husa-k0\n"
    )
    outcome = "ran, no row: training diverged in every seed"
    fam = Family("x", "p000", "mis-specified", "synthetic", "x.md", "outputs/x", practitioners=True, adaptive_outcome=outcome)
    shown = summary_cells(fam.practitioners_family(), read_rows(data / "x_practitioners.csv"))
    cells = dict(zip(results_report._HEADER, shown, strict=True))
    assert cells["Sage-Husa"] == "7e+42 [-8e+42, 2e+43]; kappa 0: 4 [3.9, 4.1]; 1.5 CPU-s"
    assert cells["best non-learned"] == "Sage-Husa, kappa 0"
    assert (cells["learned - best non-learned, % [95 %]"], cells["verdict"]) == ("4.75 [4, 5.5]", "loss")
    assert cells["learned adaptive"] == f"{outcome}; kappa 0: 3.9 [3.8, 4]"
    assert cells["learned adaptive - best non-learned, % [95 %] (verdict)"] == f"{outcome}; kappa 0: -2.5 [-3, -2] (win)"
    report = build_report((fam,), tmp_path)
    assert "around a kappa 0 UKF against the best non-learned method: x win." in report
    assert "left no row: x (training diverged in every seed)." in report


def test_collect_merges_the_kappa_0_rows_before_joining_the_learned_adaptive_ones(tmp_path, monkeypatch):
    root = tmp_path / "outputs" / "practitioners"
    root.mkdir(parents=True)
    k0 = [[h - 0.5 for h in HAND]] * 3
    _data(root / "x_", HAND, LEARNED, {"validation-search": SEARCH})  # its summary.csv: the practitioners sweep
    (root / "x_" / "practitioners").rename(root / "x")
    _k0_sweep(root / "x_", HAND, LEARNED, k0).rename(root / "x_k0")
    adaptive = [[h - 0.6 for h in HAND]] * 3
    job = {"learned": adaptive, "paper-constants": [HAND] * 3, "validation-search": SEARCH, "sage-husa-k0": k0}
    _adaptive_sweep(root / "x_", job).rename(root / "x_learned_adaptive_k0")
    (tmp_path / "results" / "data").mkdir(parents=True)
    family = Family("x", "p000", "mis-specified", "synthetic", "x.md", "outputs/x", practitioners=True)
    monkeypatch.setattr(results_report, "FAMILIES", (family,))
    results_report.collect(tmp_path)
    rows = read_rows(tmp_path / "results" / "data" / "x_practitioners.csv")
    assert {r.filter for r in rows} == {"hand-tuned", "learned", "validation-search", "sage-husa-k0", "learned-adaptive-k0"}
    pair = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned-adaptive-k0", "diff", "sage-husa-k0"))
    assert pair.estimate == pytest.approx(-0.1, rel=1e-12)
