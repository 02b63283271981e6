"""The real-data protocol end to end on small drives cut from the real smartLoc files: it runs on
any folder of libRSF drives, selects on validation, writes its report, and the transfer command
evaluates the selected filters on a second folder (a "second processing": the same epochs with
different pseudorange corrections)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from experiments.papers.smartloc import load_drive, protocol, report
from experiments.papers.smartloc.report import resolve_config, run_evaluation, run_protocol, run_transfer

from .librsf_fixture import HAVE_DATA, write_drive

pytestmark = pytest.mark.skipif(not HAVE_DATA, reason="the smartLoc excerpt tests/assets/librsf/smartlocx_* is missing")
ROOT = Path(__file__).resolve().parents[1]
SMALL = {
    "epochs": 1,
    "seeds": 1,
    "variants": ["elev_cn0"],
    "windows": {"length": 30, "stride": 15},
    "val_windows": {"length": 30, "stride": 15},
}
SMALL_BOOT = {"block": 10, "draws": 200, "seed": 0}


def _reprocessed(lines: list[str]) -> list[str]:
    """Every GLONASS pseudorange +7 m and every GPS one -2 m (other corrections, same epochs)."""
    out = []
    for ln in lines:
        f = ln.split()
        if f[0] == "pseudorange3":
            f[2] = repr(float(f[2]) + (7.0 if f[9] == "4" else -2.0))
        out.append(" ".join(f))
    return out


def _hydra(value: object) -> str:
    """A value in Hydra's override grammar (unquoted keys and strings)."""
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{_hydra(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ",".join(_hydra(v) for v in value) + "]"
    return str(value)


def _config(folder: Path) -> dict:
    base = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc.yaml"), resolve=True)
    base.update(SMALL, bootstrap=SMALL_BOOT)
    return resolve_config(base, str(folder))


def test_protocol_on_a_folder_and_transfer_to_a_second_processing(tmp_path) -> None:
    drives, second = tmp_path / "drives", tmp_path / "second"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    write_drive(second, "Cut", start=100.0, stop=140.0, edit=_reprocessed)
    run = tmp_path / "run"
    summary = run_protocol(_config(drives), run, workers=1)
    assert summary["drives"] == ["Cut"] and set(summary["folds"]) == {"A", "B"}
    for fold in summary["folds"].values():
        names = [r["filter"] for r in fold["test"]]
        assert names == ["hand-tuned", "learned-elev_cn0", "untrained-gate", "ekf-no-gate", "snapshot-wls", "sage-husa", "vb-adaptive-r"]
        sel = fold["selection"]["learned-elev_cn0"]
        assert sel["seed"] in (0, "start") and sel["epoch"] in (0, 1)
        scores = fold["val_scores"]["elev_cn0/seed0"]
        assert len(scores) == 2 and sel["val_score"] <= min(scores) + 1e-12
        assert all(k in fold["test"][1] for k in ("d_median_lo", "d_rms_hi"))
    for name in ("results.md", "summary.json", "selected.pt", "noise_model_fold_A.png", "noise_model_fold_B.png"):
        assert (run / name).exists(), name
    for fold, fs in summary["folds"].items():  # results.csv per fold: the columns and row names of the ranging protocol
        with open(run / fold / "results.csv") as fh:
            rows = list(csv.DictReader(fh))
        assert [r["filter"] for r in rows] == ["hand-tuned", "learned", *names[2:]]
        assert list(rows[0])[:4] == ["filter", "pos_err_p50", "rmse_pos", "pos_err_p95"] and {"u_rms_lo", "d_median_hi"} <= set(rows[0])
        for r, t in zip(rows, fs["test"], strict=True):
            for col, stat in (("pos_err_p50", "median"), ("rmse_pos", "rms"), ("pos_err_p95", "p95")):
                assert float(r[col]) == pytest.approx(t[stat], rel=1e-5)
        assert rows[0]["d_rms"] == "" and rows[2]["u_rms"] == "" and rows[1]["u_rms"] != ""
    assert any((run / "tb").rglob("events.out.tfevents.*"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = EventAccumulator(str(run / "tb" / "noise_models"))
    tb.Reload()
    tags = set(tb.Tags()["scalars"])
    if summary["folds"]["A"]["selection"]["learned-elev_cn0"]["values"]:  # a learned selection: its gate and noise values
        assert {f"extras/fold_A/learned-elev_cn0/measurement.robust_gate.gate_{k}" for k in ("threshold", "floor", "softness")} <= tags
    assert "noise_model/fold_A" in tb.Tags()["images"]
    again = run_evaluation(run, tmp_path / "eval")  # rebuilt from the saved selections: the same test tables
    for fold, fs in summary["folds"].items():
        assert again["folds"][fold]["tables"]["hand-tuned"] == fs["test"]
        ref = again["folds"][fold]["tables"]["ekf-no-gate"]
        assert [r["filter"] for r in ref] == names and "d_rms" not in ref[names.index("ekf-no-gate")] and "d_rms" in ref[0]
        assert again["folds"][fold]["validation"]["hand-tuned"] == pytest.approx(fs["hand_val"], rel=1e-12)
    out = tmp_path / "transfer"
    result = run_transfer(run, _config(second), out)
    whole = load_drive(second, input_file="Cut_Input.txt", truth_file="Cut_GT.txt").num_epochs
    assert result["drives"] == ["Cut"] and result["epochs"] == whole  # every epoch of the drive is tested
    assert [r["filter"] for r in result["test"]][:3] == ["hand-tuned", "learned-elev_cn0 (fold A)", "learned-elev_cn0 (fold B)"]
    assert json.loads((out / "transfer.json").read_text())["trained_in"] == str(run)


@pytest.mark.slow
def test_the_commands_run_given_only_a_folder(tmp_path) -> None:
    """`experiments/realdata.py folder=...` and the transfer command, as README gives them."""
    drives, second = tmp_path / "drives", tmp_path / "second"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    write_drive(second, "Cut", start=100.0, stop=140.0, edit=_reprocessed)
    small = [f"realdata.{k}={_hydra(v)}" for k, v in SMALL.items()]
    small += [f"realdata.bootstrap.{k}={v}" for k, v in SMALL_BOOT.items()]
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "realdata.py"),
        f"folder={drives}",
        "workers=1",
        f"hydra.run.dir={tmp_path / 'run'}",
        *small,
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Fold A: test blocks" in done.stdout
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "realdata.py"),
        f"transfer_from={tmp_path / 'run'}",
        f"folder={second}",
        f"hydra.run.dir={tmp_path / 'tr'}",
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Transfer: filters trained in" in done.stdout and (tmp_path / "tr" / "transfer.json").exists()


def _v2_config(folder: Path) -> dict:
    base = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc.yaml"), resolve=True)
    v2 = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc_v2.yaml"), resolve=True)
    base.update({k: v for k, v in v2.items() if k != "defaults"}, **SMALL, bootstrap=SMALL_BOOT)
    return resolve_config(base, str(folder))


@pytest.mark.parametrize("candidate", [True, False])
def test_v2_keeps_the_hard_gate_and_falls_back_to_hand_tuned_only_when_it_validates_better(tmp_path, candidate) -> None:
    """v2's learned filters keep the hand-tuned hard gate (not learned, rejected ranges detached);
    with the hand-tuned filter as a candidate, a learned selection is used only when its
    validation score is strictly lower, else the "learned" row is the hand-tuned filter, and the
    saved selection rebuilds (re-evaluation and transfer) the same filter."""
    drives = tmp_path / "drives"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    cfg = _v2_config(drives)
    cfg["selection"]["hand_tuned_candidate"] = candidate
    cfg["epochs"] = 2
    spec, loaded = protocol.cached_drives(json.dumps(cfg, sort_keys=True))
    filt = protocol.build_filter(spec, loaded, "scale", torch.zeros(0), learned=True)
    gate = filt.model.measurement.robust_gate
    assert not gate.learnable and float(gate.threshold) == 2.5 and float(gate.floor) == 8.0
    assert type(filt.model.measurement).__name__ == "ConstantGatePseudorange"
    assert not any("gate" in n for n in protocol.learned_names(filt, spec["learn"]))
    run = tmp_path / "run"
    summary = run_protocol(cfg, run, workers=1)
    for fs in summary["folds"].values():
        sel = fs["selection"]["learned-elev_cn0"]
        hand = fs["hand_val"]["median"] + fs["hand_val"]["rms"]
        best = min(min(s) for k, s in fs["val_scores"].items() if k.startswith("elev_cn0/"))
        rows = {r["filter"]: r for r in fs["test"]}
        if candidate and not best < hand:
            assert sel["seed"] == "hand-tuned" and sel["val_score"] == pytest.approx(hand)
            assert rows["learned-elev_cn0"]["d_rms"] == 0.0 and rows["learned-elev_cn0"]["d_median"] == 0.0
        else:
            assert sel["seed"] != "hand-tuned" and sel["val_score"] == pytest.approx(best)
    again = run_evaluation(run, tmp_path / "eval")
    for fold, fs in summary["folds"].items():
        assert again["folds"][fold]["tables"]["hand-tuned"] == fs["test"]
    assert run_transfer(run, cfg, tmp_path / "transfer")["drives"] == ["Cut"]


def test_the_fallback_row_is_the_hand_tuned_filter_and_rebuilds(tmp_path, monkeypatch) -> None:
    """Forced fallback (the hand-tuned validation score made unbeatable): the learned rows are the
    hand-tuned filter, the report says so, and re-evaluation rebuilds it from ``selected.pt``."""
    drives = tmp_path / "drives"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    cfg = _v2_config(drives)
    real = report.validation_score
    monkeypatch.setattr(report, "validation_score", lambda f, s: (-1.0, real(f, s)[1]))
    run = tmp_path / "run"
    summary = run_protocol(cfg, run, workers=1)
    for fs in summary["folds"].values():
        assert fs["selection"]["learned-elev_cn0"]["seed"] == "hand-tuned"
        row = next(r for r in fs["test"] if r["filter"] == "learned-elev_cn0")
        assert row["d_median"] == 0.0 and row["d_rms"] == 0.0 and row["rms"] == fs["test"][0]["rms"]
    assert "no learned model validates better" in (run / "results.md").read_text()
    assert torch.load(run / "selected.pt", weights_only=False)["A/elev_cn0"]["hand_tuned"] is True
    again = run_evaluation(run, tmp_path / "eval")
    for fold, fs in summary["folds"].items():
        assert again["folds"][fold]["tables"]["hand-tuned"] == fs["test"]
    moved = {r["filter"]: r for r in run_transfer(run, cfg, tmp_path / "transfer")["test"]}  # the transfer command rebuilds it too
    assert moved["learned-elev_cn0 (fold A)"]["d_rms"] == 0.0 and moved["learned-elev_cn0 (fold B)"]["d_median"] == 0.0


def test_evaluation_compares_two_runs_paired(tmp_path) -> None:
    """``compare_with``: the other run's selected rows join and serve as references; a run compared
    with itself differs by exactly zero; a run on other folds is refused."""
    drives = tmp_path / "drives"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    cfg = _v2_config(drives)
    run_protocol(cfg, tmp_path / "run", workers=1)
    out = run_evaluation(tmp_path / "run", tmp_path / "eval", compare_with=tmp_path / "run")
    for fs in out["folds"].values():
        rows = {r["filter"]: r for r in fs["tables"]["run/learned-elev_cn0"]}
        assert rows["learned-elev_cn0"]["d_rms"] == 0.0 and rows["learned-elev_cn0"]["d_median"] == 0.0
        assert rows["hand-tuned"]["rms"] == fs["tables"]["hand-tuned"][0]["rms"]
        val = {r["filter"]: r for r in fs["validation_paired"]}
        assert val["hand-tuned"]["rms"] == pytest.approx(fs["validation"]["hand-tuned"]["rms"], rel=1e-12)
        assert val["learned-elev_cn0"]["d_rms_lo"] <= val["learned-elev_cn0"]["d_rms"] <= val["learned-elev_cn0"]["d_rms_hi"]
    cfg["folds"] = {"A": cfg["folds"]["A"]}
    run_protocol(cfg, tmp_path / "one_fold", workers=1)
    with pytest.raises(ValueError, match="compare_with"):
        run_evaluation(tmp_path / "run", tmp_path / "eval2", compare_with=tmp_path / "one_fold")


def _v3_config(folder: Path) -> dict:
    cfg = _v2_config(folder)
    v3 = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "realdata" / "smartloc_v3.yaml"), resolve=True)
    cfg.update({k: v for k, v in v3.items() if k != "defaults"})
    return cfg


def test_the_loss_switch_gives_the_innovation_nll_or_a_huber_loss_of_the_horizontal_error() -> None:
    """``loss: nll`` is the learner's innovation NLL; ``loss: position`` the per-trajectory mean over
    epochs of Huber(||(E, N) error||) (checked against a numpy Huber written here; the vertical
    component does not count); anything else is refused."""
    import types

    import numpy as np

    assert protocol.training_loss({}) == "nll" and protocol.training_loss({"loss": "nll"}) == "nll"
    loss = protocol.training_loss({"loss": "position", "position_loss": {"huber_delta": 3.0}})
    gen = torch.Generator().manual_seed(0)
    mean = torch.randn(2, 7, 9, generator=gen, dtype=torch.float64) * 4.0
    truth = torch.randn(2, 7, 3, generator=gen, dtype=torch.float64) * 4.0
    got = loss(types.SimpleNamespace(mean=mean), {"truth": truth})
    n = np.linalg.norm(mean[..., :2].numpy() - truth[..., :2].numpy(), axis=-1)
    rho = np.where(n <= 3.0, 0.5 * n**2, 3.0 * (n - 1.5))
    np.testing.assert_allclose(got.numpy(), rho.mean(-1), rtol=1e-12)
    truth2 = truth.clone()
    truth2[..., 2] += 100.0
    assert torch.equal(loss(types.SimpleNamespace(mean=mean), {"truth": truth2}), got)
    with pytest.raises(ValueError, match="loss must be"):
        protocol.training_loss({"loss": "mse"})


def test_a_learned_model_is_chosen_only_below_every_non_learned_candidate() -> None:
    """``select_with_fallbacks``: strictly below the hand-tuned filter AND the untrained start, else the
    better of the two (the hand-tuned filter on a tie with the start; a tie with a learned model
    keeps the non-learned one)."""
    learned = [[10.0, 9.0, 8.5], [9.5, 8.0, 8.7]]
    assert protocol.select_with_fallbacks(learned, start=9.0, hand=8.5) == ("learned", 1, 1)
    assert protocol.select_with_fallbacks(learned, start=8.0, hand=9.0) == ("start", 0, 0)
    assert protocol.select_with_fallbacks(learned, start=9.0, hand=8.0) == ("hand-tuned", 0, 0)
    assert protocol.select_with_fallbacks(learned, start=7.0, hand=7.0) == ("hand-tuned", 0, 0)
    assert protocol.select_with_fallbacks(learned, start=7.5, hand=None) == ("start", 0, 0)
    assert protocol.select_with_fallbacks(learned, start=None, hand=None) == ("learned", 1, 1)
    assert protocol.select_with_fallbacks(learned, start=9.0, hand=8.5, horizon=0) == ("hand-tuned", 0, 0)


@pytest.mark.slow
def test_v3_trains_on_position_and_never_selects_a_model_that_validates_worse_than_its_start(tmp_path) -> None:
    """v3 end to end on a cut drive: the selected row of each variant validates no worse than the
    hand-tuned filter and the untrained start, and it is a learned model only when strictly better
    than both."""
    drives = tmp_path / "drives"
    write_drive(drives, "Cut", start=100.0, stop=140.0)
    cfg = _v3_config(drives)
    assert cfg["loss"] == "position" and cfg["selection"] == {"hand_tuned_candidate": True, "start_candidate": True}
    cfg["epochs"] = 2
    summary = run_protocol(cfg, tmp_path / "run", workers=1)
    for fs in summary["folds"].values():
        sel = fs["selection"]["learned-elev_cn0"]
        hand = fs["hand_val"]["median"] + fs["hand_val"]["rms"]
        start = fs["val_scores"]["elev_cn0/seedstart"][0]
        learned = min(min(s) for k, s in fs["val_scores"].items() if k.startswith("elev_cn0/seed") and k != "elev_cn0/seedstart")
        assert sel["val_score"] <= min(hand, start) + 1e-12
        assert sel["best_learned"]["val_score"] == pytest.approx(learned)
        if learned < min(hand, start):
            assert sel["seed"] not in ("hand-tuned", "start")
        else:
            assert sel["seed"] == ("start" if start < hand else "hand-tuned")
    from experiments.realdata_tables import tables

    md = tables(tmp_path / "run")  # the run's own numbers as markdown (learned vs hand-tuned and vs the untrained gate)
    rows = {r["filter"]: r for r in summary["folds"]["A"]["test"]}
    assert f"| A | learned-elev_cn0 | {rows['learned-elev_cn0']['median']:.2f} | {rows['learned-elev_cn0']['rms']:.2f} |" in md
    assert "| B | untrained-gate |" in md and "| A | learned-elev_cn0 | " in md.split("best learned")[1]
