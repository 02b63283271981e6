"""What one `experiments/train.py debug=smoke` run leaves behind, read back as its users would:
a clean console, TensorBoard events (hyperparameters with the final test metrics, the results
table, scalars, figures), a checkpoint that `experiments/eval.py` evaluates to the same table
and that `FilterLearner.load_from_checkpoint` loads without arguments."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
from tensorboard.plugins.hparams import plugin_data_pb2

from difffilter.learn import FilterLearner
from difffilter.learn.checkpoints import read_checkpoint, run_config
from difffilter.learn.learner import load_filter
from experiments.runner.experiment import build_filter, run_experiment
from tests.smoke_helpers import ROOT, TIMING_COLUMNS, read_rows

ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
#: Warnings printed by third-party code that no change here can avoid: Lightning 2.6 builds a
#: torch pytree spec that torch 2.13 deprecates (any Lightning run prints it once).
THIRD_PARTY = [re.compile(r"pytorch_lightning/utilities/_pytree\.py:\d+: .*LeafSpec")]
# "file.py:12: Category: message", or "file.py:12: message" (Lightning's format for warnings raised in
# its own files, e.g. the advice its checks give about a user's data loader or logging calls)
WARNING_LINE = re.compile(r"^(?P<file>\S+\.py):(?P<line>\d+): ", re.M)


def _table(run_dir: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in read_rows(run_dir / "results.csv")]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    root = tmp_path_factory.mktemp("smoke")
    run_dir = root / "run"
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), "debug=smoke", f"paths.root_dir={root}", f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, cwd=root, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir, proc


def _best(run_dir: Path) -> Path:
    best = [p for p in (run_dir / "checkpoints").glob("epoch_*.ckpt")]
    assert len(best) == 1, best
    return best[0]


def test_cli_smoke_run(smoke_run):
    run_dir, proc = smoke_run
    assert (run_dir / "results.csv").exists() and (run_dir / "results.md").exists()
    assert "| learned |" in proc.stdout
    assert list((run_dir / "tensorboard").rglob("events.out.tfevents.*"))
    # progress: Lightning's bar, and one line per epoch in the console and in the log file
    assert re.search(r"Epoch 1: 100%.*train/loss_epoch", proc.stdout)
    log = (run_dir / "train.log").read_text()
    assert re.search(r"epoch 1/2: train/loss [\d.]+, val/loss [\d.]+", log) and re.search(r"epoch 2/2: ", log)
    assert "evaluating learned (2/3)" in log and "Restoring states from the checkpoint" in log  # Lightning's lines too
    assert (run_dir / "checkpoints" / "last.ckpt").is_file()
    assert '"status": "completed"' in (run_dir / "status.json").read_text()


def test_console_has_no_warning_and_no_tip(smoke_run):
    _, proc = smoke_run
    warnings = [m.group(0) for m in WARNING_LINE.finditer(proc.stderr)]
    lines = [line for line in proc.stderr.splitlines() if WARNING_LINE.match(line)]
    unexpected = [line for line in lines if not any(p.search(line) for p in THIRD_PARTY)]
    assert not unexpected, unexpected
    assert not [w for w in warnings if str(ROOT) in w or w.startswith(("difffilter", "experiments"))]
    assert "Tip:" not in proc.stdout + proc.stderr


def _plugin_values(directory: Path, plugin: str) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {}
    for path in sorted(directory.rglob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            for value in event.summary.value:
                if value.metadata.plugin_data.plugin_name == plugin:
                    out.setdefault(value.tag, []).append(value.metadata.plugin_data.content or value.tensor.SerializeToString())
    return out


def test_tensorboard_holds_hparams_with_test_metrics_results_text_scalars_and_images(smoke_run):
    run_dir, _ = smoke_run
    tb = run_dir / "tensorboard"
    hparams = _plugin_values(tb, "hparams")
    experiment = plugin_data_pb2.HParamsPluginData.FromString(hparams["_hparams_/experiment"][-1]).experiment
    metrics = {m.name.tag for m in experiment.metric_infos}
    assert {f"results/{f}/{m}" for f in ("hand-tuned", "learned", "oracle") for m in ("rmse_pos", "anees", "nis", "nll")} <= metrics
    start = plugin_data_pb2.HParamsPluginData.FromString(hparams["_hparams_/session_start_info"][-1]).session_start_info
    # the whole resolved config: model, filter, data, optimizer, trainer...
    assert start.hparams["optimizer/lr"].number_value > 0
    assert start.hparams["filter/_target_"].string_value == "difffilter.filters.KalmanFilter"
    assert start.hparams["data/train_size"].number_value == 8
    assert start.hparams["experiment/name"].string_value == "singer2d"
    # the hparams metrics are scalars with the results' values
    acc = EventAccumulator(str(tb), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    acc.Reload()
    rows = {r["filter"]: r for r in read_rows(run_dir / "results.csv")}
    assert acc.Scalars("results/learned/rmse_pos")[-1].value == pytest.approx(float(rows["learned"]["rmse_pos"]), rel=1e-6)
    scalars = {"train/loss_epoch", "val/loss", "val/rmse_pos", "test/rmse_pos", "params/model.measurement.R[0,0]"}
    assert scalars <= set(acc.Tags()["scalars"])
    assert {"val/trajectory", "val/error", "test/trajectory", "test/error"} <= set(acc.Tags()["images"])
    assert "results/text_summary" in acc.Tags()["tensors"]
    text = acc.Tensors("results/text_summary")[-1].tensor_proto.string_val[0].decode()
    assert "| learned |" in text and "| oracle |" in text


def test_eval_entry_point_reproduces_the_test_table(smoke_run, tmp_path):
    run_dir, _ = smoke_run
    out = tmp_path / "eval"
    cmd = [sys.executable, str(ROOT / "experiments" / "eval.py"), f"ckpt_path={_best(run_dir)}", f"hydra.run.dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert _table(out) == _table(run_dir)
    assert (out / "per_run.csv").read_text() == (run_dir / "per_run.csv").read_text()
    assert "| learned |" in proc.stdout and (out / "eval.log").is_file()


def test_train_false_evaluates_with_the_composed_config(smoke_run, tmp_path):
    # train.py train=false with the training run's overrides (no stored config used) gives the same table
    run_dir, _ = smoke_run
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                "debug=smoke",
                "train=false",
                f"ckpt_path={_best(run_dir)}",
                "config_from_checkpoint=false",
                f"paths.output_dir={tmp_path}",
                "logger=none",
            ],
        )
    run_experiment(cfg)
    assert _table(tmp_path) == _table(run_dir)


def test_load_from_checkpoint_round_trips_the_learned_filter(smoke_run):
    run_dir, _ = smoke_run
    ckpt = _best(run_dir)
    learner = FilterLearner.load_from_checkpoint(str(ckpt))
    stored = read_checkpoint(ckpt)
    state = learner.state_dict()
    assert set(state) == set(stored["state_dict"])
    for key, value in stored["state_dict"].items():
        assert torch.equal(state[key], value), key
    # the learned values differ from the config's: they came from the file
    cfg = run_config(stored)
    fresh = build_filter(cfg["filter"], dtype=torch.float64, params=cfg["experiment"]["hand_tuned"])
    assert not torch.equal(fresh.model.R, learner.filter.model.R)
    filt = load_filter(str(ckpt))
    assert not filt.training and torch.equal(filt.model.R, learner.filter.model.R)
    learned = next(r for r in read_rows(run_dir / "results.csv") if r["filter"] == "learned")
    r_diag = [float(x) for x in re.search(r"R=\[\[([^\]]+)\]", learned["parameter_values"]).group(1).split(",")]
    assert filt.model.R[0, 0].item() == pytest.approx(r_diag[0], rel=1e-5)
    assert type(learner.loss_fn).__name__ == "NLLLoss"  # the loss config came back too


@pytest.mark.slow
def test_paired_comparison_app_loads_the_best_checkpoint(tmp_path):
    # experiments/p004_paired.py (a Hydra app) on a p004_blend smoke run: the learned filter comes
    # from the best validation checkpoint through load_filter, not from last.ckpt
    run_dir = tmp_path / "run"
    train = [sys.executable, str(ROOT / "experiments" / "train.py"), "experiment=p004_blend", "debug=smoke", "logger=none"]
    proc = subprocess.run([*train, f"hydra.run.dir={run_dir}"], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    paired = [sys.executable, str(ROOT / "experiments" / "p004_paired.py"), f"run_dir={run_dir}", "runs=2"]
    proc = subprocess.run(paired, capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"checkpoint {_best(run_dir).name}" in proc.stdout and "paired: learned - hand-tuned RMSE" in proc.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # the tool leaves no output directory
