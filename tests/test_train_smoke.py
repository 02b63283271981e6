"""End-to-end: `experiments/train.py debug=smoke` writes results.md / results.csv and TensorBoard
events holding the promised scalars and figures (read back with EventAccumulator)."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import pytest
import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from difffilter.evaluate.evaluation import EXTRA_TESTS_DIR, PER_RUN_FILE, read_per_run
from difffilter.filters import KalmanFilter
from difffilter.learn import DiagnosticFigures, FilterLearner, LearnerOptions, TrajectoryDataModule
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.sim import ModelSimulator
from experiments.runner.experiment import _oracle, build_filter, run_experiment
from tests.smoke_helpers import read_rows

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64


def _events(directory: Path) -> EventAccumulator:
    files = list(directory.rglob("events.out.tfevents.*"))
    assert files, f"no TensorBoard event file under {directory}"
    acc = EventAccumulator(str(files[0].parent), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    return acc


def test_smoke_run_writes_results_and_tensorboard(tmp_path):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["debug=smoke", f"paths.output_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"])
    out = run_experiment(cfg)
    rows = read_rows(tmp_path / "results.csv")
    assert [r["filter"] for r in rows] == ["hand-tuned", "learned", "oracle"]
    for col in ("rmse_pos", "anees", "nis", "nll", "time_per_step_ms"):
        assert all(float(r[col]) > 0 for r in rows), col
    assert out["metric"] == pytest.approx(float(rows[1]["rmse_pos"]))
    # the oracle knows the truth: best likelihood and a consistent covariance
    nll = {r["filter"]: float(r["nll"]) for r in rows}
    assert nll["oracle"] < nll["hand-tuned"]
    md = (tmp_path / "results.md").read_text()
    assert "| hand-tuned |" in md and "| oracle |" in md
    acc = _events(tmp_path / "tensorboard")
    scalars = set(acc.Tags()["scalars"])
    expected = {
        "train/loss_step",
        "train/loss_epoch",
        "val/loss",
        "val/rmse_pos",
        "val/anees",
        "val/nis",
        "val/nll",
        "test/rmse_pos",
        "stability/skipped_steps",
        "stability/nonfinite_trajectories",
        "params/model.dynamics.inner.tau[0]",
        "params/model.dynamics.inner.tau[1]",
        "params/model.dynamics.inner.sigma_a[0]",
        "params/model.measurement.R[0,0]",
        "params/model.measurement.R[1,1]",
    }
    assert expected <= scalars, expected - scalars
    assert len(acc.Scalars("params/model.dynamics.inner.tau[0]")) == cfg.trainer.max_epochs  # once per epoch
    images = set(acc.Tags()["images"])
    assert {"val/trajectory", "val/error", "test/trajectory", "test/error"} <= images, images


class _ModeRecordingKF(KalmanFilter):
    """A Kalman filter that also records fake two-mode probabilities (IMM-like result)."""

    record_keys = ("mode_probs",)

    def finalize_belief(self, belief):
        p = torch.sigmoid(belief["mean"][:, :1] / 50.0)
        return {**belief, "mode_probs": torch.cat([p, 1 - p], -1)}


def test_mode_probability_figure_is_logged(tmp_path):
    model = tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=0.5, dtype=f64), R=[25.0, 25.0])
    sim = ModelSimulator(model=model, num_steps=20, initial_mean=[0.0, 10.0, 0.0, 5.0], initial_cov=[100.0, 4.0, 100.0, 4.0])
    dm = TrajectoryDataModule(sim, train_size=4, val_size=2, test_size=2, batch_size=4, window=10)
    learner = FilterLearner(
        _ModeRecordingKF(model),
        "nll",
        learn=["R"],
        optimizer=functools.partial(torch.optim.Adam, lr=0.01),
        options=LearnerOptions(position_index=[0, 2]),
    )
    logger = pl.loggers.TensorBoardLogger(str(tmp_path), name="", version="")
    trainer = pl.Trainer(
        max_epochs=1,
        logger=logger,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        callbacks=[DiagnosticFigures(every_n_epochs=1)],
    )
    trainer.fit(learner, dm)
    images = set(_events(tmp_path).Tags()["images"])
    assert {"val/mode_probs", "val/trajectory", "val/error"} <= images


@pytest.mark.slow
def test_cli_ddp_sim_two_processes(tmp_path):
    # trainer=ddp_sim: 2 CPU processes with gloo; each takes half of the training trajectories.
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run_dir = tmp_path / "run"
    cmd = [
        sys.executable,
        str(ROOT / "experiments" / "train.py"),
        "trainer=ddp_sim",
        "debug=smoke",
        f"paths.root_dir={tmp_path}",
        f"hydra.run.dir={run_dir}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "MEMBER: 2/2" in proc.stderr + proc.stdout or (run_dir / "train_ddp_process_1.log").exists()
    rows = read_rows(run_dir / "results.csv")
    assert [r["filter"] for r in rows] == ["hand-tuned", "learned", "oracle"]
    # values logged per epoch are synchronised (no "use sync_dist=True" advice), no project warning
    assert "sync_dist" not in proc.stderr and "Warning" not in proc.stderr.replace("FutureWarning", ""), proc.stderr[-3000:]
    assert '"status": "completed"' in (run_dir / "status.json").read_text()


def test_oracle_specifications():
    # experiment.oracle: from the simulator's true parameters, from its make_model(), or explicit.
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=cv2d", "paths.output_dir=/unused"])
    dm = TrajectoryDataModule(instantiate(cfg.scenario, _convert_="all"), train_size=1, val_size=1, test_size=2, batch_size=1, max_steps=3)
    test = dm.dataset("test")
    hand = build_filter(cfg.filter, dtype=f64, params=cfg.experiment.hand_tuned)
    oracle = _oracle(cfg, hand, test, f64)
    torch.testing.assert_close(oracle.model.R, test.source.true_params["measurement.R"])
    torch.testing.assert_close(oracle.model.dynamics.inner.q, test.source.true_params["dynamics.inner.q"])
    assert float(hand.model.dynamics.inner.q[0]) == 5.0  # the hand-tuned filter is untouched
    cfg.experiment.oracle = OmegaConf.create({"make_model": True, "params": {"R": [1.0, 2.0]}})
    oracle = _oracle(cfg, hand, test, f64)
    torch.testing.assert_close(oracle.model.dynamics.inner.q, test.source.true_params["dynamics.inner.q"])
    torch.testing.assert_close(oracle.model.R.diagonal(), torch.tensor([1.0, 2.0], dtype=f64))
    cfg.experiment.oracle = None
    assert _oracle(cfg, hand, test, f64) is None


def test_extra_test_sets_get_their_own_results(tmp_path):
    # experiment.extra_tests: every filter is evaluated again on each extra set (test size and seed);
    # the same simulator gives the same per-run numbers as the main test set, another one others.
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=["debug=smoke", f"paths.output_dir={tmp_path}", f"paths.log_dir={tmp_path}/logs", "logger=csv"])
    with open_dict(cfg):
        cfg.experiment.extra_tests = {"same": OmegaConf.to_container(cfg.scenario), "masked": {**OmegaConf.to_container(cfg.scenario)}}
        cfg.experiment.extra_tests.masked.missing_prob = 0.3
        cfg.experiment.extra_tests.dropped = None  # an overlay dropping a test set of its base: skipped
    run_experiment(cfg)
    main_runs = read_per_run(tmp_path / "per_run.csv")
    same = read_per_run(tmp_path / EXTRA_TESTS_DIR / "same" / PER_RUN_FILE)
    other = read_per_run(tmp_path / EXTRA_TESTS_DIR / "masked" / PER_RUN_FILE)
    assert set(same) == set(main_runs) == {"hand-tuned", "learned", "oracle"}
    for name in main_runs:
        torch.testing.assert_close(same[name]["rmse_pos"], main_runs[name]["rmse_pos"], rtol=0, atol=0)
    assert not torch.equal(other["hand-tuned"]["nll"], main_runs["hand-tuned"]["nll"])
    assert "test set `masked`" in (tmp_path / EXTRA_TESTS_DIR / "masked" / "results.md").read_text()
    assert not (tmp_path / EXTRA_TESTS_DIR / "dropped").exists()
