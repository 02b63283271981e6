"""The thin FilterLearner: its few arguments, LearnerOptions in checkpoints (new and flat legacy
hyperparameters), and the runner's mapping of the flat ``learner.*`` config keys."""

from __future__ import annotations

import copy
import inspect

import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.filters import KalmanFilter
from difffilter.learn import FilterLearner, LearnerOptions, LogNormalPrior, LogPrior
from difffilter.learn.replicates import perturb_initial_values
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.selection import learnable_values, select_parameters
from difffilter.sim import sample_trajectories
from experiments.runner.learner_config import finish_learner, split_learner_config

f64 = torch.float64
M0, P0 = [0.0, 10.0, 0.0, 5.0], [100.0, 4.0, 100.0, 4.0]


def _kf(q: float = 0.5) -> KalmanFilter:
    return KalmanFilter(tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=q, dtype=f64), R=[25.0, 25.0], time_invariant=True))


def _batch() -> dict:
    data = sample_trajectories(_kf().model, batch_size=3, num_steps=12, initial_mean=M0, initial_cov=P0, seed=4)
    return {"measurements": data.measurements, "truth": data.truth}


def test_at_most_eight_arguments():
    params = [p for p in inspect.signature(FilterLearner.__init__).parameters if p != "self"]
    assert len(params) <= 8, params


def test_options_validate_and_name_what_is_wrong():
    with pytest.raises(ValueError, match="scheduler_interval"):
        LearnerOptions(scheduler_interval="batch")
    with pytest.raises(ValueError, match="smoother kind"):
        LearnerOptions(smoother="two_filter")
    with pytest.raises(ValueError, match="unknown learner options"):
        LearnerOptions.of({"dtype": "float64"})
    with pytest.raises(TypeError, match="LogPrior"):
        FilterLearner(_kf(), "nll", prior={"R": LogNormalPrior(loc=0.0, scale=1.0)})  # type: ignore[arg-type]
    assert LearnerOptions(position_index=(0, 2)).indices["position_index"] == [0, 2]


def _save(learner: FilterLearner, path, hparams: dict) -> None:
    torch.save({"state_dict": learner.state_dict(), "hyper_parameters": hparams, "pytorch-lightning_version": "2.6.0"}, path)


def test_options_travel_in_the_checkpoint_as_plain_values(tmp_path):
    opts = LearnerOptions(initial_mean=M0, initial_cov=P0, max_jitter=1e-6, position_index=[0, 2], smoother="rts")
    learner = FilterLearner(_kf(), "nll", learn=["q"], options=opts)
    assert learner.initial_cov.shape == (4, 4) and learner.initial_cov.dtype == f64
    path = tmp_path / "a.ckpt"
    _save(learner, path, dict(learner.hparams))
    loaded = FilterLearner.load_from_checkpoint(str(path), filter=_kf(q=3.0))  # weights_only loading inside
    assert loaded.options == opts and loaded.smoother is not None
    torch.testing.assert_close(loaded.initial_cov, learner.initial_cov)
    torch.testing.assert_close(learnable_values(loaded.filter), learnable_values(learner.filter))


def test_a_checkpoint_with_the_former_flat_hyperparameters_loads(tmp_path):
    # before LearnerOptions, initial_mean/initial_cov/position_index... were the learner's own arguments
    learner = FilterLearner(_kf(), "nll", options=LearnerOptions(initial_mean=M0, initial_cov=P0))
    path = tmp_path / "old.ckpt"
    flat = {"loss": "nll", "learn": None, "initial_mean": M0, "initial_cov": P0, "position_index": [0, 2]}
    flat.update(dtype="float64", fused=False, init_perturbation=0.0)
    _save(learner, path, flat)
    loaded = FilterLearner.load_from_checkpoint(str(path), filter=_kf())
    assert loaded.options.position_index == [0, 2] and loaded.options.initial_mean == M0
    torch.testing.assert_close(loaded.initial_mean, torch.tensor(M0, dtype=f64))


def test_prior_enters_the_training_loss():
    batch = {**_batch(), "initial_mean": torch.tensor(M0, dtype=f64), "initial_cov": torch.diag(torch.tensor(P0, dtype=f64))}
    prior = LogPrior({"q": LogNormalPrior(loc=0.0, scale=1.0)}, weight=0.5)
    plain, with_prior = FilterLearner(_kf(), "nll", learn=["q"]), FilterLearner(_kf(), "nll", learn=["q"], prior=prior)
    q = torch.tensor([0.5, 0.5], dtype=f64)  # one q per axis
    log_p = (-0.5 * q.log() ** 2 - 0.5 * torch.log(torch.tensor(2 * torch.pi, dtype=f64)) - q.log()).sum()
    with pytest.warns(UserWarning, match="self.log"):  # no Trainer attached: Lightning warns, the value is returned
        diff = with_prior.training_step(batch, 0) - plain.training_step(batch, 0)
    assert float(diff.detach()) == pytest.approx(-0.5 * float(log_p), rel=1e-12)


def test_runner_maps_every_flat_learner_key():
    flat = {
        "_target_": "difffilter.learn.learner.FilterLearner",
        "learn": ["q"],
        "optimizer": None,
        "scheduler": None,
        "scheduler_interval": "step",
        "monitor": "val/nll",
        "initial_mean": M0,
        "initial_cov": P0,
        "log_prior": {"q": {"_target_": "difffilter.learn.losses.LogNormalPrior", "loc": 0.0, "scale": 1.0}},
        "prior_weight": 0.25,
        "dtype": "float64",
        "max_jitter": None,
        "fused": "eager",
        "smoother": None,
        "init_perturbation": 0.3,
        "init_seed": 7,
        "position_index": [0, 2],
        "truth_position_index": None,
        "state_index": None,
        "truth_index": None,
        "figure_every_n_epochs": 5,
    }
    factory, settings = split_learner_config(flat)
    assert settings == {"dtype": "float64", "fused": "eager", "init_perturbation": 0.3, "init_seed": 7, "figure_every_n_epochs": 5}
    from hydra.utils import instantiate

    learner = instantiate(factory, _convert_="all", filter=_kf(), loss="nll")
    assert learner.options.scheduler_interval == "step" and learner.options.position_index == [0, 2]
    assert learner.prior is not None and learner.prior.weight == 0.25
    # the runner's part, in the order the learner once applied it: dtype, perturbation, engine
    expected = _kf()
    perturb_initial_values(expected, select_parameters(expected, ["q"]), 0.3, seed=7)
    finish_learner(learner, settings)
    assert isinstance(learner.engine, FusedFilter)
    torch.testing.assert_close(learnable_values(learner.filter), learnable_values(expected))
    assert learnable_values(learner.filter)["model.dynamics.inner.q"][0] != 0.5
    with pytest.raises(ValueError, match="learner.fused"):
        split_learner_config({"fused": "yes"})
    # a fused learner computes what the plain one computes
    plain = FilterLearner(copy.deepcopy(learner.filter), "nll", options=learner.options)
    batch = _batch()
    torch.testing.assert_close(learner(batch).mean, plain(batch).mean)
    # dtype: the filter and the initial-belief buffers
    single = finish_learner(FilterLearner(_kf(), "nll", options={"initial_mean": M0, "initial_cov": P0}), {"dtype": "float32"})
    assert single.initial_cov.dtype == torch.float32 and all(p.dtype == torch.float32 for p in single.filter.parameters())
