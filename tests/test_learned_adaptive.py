"""The learned adaptive rows of issue 25 (results/p00_practitioners.md, "Learned adaptive"): the
overlays ``<family>_learned_adaptive`` train Sage-Husa (forgetting factor and starting noise
learned) with the family's protocol, and ``python -m experiments.practitioners --adaptive``
joins their ``learned`` row to the family's data file as ``learned-adaptive``, paired with the
best non-learned row rebuilt in the same jobs."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf, open_dict

import difffilter.learn  # noqa: F401  (registers the replicate_seed resolver)
from difffilter.evaluate.intervals import crossed_interval
from experiments.practitioners import join_learned_adaptive, main, summarize_practitioners
from experiments.results_tables import read_rows
from tests.smoke_helpers import run_train_smoke
from tests.test_practitioners import _write_sweep

ROOT = Path(__file__).resolve().parents[1]
#: overlay -> the practitioners overlay it extends (whose training it must keep)
FAMILIES = {
    "p001_elevation_learned_adaptive": "p001_elevation_practitioners",
    "p004_urban_learned_adaptive": "p004_urban_practitioners",
    "p002_disturbed_learned_adaptive": "p002_disturbed_practitioners",
    "p004_mems_learned_adaptive": "p004_mems_practitioners",
    "p004_blend_learned_adaptive": "p004_blend_practitioners",
    "p004_outage_learned_adaptive": "p004_outage_practitioners",
    "p002_pdr_learned_adaptive": "p002_pdr_practitioners",
    "p002_infamily_learned_adaptive": "p002_infamily_practitioners",
    # p003: Sage-Husa around the single simplified UKF of the practitioners' row, not the IMM bank
    "p003_physical_learned_adaptive": "p003_physical_practitioners",
    "p003_modes_learned_adaptive": "p003_modes_practitioners",
    "p003_imm_sins_learned_adaptive": "p003_imm_sins_practitioners",
    "p000_nominal_learned_adaptive": "p000_nominal_practitioners",
    "p000_odometer_learned_adaptive": "p000_odometer_practitioners",
    "p000_gps_learned_adaptive": "p000_gps_practitioners",
    "p000_gyro_learned_adaptive": "p000_gyro_practitioners",
    "p000_infamily_learned_adaptive": "p000_infamily_practitioners",
    "p001_colored_learned_adaptive": "p001_colored_practitioners",
    "p001_multipath_learned_adaptive": "p001_multipath_practitioners",
    "p001_multipath_shared_learned_adaptive": "p001_multipath_shared_practitioners",
}
#: what a learned adaptive job must share with its family's training (everything but the filter and `learn`)
SHARED = ("data", "trainer", "optimizer", "scheduler", "loss", "learner", "seed", "dtype", "model", "scenario")


def _compose(experiment: str) -> dict:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={experiment}"], return_hydra_config=True)
    cfg.hydra.job.num = 0  # set by a launcher; the paths interpolate hydra's run directory
    cfg.hydra.runtime.output_dir = "unused"
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def test_every_learned_adaptive_overlay_is_listed():
    found = {p.stem for p in (ROOT / "experiments" / "papers").glob("*/conf/experiment/*_learned_adaptive.yaml")}
    assert found == set(FAMILIES)


@pytest.mark.parametrize("overlay", sorted(FAMILIES))
def test_overlay_trains_sage_husa_with_the_family_protocol(overlay):
    family, new = _compose(FAMILIES[overlay]), _compose(overlay)
    assert new["learner"].pop("learn") == new["learn"] and family["learner"].pop("learn") == family["learn"]
    # a family that starts learning from a value of a parameter Sage-Husa lacks (p001_colored's Psi = 0)
    # starts from the paper's values instead; nothing else of the learner may differ
    if new["learner"].get("start_params", "absent") is None:
        family["learner"]["start_params"] = None
    for key in SHARED:
        assert new.get(key) == family.get(key), key
    exp, fexp = new["experiment"], family["experiment"]
    for key in ("position_index", "truth_position_index", "metric", "test_name", "extra_tests", "state_blocks"):
        assert exp.get(key) == fexp.get(key), key
    # the trained filter: Sage-Husa around the filter the practitioners' sage-husa row wraps, from b 0.98
    filt = new["filter"]
    assert filt["_target_"] == "difffilter.filters.SageHusa" and filt["b"] == 0.98
    assert filt["inner"] == fexp["baselines"]["sage-husa"]["filter"]["inner"]
    assert (filt["adapt_r"], filt["adapt_q"]) == (True, False)
    assert new["learn"][0] == "b" and set(new["learn"][1:]) <= set(family["learn"])
    # every non-learned row of the family's sweep, on the family's filter where it used the family's
    paper = exp["baselines"]["paper-constants"]
    assert paper["filter"] == family["filter"]
    assert {k: v for k, v in paper["params"].items() if v is not None} == {k: v for k, v in fexp["hand_tuned"].items() if v is not None}
    assert set(fexp["baselines"]) <= set(exp["baselines"])
    for name, spec in fexp["baselines"].items():
        want = spec.get("filter") or family["filter"]
        assert exp["baselines"][name].get("filter") == want, name
        assert exp["baselines"][name].get("tune") == spec.get("tune"), name


def _sweep(root: Path, hand: list[float], rows: dict[str, list[list[float]]]) -> Path:
    _write_sweep(root, {"hand-tuned": [hand] * len(next(iter(rows.values()))), **rows}, {"learned": [20.0, 22.0, 24.0]})
    return root


def _family_csv(tmp_path: Path, hand: list[float], textbook: list[float], search: list[list[float]]) -> Path:
    """A family's data file as the practitioners' summary writes it (plain learned loses to textbook)."""
    learned = [[t + 0.05 * (s + 1) for t in textbook] for s in range(3)]
    per_seed = {"learned": learned, "textbook": [textbook] * 3, "validation-search": search}
    path = summarize_practitioners(_sweep(tmp_path / "practitioners", hand, per_seed))
    return path


def test_join_pairs_learned_adaptive_with_the_best_row_rebuilt_in_its_jobs(tmp_path):
    gen = torch.Generator().manual_seed(1)
    runs = 10
    hand = (3.0 + torch.rand(runs, generator=gen, dtype=torch.float64)).tolist()
    textbook = [h - 0.4 for h in hand]  # the best non-learned row
    search = [[h - 0.3 + 0.01 * s for h in hand] for s in range(3)]
    data = _family_csv(tmp_path, hand, textbook, search)
    adaptive = [[t - 0.2 - 0.02 * (s + 1) - 0.001 * r for r, t in enumerate(textbook)] for s in range(3)]
    # the learned adaptive jobs: their own hand-tuned (Sage-Husa at its start) differs, the rebuilt rows do not
    start = [h + 1.0 for h in hand]
    job = {"learned": adaptive, "paper-constants": [hand] * 3, "textbook": [textbook] * 3, "validation-search": search}
    sweep = _sweep(tmp_path / "adaptive", start, job)
    lines = join_learned_adaptive(sweep, data)
    rows = read_rows(data)
    mine = {(r.quantity, r.reference): r for r in rows if r.filter == "learned-adaptive"}
    assert set(mine) == {
        ("rmse_pos", ""),
        ("diff", ""),
        ("diff_pct", ""),
        ("diff", "textbook"),
        ("diff_pct", "textbook"),
        ("tuning_cpu_s", ""),
    }
    a, t, h = (torch.tensor(x, dtype=torch.float64) for x in (adaptive, textbook, hand))
    iv = crossed_interval(a - t, 0.95)
    got = mine[("diff", "textbook")]
    assert (got.estimate, got.lo, got.hi) == pytest.approx((iv.estimate, iv.lo, iv.hi), rel=1e-12) and got.hi < 0
    assert mine[("diff_pct", "textbook")].estimate == pytest.approx(100 * iv.estimate / t.mean().item(), rel=1e-12)
    assert mine[("diff", "")].estimate == pytest.approx((a - h).mean().item(), rel=1e-12)  # against the paper's constants
    assert mine[("rmse_pos", "")].estimate == pytest.approx(a.mean().item(), rel=1e-12)
    assert (mine[("tuning_cpu_s", "")].estimate, mine[("rmse_pos", "")].seeds) == (22.0, "3")
    assert "- textbook:" in lines[0] and "learned (unpaired, means)" in lines[0] and "hand-tuned 0" in lines[0]
    # joining again replaces the rows, and the family's other rows are untouched
    before = [r for r in rows if r.filter != "learned-adaptive"]
    join_learned_adaptive(sweep, data)
    again = read_rows(data)
    assert [r for r in again if r.filter != "learned-adaptive"] == before
    assert sum(r.filter == "learned-adaptive" for r in again) == len(mine)


def test_join_refuses_jobs_whose_rebuilt_rows_are_not_the_familys(tmp_path):
    runs = 6
    hand = [2.0 + 0.1 * r for r in range(runs)]
    textbook = [h - 0.4 for h in hand]
    data = _family_csv(tmp_path, hand, textbook, [[h - 0.3 for h in hand]] * 3)
    text = data.read_text()
    other = [[t + 1e-6 for t in textbook]] * 3  # another test set or code state moves the row
    job = {"learned": [textbook] * 3, "paper-constants": [hand] * 3, "textbook": other}
    sweep = _sweep(tmp_path / "adaptive", hand, job)
    with pytest.raises(ValueError, match="'textbook'.*no pairing"):
        join_learned_adaptive(sweep, data)
    assert data.read_text() == text  # nothing written
    with pytest.raises(SystemExit):  # --adaptive needs --into
        main(["--adaptive", str(sweep)])


@pytest.mark.slow
@pytest.mark.parametrize("overlay", sorted(FAMILIES))
def test_overlay_runs_end_to_end(tmp_path, overlay):
    rows, _ = run_train_smoke(tmp_path, overlay)
    by_name = {r["filter"]: r for r in rows}
    assert {"hand-tuned", "learned", "paper-constants", "validation-search", "sage-husa"} <= set(by_name)
    assert math.isfinite(float(by_name["learned"]["rmse_pos"])) and by_name["learned"]["parameters"].startswith("b=")
    with (tmp_path / "results.csv").open(newline="") as fh:
        assert float(next(r for r in csv.DictReader(fh) if r["filter"] == "learned")["tuning_cpu_s"]) > 0


def _family_x(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[list[float], list[float], Path]:
    """Family ``x``'s practitioners sweep under ``tmp_path/outputs/practitioners/x`` with its summary
    (plain learned loses to the textbook rule), the results' data folder, and ``x`` as
    ``results_report``'s only family: ``(hand, textbook, sweep folder)``."""
    import experiments.results_report as report

    monkeypatch.setattr(
        report, "FAMILIES", (report.Family("x", "p00x", "mis-specified", "synthetic", "x.md", "outputs/x", practitioners=True),)
    )
    (tmp_path / "results" / "data").mkdir(parents=True)
    hand = [2.0 + 0.1 * r for r in range(6)]
    textbook = [h - 0.4 for h in hand]
    prac = tmp_path / "outputs" / "practitioners" / "x"
    prac.parent.mkdir(parents=True)
    learned = [[t + 0.05 * (s + 1) for t in textbook] for s in range(3)]
    summarize_practitioners(_sweep(prac, hand, {"learned": learned, "textbook": [textbook] * 3}))
    return hand, textbook, prac


def test_collect_joins_the_learned_adaptive_rows_again_after_copying_a_practitioners_summary(tmp_path, monkeypatch):
    import experiments.results_report as report

    hand, textbook, prac = _family_x(tmp_path, monkeypatch)
    job = {"learned": [[t - 0.1 for t in textbook]] * 3, "paper-constants": [hand] * 3, "textbook": [textbook] * 3}
    _sweep(tmp_path / "outputs" / "practitioners" / "x_learned_adaptive", hand, job)
    report.collect(tmp_path)
    rows = read_rows(tmp_path / "results" / "data" / "x_practitioners.csv")
    joined = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned-adaptive", "diff", "textbook"))
    assert joined.estimate == pytest.approx(-0.1, rel=1e-12)
    assert {r.filter for r in rows} == {"hand-tuned", "learned", "textbook", "learned-adaptive"}


def test_collect_joins_the_learned_adaptive_rows_to_the_committed_file_when_the_family_did_not_run(tmp_path, monkeypatch):
    """reproduce.py's learned adaptive jobs leave the join to ``--collect``: where the family's own
    sweep did not run (``--only``), the committed data file gets the rows, its shared rows checked."""
    import experiments.results_report as report

    hand, textbook, prac = _family_x(tmp_path, monkeypatch)
    committed = tmp_path / "results" / "data" / "x_practitioners.csv"
    (prac / "summary.csv").rename(committed)  # the committed file; the family's sweep left no summary
    job = {"learned": [[t - 0.1 for t in textbook]] * 3, "paper-constants": [hand] * 3, "textbook": [textbook] * 3}
    _sweep(tmp_path / "outputs" / "practitioners" / "x_learned_adaptive", hand, job)
    assert report.collect(tmp_path) == []
    rows = read_rows(committed)
    joined = next(r for r in rows if (r.filter, r.quantity, r.reference) == ("learned-adaptive", "diff", "textbook"))
    assert joined.estimate == pytest.approx(-0.1, rel=1e-12)
    # a learned adaptive sweep whose rebuilt rows are not the committed file's is refused
    shutil.rmtree(tmp_path / "outputs" / "practitioners" / "x_learned_adaptive")
    job["textbook"] = [[t + 0.01 for t in textbook]] * 3
    _sweep(tmp_path / "outputs" / "practitioners" / "x_learned_adaptive", hand, job)
    with pytest.raises(ValueError):
        report.collect(tmp_path)
