"""Smoothed-state losses and the smoother switch of FilterLearner / run_experiment."""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
from hydra import compose, initialize_config_dir
from scipy.stats import multivariate_normal

from difffilter.evaluate import evaluate_filter
from difffilter.filters import KalmanFilter
from difffilter.learn import FilterLearner, LearnerOptions, MSELoss, StateNLLLoss, TrajectoryDataModule, learnable_values
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.sim.sampling import ModelSimulator
from difffilter.smoothers import RTSSmoother, SmootherResult
from experiments.runner.experiment import run_experiment
from tests.smoke_helpers import read_rows

f64 = torch.float64
CV_PRIOR = ([0.0, 10.0, 0.0, 5.0], [100.0, 4.0, 100.0, 4.0])


def cv_model(q: float = 0.5, r: float = 25.0):
    return tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=q, dtype=f64), R=[r, r], time_invariant=True)


def _dm(n=4, steps=30, window=None, seed_model=None):
    sim = ModelSimulator(
        model=seed_model or cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1], missing_prob=0.1
    )
    dm = TrajectoryDataModule(sim, train_size=n, val_size=2, test_size=n, batch_size=n, window=window, shuffle=False)
    dm.setup("fit")
    return dm


def test_state_nll_equals_the_gaussian_log_density_of_the_truth():
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(2, 5, 4, generator=g, dtype=f64)
    a = torch.randn(2, 5, 4, 4, generator=g, dtype=f64)
    cov = a @ a.mT + 0.5 * torch.eye(4, dtype=f64)
    truth = torch.randn(2, 5, 3, generator=g, dtype=f64)
    truth[1, 2] = float("nan")  # a step without truth is left out
    result = SmootherResult(mean=mean, cov=cov, filtered=None)  # type: ignore[arg-type]
    loss = StateNLLLoss(state_index=[0, 2], truth_index=[1, 0])(result, {"truth": truth})
    for b in range(2):
        vals = [
            -multivariate_normal(mean[b, t, [0, 2]].numpy(), cov[b, t][np.ix_([0, 2], [0, 2])].numpy()).logpdf(truth[b, t, [1, 0]].numpy())
            for t in range(5)
            if torch.isfinite(truth[b, t]).all()
        ]
        assert float(loss[b]) == pytest.approx(np.mean(vals), rel=1e-12)


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_learner_smooths_each_window_from_the_carried_belief():
    dm = _dm(n=3, steps=30, window=10)
    learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), MSELoss(state_index=[0, 2]), learn=["q"], options=LearnerOptions(smoother="rts"))
    ref_filter = KalmanFilter(cv_model(q=2.0))
    ref = RTSSmoother(ref_filter)
    belief = None
    data = dm.dataset("train")
    for i, batch in enumerate(dm.train_dataloader()):
        loss = learner.training_step(batch, i)
        out = ref(batch["measurements"], data.initial_mean, data.initial_cov, mask=batch["mask"], belief=belief)
        assert isinstance(out, SmootherResult)
        expected = MSELoss(state_index=[0, 2])(out, batch).mean()
        assert loss.item() == pytest.approx(expected.item(), rel=1e-12)
        belief = {k: v.detach() for k, v in out.final_belief.items()}
    with pytest.raises(ValueError, match="smoother kind"):
        FilterLearner(KalmanFilter(cv_model()), "mse", options={"smoother": "two_filter"})


def test_validation_logs_filtered_and_smoothed_metrics():
    dm = _dm(n=4, steps=25)
    learner = FilterLearner(
        KalmanFilter(cv_model()), "nll", learn=["q"],
        options=LearnerOptions(smoother={"kind": "rts", "train": False}, position_index=[0, 2]),
        optimizer=functools.partial(torch.optim.SGD, lr=0.0),
    )  # fmt: skip
    trainer = pl.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (metrics,) = trainer.validate(learner, dm, verbose=False)
    val = dm.dataset("val")
    filt = evaluate_filter(learner.filter, val, position_index=[0, 2])
    smooth = evaluate_filter(learner.filter, val, position_index=[0, 2], smoother=learner.smoother)
    # Lightning hands back logged values as float32
    assert metrics["val/rmse_pos"] == pytest.approx(filt["rmse_pos"], rel=1e-6)
    assert metrics["val/smoothed_rmse_pos"] == pytest.approx(smooth["rmse_pos"], rel=1e-6)
    assert metrics["val/smoothed_rmse_pos"] < metrics["val/rmse_pos"]
    assert smooth["nll"] == pytest.approx(filt["nll"], rel=1e-12)  # the innovation likelihood is the filter's


def test_smoothed_state_nll_recovers_q_and_r():
    """The log score of the truth under the smoothed posterior is minimised by the true
    parameters (the exact conditional), so unlike the mse it identifies the noise scale too."""
    truth = cv_model(q=0.5, r=25.0)
    sim = ModelSimulator(model=truth, num_steps=80, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    dm = TrajectoryDataModule(sim, train_size=24, val_size=2, test_size=2, batch_size=24, window=None, shuffle=False)
    lbfgs = functools.partial(torch.optim.LBFGS, lr=1.0, max_iter=30, line_search_fn="strong_wolfe")
    options = LearnerOptions(smoother="rts")
    learner = FilterLearner(KalmanFilter(cv_model(q=5.0, r=4.0)), StateNLLLoss(), learn=["q", "R"], optimizer=lbfgs, options=options)
    trainer = pl.Trainer(
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        num_sanity_val_steps=0, limit_val_batches=0, accelerator="cpu", max_epochs=1,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trainer.fit(learner, dm)
    values = learnable_values(learner.filter)
    r = values["model.measurement.R"].diagonal()
    q = values["model.dynamics.inner.q"]
    assert float(((r - 25.0).abs() / 25.0).max()) < 0.15
    assert float(((q - 0.5).abs() / 0.5).max()) < 0.3


@pytest.mark.parametrize("choice", ["rts", "fixed_lag"])
def test_smoother_switch_adds_smoothed_rows(tmp_path, choice):
    conf = str(Path(__file__).resolve().parents[1] / "conf")
    overrides = ["debug=smoke", f"smoother={choice}", "loss=state_nll", "logger=csv", "callbacks=none", "trainer.max_epochs=1"]
    overrides += [
        "data.train_size=4",
        "data.test_size=4",
        "data.max_steps=30",
        f"paths.output_dir={tmp_path}",
        f"paths.log_dir={tmp_path}/logs",
    ]
    with initialize_config_dir(config_dir=conf, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run_experiment(cfg)
    rows = {r["filter"]: r for r in read_rows(tmp_path / "results.csv")}
    assert list(rows) == ["hand-tuned", "hand-tuned (smoothed)", "learned", "learned (smoothed)", "oracle", "oracle (smoothed)"]
    for name in ("hand-tuned", "learned", "oracle"):
        # same filter, same innovations; smoothing uses later measurements, so its error is lower
        assert rows[f"{name} (smoothed)"]["nll"] == rows[name]["nll"]
        assert float(rows[f"{name} (smoothed)"]["rmse_pos"]) < float(rows[name]["rmse_pos"])
    assert "(smoothed)' rows" in (tmp_path / "results.md").read_text()
