"""learn.holdout: contiguous blocks, bounded parameters with a log-distance prior, per-epoch
validation snapshots and selection, paired block-bootstrap tables."""

from __future__ import annotations

import math

import pytest
import pytorch_lightning as pl
import torch

from difffilter.evaluate.intervals import block_bootstrap_difference
from difffilter.filters import KalmanFilter
from difffilter.learn.data import TrajectorySet, WindowedTrajectories
from difffilter.learn.learner import FilterLearner
from difffilter.models.base import StateSpaceModel
from difffilter.models.motion import ConstantVelocity
from difffilter.models.tracking import linear_measurement
from difffilter.params import Interval
from difffilter.selection import named_raw_parameters
from experiments.holdout import (
    EpochSnapshots,
    LogDistancePrior,
    bound_parameters,
    clone_with_snapshot,
    contiguous_blocks,
    error_statistics,
    paired_error_table,
    select_candidate,
)

F64 = torch.float64


def test_contiguous_blocks() -> None:
    blocks = contiguous_blocks(1372, {"train": (0.0, 0.4), "val": (0.4, 0.6), "test": (0.6, 1.0)})
    assert blocks == {"train": (0, 549), "val": (549, 823), "test": (823, 1372)}
    with pytest.raises(ValueError, match="overlap"):
        contiguous_blocks(100, {"a": (0.0, 0.5), "b": (0.4, 1.0)})
    with pytest.raises(ValueError, match="0 <= a < b <= 1"):
        contiguous_blocks(100, {"a": (0.5, 0.2)})
    with pytest.raises(ValueError, match="holds no step"):
        contiguous_blocks(3, {"a": (0.0, 0.1)})


def _model() -> StateSpaceModel:
    return StateSpaceModel(ConstantVelocity(axes=1, dt=1.0, q=0.3, dtype=F64), linear_measurement(R=[4.0], H=[[1.0, 0.0]], dtype="float64"))


def test_bound_parameters_and_prior() -> None:
    model = _model()
    bounds = bound_parameters(model, ["q", "R"], ratio=10.0)
    assert bounds["dynamics.q"] == pytest.approx((0.03, 3.0))
    assert isinstance(model.dynamics.parametrizations.q[0], Interval)
    torch.testing.assert_close(model.dynamics.q.detach(), torch.tensor([0.3], dtype=F64))
    with torch.no_grad():  # any raw value stays in the bounds
        named_raw_parameters(model)["dynamics.q"][0].fill_(40.0)
    assert float(model.dynamics.q.detach()) == pytest.approx(3.0)
    prior = LogDistancePrior(reference=torch.tensor([0.3], dtype=F64), scale=0.5)
    assert float(prior.log_prob(torch.tensor([0.3], dtype=F64))) == 0.0
    assert float(prior.log_prob(torch.tensor([0.3 * math.e], dtype=F64))) == pytest.approx(-2.0)
    with pytest.raises(ValueError, match="ratio"):
        bound_parameters(model, ["q"], ratio=1.0)


def test_selection_prefers_the_earliest_best_epoch() -> None:
    scores = [[5.0, 4.0, 3.0, 1.0], [5.0, 2.0, 2.0], [4.5]]
    assert select_candidate(scores) == (0, 3)
    assert select_candidate(scores, horizon=2) == (1, 1)  # ties -> earlier epoch
    assert select_candidate(scores, horizon=0) == (2, 0)
    assert select_candidate([[math.nan, 3.0], [3.0]]) == (1, 0)  # ties across replicates: earlier epoch first
    with pytest.raises(ValueError, match="no finite"):
        select_candidate([[math.inf]])


def test_epoch_snapshots_record_and_restore_every_epoch() -> None:
    """A Kalman filter learns q by NLL; the callback holds one score and snapshot per epoch (and
    the start); a snapshot restored into a copy reproduces that epoch's score exactly."""
    g = torch.Generator().manual_seed(0)
    truth = torch.cumsum(torch.cumsum(torch.randn(8, 60, 1, generator=g, dtype=F64) * 1.5, 1), 1)
    z = truth + 2.0 * torch.randn(8, 60, 1, generator=g, dtype=F64)
    data = TrajectorySet(
        measurements=z,
        truth=torch.cat([truth, truth], -1),
        initial_mean=torch.zeros(8, 2, dtype=F64),
        initial_cov=torch.eye(2, dtype=F64).expand(8, 2, 2) * 100,
    )
    filt = KalmanFilter(_model())

    def score(f: torch.nn.Module) -> tuple[float, dict[str, float]]:
        res = f(z, data.initial_mean, data.initial_cov)
        e = (res.mean[..., 0] - truth[..., 0]).abs().reshape(-1)
        return float(error_statistics(e)["rms"]), {"median": float(e.median())}

    snaps = EpochSnapshots(score, ["model.dynamics.q"])
    learner = FilterLearner(filt, "nll", learn=["q"], optimizer=lambda p: torch.optim.Adam(p, lr=0.2))
    trainer = pl.Trainer(
        max_epochs=4, logger=False, callbacks=[snaps], enable_checkpointing=False, enable_progress_bar=False, limit_val_batches=0
    )
    trainer.fit(learner, train_dataloaders=WindowedTrajectories(data, batch_size=8))
    assert len(snaps.scores) == len(snaps.snapshots) == 5 and set(snaps.extras[0]) == {"median"}
    assert len({float(s["model.dynamics.q"][0]) for s in snaps.snapshots}) == 5  # q moved every epoch
    for e in (0, 2, 4):
        twin = clone_with_snapshot(KalmanFilter(_model()), snaps.snapshots[e])
        with torch.no_grad():
            assert score(twin)[0] == pytest.approx(snaps.scores[e], rel=1e-12)


def test_paired_error_table_uses_the_library_bootstrap() -> None:
    g = torch.Generator().manual_seed(1)
    hand = torch.rand(300, generator=g, dtype=F64) * 10
    better = hand * 0.8
    rows = paired_error_table({"hand": hand, "better": better}, "hand", block=20, draws=500, seed=3)
    assert rows[0]["filter"] == "hand" and "d_rms" not in rows[0]
    iv = block_bootstrap_difference(better, hand, statistic="rms", block=20, draws=500, seed=3)
    assert (rows[1]["d_rms"], rows[1]["d_rms_lo"], rows[1]["d_rms_hi"]) == (iv.estimate, iv.lo, iv.hi)
    assert rows[1]["d_rms_hi"] < 0 and rows[1]["median"] == pytest.approx(float(better.median()))
    assert rows[1]["p95"] == pytest.approx(float(torch.quantile(better, 0.95)))
    with pytest.raises(ValueError, match="reference"):
        paired_error_table({"a": hand}, "b", block=5)
