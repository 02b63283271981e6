"""One trajectory container: TrajectorySet, which the sampler's and the papers' trajectories
subclass; a raw (shared initial belief) and a normalised set batch alike."""

from __future__ import annotations

import importlib

import pytest
import torch

import difffilter.learn as learn
from difffilter.learn.data import TrajectoryDataModule
from difffilter.models import tracking_model
from difffilter.models.motion import ConstantVelocity
from difffilter.sim import ModelSimulator, SampledTrajectories, TrajectorySet, sample_trajectories

f64 = torch.float64
M0, P0 = [0.0, 1.0, 0.0, 2.0], [4.0, 1.0, 4.0, 1.0]


def _model():
    return tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=0.5, dtype=f64), R=[4.0, 4.0])


def test_sampled_trajectories_are_a_trajectory_set_and_batch_like_the_normalised_set():
    data = sample_trajectories(_model(), batch_size=5, num_steps=9, initial_mean=M0, initial_cov=P0, seed=3, missing_prob=0.2)
    assert isinstance(data, TrajectorySet) and learn.TrajectorySet is TrajectorySet
    assert data.initial_cov.shape == (4, 4)  # one P0 for all: the raw producer's layout
    norm = TrajectorySet.from_simulation(data, f64)
    assert type(norm) is TrajectorySet and norm.source is data and norm.initial_cov.shape == (5, 4, 4)
    index = torch.tensor([3, 0])
    raw_batch, norm_batch = data.batch(index, 2, 7), norm.batch(index, 2, 7)
    assert raw_batch.keys() == norm_batch.keys()
    for key, value in norm_batch.items():
        other = raw_batch[key]
        if isinstance(value, torch.Tensor):
            torch.testing.assert_close(other, value, rtol=0, atol=0, equal_nan=True, msg=key)
        else:
            assert other == value, key
    assert torch.equal(norm_batch["initial_cov"][1], torch.diag(torch.tensor(P0, dtype=f64)))
    torch.testing.assert_close(norm_batch["measurements"], data.measurements[index][:, 2:7], rtol=0, atol=0, equal_nan=True)


def test_the_data_module_serves_a_trajectory_set():
    sim = ModelSimulator(model=_model(), num_steps=6, initial_mean=M0, initial_cov=P0)
    dm = TrajectoryDataModule(sim, train_size=3, val_size=2, test_size=2, batch_size=3, window=None)
    test = dm.dataset("test")
    assert type(test) is TrajectorySet and isinstance(test.source, SampledTrajectories) and len(test) == 2


@pytest.mark.parametrize(
    ("module", "name"),
    [
        ("experiments.papers.p000.experiment", "P000Trajectories"),
        ("experiments.papers.p001.experiment", "P001Trajectories"),
        ("experiments.papers.p004.experiment", "P004Trajectories"),
        ("experiments.papers.smartloc.experiment", "SmartLocTrajectories"),
    ],
)
def test_papers_subclass_the_one_container(module, name):
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, TrajectorySet)


def test_the_former_second_container_is_a_deprecated_name_of_the_first():
    import difffilter.learn.data as data_module

    with pytest.warns(DeprecationWarning, match="subclass difffilter.sim.TrajectorySet"):
        assert data_module.SimulatedTrajectories is TrajectorySet
    with pytest.raises(AttributeError):
        data_module.NoSuchContainer  # noqa: B018
