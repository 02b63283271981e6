"""Tuned baselines of an experiment (experiments/runner/baselines.py): EM on the training
trajectories and a validation search, each equal to calling the library directly on the same
data, their rows and tuning cost in results.csv, and config errors that name the key."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from difffilter.filters import KalmanFilter
from difffilter.learn.data import TrajectorySet
from difffilter.learn.em import fit_em
from difffilter.learn.search import validation_loss
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.sim import ModelSimulator
from experiments.runner.baselines import tune_baseline
from experiments.runner.experiment import run_experiment
from tests.smoke_helpers import read_rows

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64


def _filter(r: float) -> KalmanFilter:
    return KalmanFilter(tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=0.5, dtype=f64), R=[r, r]))


def _data(seed: int, n: int = 6, steps: int = 60) -> TrajectorySet:
    truth_model = _filter(9.0).model
    sim = ModelSimulator(model=truth_model, initial_mean=[0.0, 1.0, 0.0, 1.0], initial_cov=[1.0, 0.1, 1.0, 0.1], num_steps=steps)
    return TrajectorySet.from_simulation(sim(batch_size=n, seed=seed), dtype=f64)


def _belief() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=f64), torch.diag(torch.tensor([1.0, 0.1, 1.0, 0.1], dtype=f64))


def test_em_baseline_equals_fit_em_on_the_first_training_trajectories():
    train, val = _data(0), _data(1)
    mean, cov = _belief()
    tuned = _filter(1.0)
    info = tune_baseline(
        tuned,
        {"method": "em", "learn": ["model.measurement.R"], "num_iters": 5, "trajectories": 4},
        name="em",
        train=train,
        val=val,
        initial_mean=mean,
        initial_cov=cov,
    )
    direct = _filter(1.0)
    batch = train.batch(torch.arange(4))
    fit_em(direct, batch["measurements"], mean, cov, batch["mask"], batch["controls"], num_iters=5, learn=["model.measurement.R"])
    torch.testing.assert_close(tuned.model.measurement.R, direct.model.measurement.R, rtol=0, atol=0)
    assert info["tuning_cpu_s"] > 0 and "4 train traj" in info["tuning"]
    # EM moved R from the hand-tuned 1 towards the truth 9
    assert float(tuned.model.measurement.R[0, 0].detach()) > 3.0


def test_grid_baseline_picks_the_best_validation_candidate():
    train, val = _data(0), _data(1)
    mean, cov = _belief()
    grid = [1.0, 9.0, 81.0]
    tuned = _filter(2.0)
    info = tune_baseline(
        tuned,
        {"method": "grid", "grid": {"model.measurement.R": grid}, "score": "rmse"},
        name="grid",
        train=train,
        val=val,
        initial_mean=mean,
        initial_cov=cov,
        position_index=[0, 2],
    )
    # brute force on the same validation set, independently of the search helper's loop
    score = validation_loss(val.measurements, mean, cov, truth=val.truth, kind="rmse", index=[0, 2], truth_index=[0, 2])
    scores = {r: score(_filter(r)) for r in grid}
    best = min(scores, key=scores.get)
    assert float(tuned.model.measurement.R[0, 0].detach()) == pytest.approx(best)
    assert "3 candidates" in info["tuning"] and info["tuning_cpu_s"] > 0


@pytest.mark.parametrize(
    ("tune", "match"),
    [
        ({"method": "bayes"}, r"experiment\.baselines\.x\.tune\.method must be one of"),
        ({"method": "em", "iters": 3}, r"experiment\.baselines\.x\.tune has unknown keys \['iters'\]"),
        ({"method": "em", "num_iters": 0}, r"experiment\.baselines\.x\.tune\.num_iters must be a positive integer"),
        ({"method": "em", "trajectories": 99}, r"experiment\.baselines\.x\.tune\.trajectories = 99 but the data have only 6"),
        ({"method": "grid", "grid": {}}, r"experiment\.baselines\.x\.tune\.grid must map one to three"),
        ({"method": "grid", "grid": {"R": {"low": 2, "high": 1, "num": 3}}}, r"tune\.grid\.R must have 0 < low < high"),
        ({"method": "random", "bounds": {"R": [3, 1]}}, r"tune\.bounds\.R must be \[low, high\]"),
    ],
)
def test_bad_tune_configs_name_the_key(tune, match):
    mean, cov = _belief()
    with pytest.raises(ValueError, match=match):
        tune_baseline(_filter(1.0), tune, name="x", train=_data(0), val=_data(1), initial_mean=mean, initial_cov=cov)


def test_experiment_rows_for_tuned_baselines(tmp_path):
    overrides = [
        "debug=smoke",
        f"paths.output_dir={tmp_path}",
        f"paths.log_dir={tmp_path}/logs",
        "logger=none",
        "+experiment.baselines.em.tune={method: em, learn: [model.measurement.R], num_iters: 3}",
        "+experiment.baselines.grid-search.tune={method: grid, relative: true, grid: {model.measurement.R: [0.5, 1.0, 2.0]}}",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    hand_r = copy.deepcopy(cfg.experiment.hand_tuned)
    run_experiment(cfg)
    rows = {r["filter"]: r for r in read_rows(tmp_path / "results.csv")}
    assert {"hand-tuned", "learned", "em", "grid-search"} <= set(rows)
    for name in ("learned", "em", "grid-search"):
        assert float(rows[name]["tuning_cpu_s"]) > 0, name
    assert rows["em"]["tuning"].startswith("EM 3 it on") and "grid search over 3 candidates" in rows["grid-search"]["tuning"]
    assert cfg.experiment.hand_tuned == hand_r  # tuning leaves the hand-tuned settings alone
