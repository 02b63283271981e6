"""The 2-D ranging protocol (experiments.ranging.protocol / .report) on the excerpts
shipped with the tests: folds by blocks and by data set, selection never worse than the untrained
start or hand-tuned on validation, results.csv per fold with the expected rows and columns, the
extras figure and TensorBoard events; and ``experiments/realdata.py folder=<ranging folder>``."""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from difffilter.datasets import find_recordings, load_ranging
from difffilter.models.navigation.ranging2d import multilateration
from experiments.ranging.pieces import _heading
from experiments.ranging.protocol import (
    EXTRA_BASELINES,
    Piece,
    _errors,
    _filters,
    eval_tensors,
    fold_pieces,
    lead_in_start,
    piece_tensors,
    run_fold,
    select_candidate,
    start_position_variance,
)
from experiments.ranging.report import extras, fold_specs, run_ranging, write_csv

ASSETS = Path(__file__).parent / "assets" / "librsf"
ROOT = Path(__file__).resolve().parents[1]
CFG = {
    "folds": {"A": {"train": [0.0, 0.6], "val": [0.6, 0.8], "test": [0.8, 1.0]}},
    "by_dataset": True,
    "val_fraction": 0.3,
    "windows": {"length": 12, "stride": 12},
    "bias": "anchor",
    "noise": "anchor",
    "gate": {"threshold": 3.0, "floor": 3.0, "softness": 0.5},
    "seeds": 2,
    "epochs": 2,
    "lr": 0.05,
    "batches": 1,
    "burn_in": 2,
    "eval_burn_in": 2,
    "init_perturbation": 0.1,
    "bootstrap": {"block": 5, "draws": 200, "seed": 0},
}


def _recordings():  # type: ignore[no-untyped-def]
    return [load_ranging(i, g) for _n, i, g in find_recordings(ASSETS)]


def test_folds_by_blocks_and_by_data_set() -> None:
    recs = _recordings()
    specs = fold_specs(recs, CFG)
    assert list(specs) == ["W3500x_heavy-tailed/A", "W3500x_skewed/A", "leave_out_W3500x_heavy-tailed", "leave_out_W3500x_skewed"]
    pieces = fold_pieces(*specs["leave_out_W3500x_skewed"])
    assert [(p.recording.name, p.first, p.stop) for p in pieces["train"]] == [("W3500x_heavy-tailed", 0, 43)]
    assert [(p.recording.name, p.first, p.stop) for p in pieces["val"]] == [("W3500x_heavy-tailed", 43, 61)]
    assert [(p.recording.name, p.first, p.stop) for p in pieces["test"]] == [("W3500x_skewed", 0, 61)]
    blocks = fold_pieces(*specs["W3500x_skewed/A"])
    assert [(p.first, p.stop) for role in ("train", "val", "test") for p in blocks[role]] == [(0, 37), (37, 49), (49, 61)]


def test_selection_is_never_worse_than_its_start_or_hand_tuned_on_validation(monkeypatch, tmp_path) -> None:
    recs = _recordings()
    seen = []
    monkeypatch.setitem(
        EXTRA_BASELINES,
        "extra-hook",
        lambda rec: seen.append(rec.name) or run_fold.__globals__["_filters"](rec.num_anchors, CFG)["hand-tuned"],
    )
    res = run_fold(fold_pieces([recs[1]], CFG["folds"]["A"]), CFG)
    s = res.selected
    assert s["val_score"] <= s["val_untrained"] and s["val_score"] <= s["val_hand_tuned"]
    assert [r["filter"] for r in res.rows] == [
        "hand-tuned",
        "learned",
        "untrained-gate",
        "hand-tuned-hard-gate",
        "sage-husa",
        "vb-adaptive-r",
        "extra-hook",
        "snapshot-lsq",
    ]
    assert seen == ["W3500x_skewed"]
    hook = next(r for r in res.rows if r["filter"] == "extra-hook")
    assert hook["d_median"] == 0.0 and hook["d_rms"] == 0.0  # the hook returned the hand-tuned filter: identical errors
    adaptive = next(r for r in res.rows if r["filter"] == "sage-husa")
    assert adaptive["d_rms"] != 0.0 and all(math.isfinite(adaptive[k]) for k in ("pos_err_p50", "rmse_pos", "pos_err_p95"))
    assert len(res.history) == 2 and all(len(h["scores"]) == 3 for h in res.history)
    best = min(min(h["scores"]) for h in res.history)
    assert s["val_score"] == pytest.approx(min(best, s["val_untrained"], s["val_hand_tuned"]))
    ex = extras(res.start)
    assert ex["range_bias"] == [0.0] * 8 and ex["noise_scale"] == pytest.approx([1.0] * 8) and ex["gate_floor"] == pytest.approx([3.0])
    write_csv(tmp_path / "f" / "results.csv", res.rows)
    with open(tmp_path / "f" / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["filter"] for r in rows] == [r["filter"] for r in res.rows] and rows[0]["d_median"] == ""
    assert float(rows[1]["rmse_pos"]) == pytest.approx(float(res.errors["learned"].pow(2).mean().sqrt()), rel=1e-5)


@pytest.mark.slow
def test_run_ranging_writes_csv_per_fold_figure_and_tensorboard(tmp_path) -> None:
    cfg = {**CFG, "seeds": 1, "epochs": 1}
    results = run_ranging(ASSETS, cfg, tmp_path, only=["W3500x_skewed"])
    assert list(results) == ["W3500x_skewed/A"]
    with open(tmp_path / "W3500x_skewed" / "A" / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {"filter", "pos_err_p50", "rmse_pos", "pos_err_p95", "d_median_lo", "d_rms_hi"} <= set(rows[0])
    assert [r["filter"] for r in rows][:2] == ["hand-tuned", "learned"] and "snapshot-lsq" in [r["filter"] for r in rows]
    e = results["W3500x_skewed/A"].errors["hand-tuned"]
    assert float(rows[0]["pos_err_p50"]) == pytest.approx(float(e.median()), rel=1e-5)
    assert float(rows[0]["rmse_pos"]) == pytest.approx(float(e.pow(2).mean().sqrt()), rel=1e-5)
    assert (tmp_path / "learned_extras.png").stat().st_size > 10_000 and any((tmp_path / "tb").iterdir())
    summary = json.loads((tmp_path / "summary.json").read_text())
    fold = summary["folds"]["W3500x_skewed/A"]
    gated = fold["selected"]["candidate"] != "hand-tuned"  # hand-tuned may win validation: it has no gate
    assert ({"gate_threshold", "gate_floor", "gate_softness", "range_bias", "noise_scale"} <= set(fold["extras"])) == gated
    assert "| W3500x_skewed/A | learned |" in (tmp_path / "results.md").read_text()


@pytest.mark.slow
def test_the_command_runs_on_a_ranging_folder(tmp_path) -> None:
    """``python experiments/realdata.py folder=<dir>`` with only a folder given (tiny settings)."""
    over = [
        f"realdata_ranging.{k}={v}"
        for k, v in {
            "seeds": 1,
            "epochs": 1,
            "windows.length": 12,
            "windows.stride": 12,
            "bootstrap.draws": 100,
            "bootstrap.block": 5,
            "burn_in": 2,
            "eval_burn_in": 2,
        }.items()
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "experiments" / "realdata.py"),
            f"folder={ASSETS}",
            f"hydra.run.dir={tmp_path}",
            "realdata_ranging.by_dataset=false",
            *over,
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    for name in ("W3500x_heavy-tailed", "W3500x_skewed"):
        assert (tmp_path / name / "A" / "results.csv").is_file()
    assert "| W3500x_skewed/A | learned |" in out.stdout
    assert torch.isfinite(torch.tensor(json.loads((tmp_path / "summary.json").read_text())["seconds"]))


def test_select_candidate_keeps_the_start_unless_a_trained_one_is_strictly_better() -> None:
    assert select_candidate([2.0, 3.0, 2.5, 2.0]) == 0  # ties keep the start (listed first)
    assert select_candidate([2.0, 1.0, 1.5]) == 1
    assert select_candidate([2.0, math.nan, math.inf, 1.9]) == 3  # non-finite never wins
    assert select_candidate([math.nan, math.inf]) == 0
    with pytest.raises(ValueError, match="at least one candidate"):
        select_candidate([])


def test_run_fold_keeps_the_untrained_start_when_training_only_makes_it_worse(monkeypatch) -> None:
    import experiments.ranging.protocol as protocol

    def worse(start, train, val, cfg, seed, log):  # type: ignore[no-untyped-def]
        bad = copy.deepcopy(start)
        with torch.no_grad():
            bad.model.measurement.range_bias = torch.full((8,), -6.0 - seed, dtype=torch.float64)
        s0 = protocol._score(start, val, int(cfg["eval_burn_in"]))
        return {
            "seed": seed,
            "scores": [s0, protocol._score(bad, val, int(cfg["eval_burn_in"]))],
            "snapshots": [start.state_dict(), bad.state_dict()],
        }

    monkeypatch.setattr(protocol, "_train_seed", worse)
    # heavy-tailed excerpt: there the untrained gate scores below hand-tuned on validation
    res = run_fold(fold_pieces([_recordings()[0]], CFG["folds"]["A"]), CFG)
    assert res.selected["val_untrained"] < res.selected["val_hand_tuned"]
    assert res.selected["candidate"] == "untrained-gate" and res.selected["val_score"] == res.selected["val_untrained"]
    torch.testing.assert_close(res.errors["learned"], res.errors["untrained-gate"])
    learned = next(r for r in res.rows if r["filter"] == "learned")
    assert learned["u_median"] == 0.0 and learned["u_rms"] == 0.0 and "u_median" not in res.rows[2]


def test_start_variance_and_heading_follow_their_rules() -> None:
    rec = _recordings()[1]
    piece = fold_pieces([rec], CFG["folds"]["A"])["train"][0]
    fix = multilateration(
        torch.as_tensor(rec.ranges), torch.as_tensor(rec.range_var), torch.as_tensor(rec.mask), torch.as_tensor(rec.anchors)
    ).numpy()
    err = np.linalg.norm(fix[piece.first : piece.stop] - rec.truth[piece.first : piece.stop], axis=1)
    expect = max(0.25, np.quantile(err[np.isfinite(err)], 0.95) ** 2 / 5.991464547107979)
    assert start_position_variance([piece]) == pytest.approx(expect, rel=1e-9)
    # the truth file's angle at each step; without it, motion direction minus the odometry's direction
    assert rec.heading is not None and np.isfinite(rec.heading).all()
    no_angles = dataclasses.replace(rec, heading=None, heading0=None)
    for k in (0, 7, 30):
        assert _heading(rec, k) == rec.heading[k]
        gap = (_heading(no_angles, k) - rec.heading[k] + np.pi) % (2 * np.pi) - np.pi
        assert abs(gap) < 0.2, (k, gap)


def test_lead_in_start_follows_its_rules() -> None:
    a, b = _recordings()
    p = Piece(a, 40, 55)
    assert lead_in_start(p, 0) == 40 and lead_in_start(p, 10) == 30 and lead_in_start(p, 100) == 0 and lead_in_start(p, None) == 0
    # a preceding test piece of the same recording bounds the lead-in; other recordings and later pieces do not
    assert lead_in_start(p, 30, avoid=[Piece(a, 0, 35)]) == 35
    assert lead_in_start(p, 30, avoid=[Piece(a, 0, 40)]) == 40  # test right before: a cold start
    assert lead_in_start(p, 30, avoid=[Piece(b, 0, 35), Piece(a, 55, 61)]) == 10
    with pytest.raises(ValueError, match="eval_lead_in"):
        lead_in_start(p, -1)


def test_a_warm_start_scores_the_pieces_steps_from_one_run_through_the_lead_in() -> None:
    rec = _recordings()[0]
    piece, burn = Piece(rec, 40, 61), 2
    for name, filt in _filters(rec.num_anchors, CFG).items():
        cold = _errors(filt, eval_tensors(piece, pos_var=4.0, lead_in=0), burn)
        torch.testing.assert_close(cold, _errors(filt, piece_tensors(piece, pos_var=4.0), burn))
        for lead, lo in ((15, 25), (None, 0)):
            warm = eval_tensors(piece, pos_var=4.0, lead_in=lead)
            assert warm["skip"] == 40 - lo and warm["z"].shape[1] == 61 - lo
            # reference: one run from the lead-in's first step, its errors at the piece's steps after the burn-in
            span = piece_tensors(Piece(rec, lo, 61), pos_var=4.0)
            with torch.no_grad():
                res = filt(span["z"], span["m0"], span["P0"], mask=span["mask"], controls=span["u"])
            ref = (res.mean[0, 40 - lo + burn :, :2] - torch.as_tensor(rec.truth[40 + burn : 61])).norm(dim=-1)
            got = _errors(filt, warm, burn)
            assert got.shape == cold.shape, name  # the same steps are scored, warm or cold
            torch.testing.assert_close(got, ref[torch.isfinite(ref)])
        assert not torch.equal(_errors(filt, eval_tensors(piece, pos_var=4.0, lead_in=None), burn), cold), name


def test_run_fold_warm_starts_every_row_alike() -> None:
    rec = _recordings()[0]
    pieces = fold_pieces([rec], CFG["folds"]["A"])
    cold = run_fold(pieces, {**CFG, "seeds": 1, "epochs": 1})
    warm = run_fold(pieces, {**CFG, "seeds": 1, "epochs": 1, "eval_lead_in": 10})
    test = eval_tensors(pieces["test"][0], pos_var=warm.selected["start_pos_var"], lead_in=10)
    assert test["skip"] == 10
    for row in ("hand-tuned", "untrained-gate", "hand-tuned-hard-gate"):
        torch.testing.assert_close(warm.errors[row], _errors(_filters(rec.num_anchors, CFG)[row], test, 2))
    assert {k: len(v) for k, v in warm.errors.items()} == {k: len(v) for k, v in cold.errors.items()}
    torch.testing.assert_close(warm.errors["snapshot-lsq"], cold.errors["snapshot-lsq"])  # per step: no state to warm
    assert not torch.equal(warm.errors["hand-tuned"], cold.errors["hand-tuned"])


@pytest.mark.slow
def test_several_folders_pool_their_data_sets_and_kinds_must_agree(tmp_path) -> None:
    """``folder=[a, b]``: the data sets of both folders (each a copy of one input and the shared
    truth) get block folds and leave-one-data-set-out folds; a name in two folders, and folders of
    different kinds, are errors naming them."""
    import shutil

    from experiments.realdata import data_kind, folder_list

    one, two = tmp_path / "one", tmp_path / "two"
    for folder, name in ((one, "heavy-tailed"), (two, "skewed")):
        folder.mkdir()
        shutil.copy(ASSETS / f"W3500x_{name}_Input.txt", folder)
        shutil.copy(ASSETS / "W3500x_GT.txt", folder)
    cfg = {**CFG, "seeds": 1, "epochs": 1, "folds": {}}  # data-set folds only: the block folds are tested above
    results = run_ranging([one, two], cfg, tmp_path / "run")
    assert list(results) == ["leave_out_W3500x_heavy-tailed", "leave_out_W3500x_skewed"]
    for fold in results:
        assert (tmp_path / "run" / fold / "results.csv").is_file()
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["folder"] == [str(one), str(two)]
    shutil.copy(ASSETS / "W3500x_skewed_Input.txt", one)
    with pytest.raises(ValueError, match=r"same name in several folders: {.W3500x_skewed.: \[.*one/W3500x_skewed_Input.txt"):
        run_ranging([one, two], cfg, tmp_path / "again")
    assert folder_list(None) == [] and folder_list(str(one)) == [str(one)] and folder_list([one, two]) == [str(one), str(two)]
    assert data_kind([str(one), str(two)]) == "ranging2d"
    gnss = tmp_path / "gnss"
    gnss.mkdir()
    (gnss / "D_Input.txt").write_text("pseudorange3 0 2e7 25 1 2 3 5 1 40 45\n")
    with pytest.raises(ValueError, match="different kinds"):
        data_kind([str(one), str(gnss)])


def test_a_folder_without_truth_or_inputs_is_refused_before_training(tmp_path) -> None:
    """A data set without ``point2`` truth cannot be scored, a folder without ``<name>_Input.txt``
    holds no data set: both are errors naming what is missing (nothing trains)."""
    import shutil

    shutil.copy(ASSETS / "W3500x_skewed_Input.txt", tmp_path)
    with pytest.raises(ValueError, match=r"without point2 ground truth cannot be scored: \['W3500x_skewed'\]"):
        run_ranging(tmp_path, CFG, tmp_path / "run")
    (tmp_path / "W3500x_GT.txt").write_text("angle 0 0.5\n")  # a truth file without point2 records
    with pytest.raises(ValueError, match=r"W3500x_GT.txt: no point2 records"):
        run_ranging(tmp_path, CFG, tmp_path / "run")
    empty = tmp_path / "empty"
    empty.mkdir()
    shutil.copy(ASSETS / "W3500x_GT.txt", empty)
    with pytest.raises(FileNotFoundError, match="empty: no data set found"):
        run_ranging(empty, CFG, tmp_path / "run")
