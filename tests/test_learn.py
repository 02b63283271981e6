"""The learning stack: in-family sampler, parameter selection, data windows, truncated BPTT,
stability kit and parameter recovery (small scale here, full scale under -m slow)."""

from __future__ import annotations

import functools
import math
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import pytorch_lightning as pl
import torch

from difffilter.evaluate import evaluate_filter
from difffilter.filters import KalmanFilter
from difffilter.learn import (
    FilterLearner,
    LearnerOptions,
    LogNormalPrior,
    LogPrior,
    MSELoss,
    NLLLoss,
    TrajectoryDataModule,
    assign_parameters,
    learnable_values,
    match_parameters,
    select_parameters,
)
from difffilter.learn.data import TrajectorySet, WindowedTrajectories
from difffilter.learn.learner import parameter_scalars
from difffilter.models import LinearModel, TimeInvariantDynamics, linear_measurement, tracking_model
from difffilter.models.base import DynamicsModel, StateSpaceModel
from difffilter.models.motion import ConstantVelocity, Singer
from difffilter.sim import ModelSimulator, sample_trajectories
from tests import memory_probe

f64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
CV_PRIOR = ([0.0, 10.0, 0.0, 5.0], [100.0, 4.0, 100.0, 4.0])
SINGER_PRIOR = ([0.0, 10.0, 0.0, 0.0, 5.0, 0.0], [100.0, 4.0, 1.0, 100.0, 4.0, 1.0])


def cv_model(q: float = 0.5, r: float = 25.0, *, time_invariant: bool = True) -> StateSpaceModel:
    return tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=q, dtype=f64), R=[r, r], time_invariant=time_invariant)


def singer_model(tau: float = 10.0, sigma_a: float = 1.0, r: float = 25.0) -> StateSpaceModel:
    return tracking_model(dynamics=Singer(axes=2, dt=1.0, tau=tau, sigma_a=sigma_a, dtype=f64), R=[r, r], time_invariant=True)


def quiet_trainer(**kw) -> pl.Trainer:
    opts = dict(
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        accelerator="cpu",
    )
    opts.update(kw)
    return pl.Trainer(**opts)


def lbfgs(max_iter: int):
    return functools.partial(torch.optim.LBFGS, lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")


# -- sampler -------------------------------------------------------------------------------------
def test_sampler_shapes_determinism_and_dtypes():
    model = cv_model()
    kw = dict(batch_size=3, num_steps=7, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    a = sample_trajectories(model, seed=11, **kw)
    b = sample_trajectories(model, seed=11, **kw)
    c = sample_trajectories(model, seed=12, **kw)
    d = sample_trajectories(model, seed=11, dtype="float32", **kw)
    assert a.truth.shape == (3, 7, 4) and a.measurements.shape == (3, 7, 2) and a.mask is None
    assert a.initial_mean.shape == (3, 4) and a.initial_cov.shape == (4, 4)
    assert torch.equal(a.truth, b.truth) and torch.equal(a.measurements, b.measurements)
    assert not torch.equal(a.truth, c.truth)
    assert d.truth.dtype == torch.float32 and torch.equal(d.truth, a.truth.float())
    assert set(a.true_params) == {"dynamics.inner.q", "measurement.R"}
    m = a.make_model()
    assert m is not model and torch.equal(m.R, model.R)
    with pytest.raises(ValueError, match="initial_cov"):
        sample_trajectories(model, batch_size=2, num_steps=3, initial_mean=CV_PRIOR[0], initial_cov=torch.eye(3))


def test_sampler_noise_statistics_match_the_model():
    # x_k - F x_{k-1} ~ N(0, Q) and z_k - H x_k ~ N(0, R): sample covariances within ~4 standard
    # errors (var of a sample variance of N normals: 2 s^4 / N).
    g = torch.Generator().manual_seed(0)
    a = torch.randn(3, 3, generator=g, dtype=f64)
    Q = a @ a.T + 0.5 * torch.eye(3, dtype=f64)
    F = torch.eye(3, dtype=f64) * 0.9 + 0.05
    H = torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, -1.0]], dtype=f64)
    R = torch.tensor([[2.0, 0.3], [0.3, 0.5]], dtype=f64)
    model = LinearModel(F=F, H=H, Q=Q, R=R)
    data = sample_trajectories(
        model, batch_size=200, num_steps=50, initial_mean=torch.ones(3, dtype=f64), initial_cov=torch.eye(3, dtype=f64), seed=1
    )
    x = torch.cat([data.initial_state[:, None], data.truth], 1)
    w = (x[:, 1:] - x[:, :-1] @ F.T).reshape(-1, 3)
    v = (data.measurements - data.truth @ H.T).reshape(-1, 2)
    n = w.shape[0]
    for sample, ref in ((w.T @ w / n, Q), (v.T @ v / n, R)):
        se = torch.sqrt((ref.diagonal()[:, None] * ref.diagonal()[None, :] + ref**2) / n)
        assert bool(((sample - ref).abs() < 4 * se).all()), (sample, ref)
    x0 = data.initial_state - 1.0
    assert float(x0.mean()) == pytest.approx(0.0, abs=4 / math.sqrt(600))


def test_sampler_state_dependent_noise_and_missing():
    class Growing(DynamicsModel):
        """x_k = x_{k-1} + w, Var(w) = 0.01 + x^2: checks process_noise(x) is used."""

        def __init__(self) -> None:
            super().__init__()
            self.state_dim = 1

        def forward(self, x, u=None):
            return x

        def process_noise(self, x, u=None):
            return (0.01 + x[..., None] ** 2) * torch.ones(1, 1, dtype=x.dtype)

    model = StateSpaceModel(Growing(), linear_measurement(R=1.0, H=[[1.0]]))
    data = sample_trajectories(model, batch_size=4000, num_steps=1, initial_mean=[2.0], initial_cov=[[1e-12]], seed=3, missing_prob=0.3)
    step = data.truth[:, 0, 0] - 2.0
    assert float(step.var()) == pytest.approx(4.01, rel=4 * math.sqrt(2 / 4000))
    assert data.mask is not None and float(data.mask.double().mean()) == pytest.approx(0.7, abs=0.03)
    assert bool(torch.isnan(data.measurements[~data.mask]).all())


def test_model_simulator_sets_true_params_and_num_steps():
    sim = ModelSimulator(
        model=cv_model(q=3.0), num_steps=20, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1], true_params={"q": 0.5, "R": [9.0, 4.0]}
    )
    data = sim(batch_size=2, seed=0, dtype="float64")
    assert data.truth.shape == (2, 20, 4) and sim(batch_size=2, seed=0, num_steps=5).truth.shape == (2, 5, 4)
    torch.testing.assert_close(data.true_params["measurement.R"], torch.diag(torch.tensor([9.0, 4.0], dtype=f64)))
    torch.testing.assert_close(data.true_params["dynamics.inner.q"], torch.tensor([0.5, 0.5], dtype=f64))


# -- parameter selection -------------------------------------------------------------------------
def test_match_select_and_assign_parameters():
    kf = KalmanFilter(cv_model())
    assert match_parameters(kf, ["R"]) == {"R": ["model.measurement.R"]}
    assert match_parameters(kf, ["model.*.q"]) == {"model.*.q": ["model.dynamics.inner.q"]}
    with pytest.raises(ValueError, match="matches nothing"):
        match_parameters(kf, ["tau"])
    names = select_parameters(kf, ["R"])
    assert names == ["model.measurement.R"]
    assert [p.requires_grad for p in kf.parameters()].count(True) == 1
    assert set(learnable_values(kf)) == {"model.measurement.R"}
    assign_parameters(kf, {"R": [9.0, 4.0], "q": 2.0})
    torch.testing.assert_close(kf.model.R, torch.diag(torch.tensor([9.0, 4.0], dtype=f64)))
    torch.testing.assert_close(kf.model.dynamics.inner.q, torch.tensor([2.0, 2.0], dtype=f64))
    full = LinearModel(
        F=torch.eye(2, dtype=f64), H=torch.eye(2, dtype=f64), Q=torch.eye(2, dtype=f64), R=torch.eye(2, dtype=f64), Q_structure="scalar"
    )
    assign_parameters(full, {"Q": 3.0, "R": 2.0})  # scalar: ScaledMatrix scale / s * I
    torch.testing.assert_close(full.Q, 3.0 * torch.eye(2, dtype=f64))
    torch.testing.assert_close(full.R, 2.0 * torch.eye(2, dtype=f64))
    with pytest.raises(ValueError, match="cannot set"):
        assign_parameters(full, {"R": [[1.0, 2.0], [2.0, 1.0]]})  # not positive definite


def test_time_invariant_dynamics_matches_and_tracks_parameter_changes():
    z = sample_trajectories(singer_model(), batch_size=3, num_steps=25, initial_mean=SINGER_PRIOR[0], initial_cov=SINGER_PRIOR[1], seed=0)
    plain = KalmanFilter(tracking_model(dynamics=Singer(axes=2, dt=1.0, tau=7.0, sigma_a=0.8, dtype=f64), R=[20.0, 30.0]))
    cached = KalmanFilter(
        tracking_model(dynamics=Singer(axes=2, dt=1.0, tau=7.0, sigma_a=0.8, dtype=f64), R=[20.0, 30.0], time_invariant=True)
    )
    assert isinstance(cached.model.dynamics, TimeInvariantDynamics)
    grads = []
    for kf in (plain, cached):
        loss = -kf(z.measurements, z.initial_mean, z.initial_cov).log_likelihood.sum()
        loss.backward()
        grads.append(torch.cat([p.grad.flatten() for p in kf.parameters()]))
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)
    for kf in (plain, cached):  # a changed parameter must be seen by the next run
        assign_parameters(kf, {"tau": 30.0})
    a = plain(z.measurements, z.initial_mean, z.initial_cov).mean
    b = cached(z.measurements, z.initial_mean, z.initial_cov).mean
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    import copy

    copy.deepcopy(cached)  # the cache (non-leaf tensors) must not break deep copies
    with pytest.raises(ValueError, match="per-step inputs"):
        cached(z.measurements, z.initial_mean, z.initial_cov, controls={"dt": torch.ones(3, 25, 1, dtype=f64)})


# -- data ----------------------------------------------------------------------------------------
def _data(n=6, steps=10, **kw) -> TrajectorySet:
    sim = ModelSimulator(model=cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1], missing_prob=0.2)
    raw = sim(batch_size=n, seed=4)
    raw.controls = {"dt": torch.arange(n * steps, dtype=f64).reshape(n, steps, 1)}
    return TrajectorySet.from_simulation(raw, f64, **kw)


def test_windows_cover_trajectories_in_order_with_masks_and_controls():
    data = _data()
    ds = WindowedTrajectories(data, batch_size=4, window=4)
    batches = list(ds)
    assert len(batches) == len(ds) == 2 * 3
    assert [b["window_index"] for b in batches] == [0, 1, 2, 0, 1, 2]
    assert [b["measurements"].shape[1] for b in batches] == [4, 4, 2, 4, 4, 2]
    first = batches[:3]
    z = torch.cat([b["measurements"] for b in first], 1)
    torch.testing.assert_close(z, data.measurements[:4], equal_nan=True)
    torch.testing.assert_close(torch.cat([b["mask"] for b in first], 1), data.mask[:4])
    torch.testing.assert_close(torch.cat([b["controls"]["dt"] for b in first], 1), data.controls["dt"][:4])
    assert batches[3]["index"].tolist() == [4, 5]


def test_shards_shuffle_and_truncation():
    data = _data(n=7, steps=10, max_steps=6)
    assert data.num_steps == 6
    shards = [
        WindowedTrajectories(data, batch_size=2, window=None, shuffle=True, seed=3, rank=r, world_size=2, equal_shards=True) for r in (0, 1)
    ]
    ids = [torch.cat([b["index"] for b in s]) for s in shards]
    assert len(ids[0]) == len(ids[1]) == 3 and not set(ids[0].tolist()) & set(ids[1].tolist())
    again = torch.cat([b["index"] for b in shards[0]])  # next pass reshuffles, deterministically
    fresh = WindowedTrajectories(data, batch_size=2, shuffle=True, seed=3, rank=0, world_size=2, equal_shards=True)
    list(fresh)
    assert torch.equal(again, torch.cat([b["index"] for b in fresh]))


def test_datamodule_seeds_and_max_steps():
    sim = ModelSimulator(model=cv_model(), num_steps=50, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    dm = TrajectoryDataModule(
        sim, train_size=4, val_size=3, test_size=2, batch_size=2, max_steps=12, seeds={"train": 5, "val": 6, "test": 7}
    )
    dm.setup()
    assert len(dm.dataset("train")) == 4 and len(dm.dataset("val")) == 3 and len(dm.dataset("test")) == 2
    assert dm.dataset("train").num_steps == 12  # passed to the simulator as num_steps
    assert not torch.equal(dm.dataset("train").measurements[:2], dm.dataset("val").measurements[:2])
    torch.testing.assert_close(dm.dataset("train").measurements, sim(batch_size=4, seed=5, num_steps=12).measurements)
    assert len(list(dm.val_dataloader())) == 1
    with pytest.warns(UserWarning, match="not distinct"):
        TrajectoryDataModule(sim, seeds={"train": 1, "val": 1})


# -- truncated BPTT ------------------------------------------------------------------------------
def _grads(module) -> torch.Tensor:
    return torch.cat([p.grad.flatten() for p in module.parameters() if p.requires_grad])


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
@pytest.mark.parametrize("window", [40, 64])
def test_window_at_least_T_equals_full_bptt(window):
    steps = 40
    sim = ModelSimulator(model=cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1], missing_prob=0.1)
    dm = TrajectoryDataModule(sim, train_size=3, val_size=1, test_size=1, batch_size=3, window=window, shuffle=False)
    dm.setup("fit")
    start = {"q": 2.0, "R": [9.0, 16.0]}
    learner = FilterLearner(KalmanFilter(cv_model()), "nll", learn=["q", "R"])
    assign_parameters(learner.filter, start)
    (batch,) = list(dm.train_dataloader())
    learner.training_step(batch, 0).backward()
    ref = KalmanFilter(cv_model())
    assign_parameters(ref, start)
    data = dm.dataset("train")
    res = ref(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask)
    NLLLoss()(res, {}).mean().backward()
    torch.testing.assert_close(_grads(learner.filter), _grads(ref), rtol=1e-10, atol=1e-10)


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_windows_carry_the_belief_and_truncate_gradients():
    steps, window = 60, 15
    sim = ModelSimulator(model=cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    dm = TrajectoryDataModule(sim, train_size=4, val_size=1, test_size=1, batch_size=4, window=window, shuffle=False)
    dm.setup("fit")
    learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), "nll", learn=["q"])
    losses = []
    for i, batch in enumerate(dm.train_dataloader()):
        loss = learner.training_step(batch, i)
        loss.backward()
        losses.append(float(loss.detach()))
    truncated = _grads(learner.filter)
    ref = KalmanFilter(cv_model(q=2.0))
    select_parameters(ref, ["q"])
    data = dm.dataset("train")
    full = NLLLoss()(ref(data.measurements, data.initial_mean, data.initial_cov), {}).mean()
    # Equal windows: the mean of the window losses is the full-run loss (belief carried exactly).
    assert sum(losses) / len(losses) == pytest.approx(float(full), rel=1e-12)
    (full * len(losses)).backward()
    # ... but gradients stop at window boundaries, so they differ from full BPTT.
    assert float((truncated - _grads(ref)).abs().max()) > 1e-8


# -- stability kit -------------------------------------------------------------------------------
def _small_dm(n=4, steps=20, window=None) -> TrajectoryDataModule:
    sim = ModelSimulator(model=cv_model(), num_steps=steps, initial_mean=CV_PRIOR[0], initial_cov=CV_PRIOR[1])
    return TrajectoryDataModule(sim, train_size=n, val_size=2, test_size=2, batch_size=n, window=window, shuffle=False)


def test_nonfinite_trajectories_are_excluded_and_counted():
    def loss(result, batch):
        nll = NLLLoss()(result, batch)
        return torch.where(batch["index"] == 0, torch.full_like(nll, float("nan")), nll)

    learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), loss, learn=["q"], optimizer=functools.partial(torch.optim.SGD, lr=1e-3))
    with pytest.warns(RuntimeWarning, match="non-finite loss were left out"):
        quiet_trainer(max_epochs=1).fit(learner, _small_dm(window=5))
    assert learner.nonfinite_trajectories == 4 and learner.skipped_steps == 0
    assert float(learner.filter.model.dynamics.inner.q[0]) != 2.0


def test_nonfinite_loss_or_gradient_skips_the_step():
    def nan_loss(result, batch):
        return NLLLoss()(result, batch) * float("nan")

    def nan_grad(result, batch):
        q = learner.filter.model.dynamics.inner.parametrizations.q.original
        return NLLLoss()(result, batch) + torch.sqrt(q - q.detach()).sum()  # value 0, gradient inf

    for fn in (nan_loss, nan_grad):
        learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), fn, learn=["q"], optimizer=functools.partial(torch.optim.Adam, lr=0.1))
        with pytest.warns(RuntimeWarning) as record:
            quiet_trainer(max_epochs=2).fit(learner, _small_dm(window=10))
        messages = [str(w.message) for w in record if issubclass(w.category, RuntimeWarning)]
        assert sum("step with a non-finite" in m for m in messages) == 1  # warned once, counted always
        assert learner.skipped_steps == 4
        torch.testing.assert_close(learner.filter.model.dynamics.inner.q, torch.tensor([2.0, 2.0], dtype=f64))


def test_gradient_clipping_from_the_trainer_bounds_the_step():
    learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), "nll", learn=["q"], optimizer=functools.partial(torch.optim.SGD, lr=1.0))
    raw = learner.filter.model.dynamics.inner.parametrizations.q.original
    before = raw.detach().clone()
    quiet_trainer(max_epochs=1, gradient_clip_val=1e-3).fit(learner, _small_dm())
    assert float((raw.detach() - before).norm()) == pytest.approx(1e-3, rel=1e-4)  # Lightning divides by (norm + 1e-6)


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_log_prior_enters_the_loss():
    prior = LogNormalPrior(loc=math.log(100.0), scale=0.5)
    kw = dict(learn=["R"])
    plain = FilterLearner(KalmanFilter(cv_model()), "nll", **kw)
    with_prior = FilterLearner(KalmanFilter(cv_model()), "nll", prior=LogPrior({"R": prior}, weight=0.3), **kw)
    batch = next(iter(_small_dm().train_dataloader()))
    r = torch.tensor([25.0, 25.0], dtype=f64)
    ref = float((-0.5 * ((r.log() - math.log(100.0)) / 0.5) ** 2 - math.log(0.5) - 0.5 * math.log(2 * math.pi) - r.log()).sum())
    assert float(with_prior.log_prior()) == pytest.approx(ref, rel=1e-12)
    got, base = with_prior.training_step(batch, 0).detach(), plain.training_step(batch, 0).detach()
    assert float(got) == pytest.approx(float(base) - 0.3 * ref, rel=1e-12)


def test_parameter_scalars_and_argument_errors():
    assert parameter_scalars("p/tau", torch.tensor([3.0, 4.0])) == {"p/tau[0]": 3.0, "p/tau[1]": 4.0}
    assert parameter_scalars("p/R", torch.diag(torch.tensor([1.0, 2.0]))) == {"p/R[0,0]": 1.0, "p/R[1,1]": 2.0}
    pi = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=f64)
    assert parameter_scalars("p/Pi", pi) == {
        "p/Pi[0,0]": 0.9,
        "p/Pi[0,1]": pytest.approx(0.1),
        "p/Pi[1,0]": pytest.approx(0.2),
        "p/Pi[1,1]": pytest.approx(0.8),
    }
    assert parameter_scalars("p/d", torch.tensor(0.85)) == {"p/d": pytest.approx(0.85)}
    with pytest.raises(ValueError, match="loss must be"):
        FilterLearner(KalmanFilter(cv_model()), "l2")
    with pytest.raises(TypeError, match="GaussianFilter"):
        FilterLearner(cv_model())  # type: ignore[arg-type]
    learner = FilterLearner(KalmanFilter(cv_model()), "nll", learn=["R"])
    with pytest.raises(ValueError, match="initial belief"):
        learner.initial_belief({"initial_mean": None})


# -- parameter recovery --------------------------------------------------------------------------
def _recover(truth, start, learn, loss, *, n, steps, prior, position_index, max_iter=40, test_n=32):
    sim = ModelSimulator(model=truth, num_steps=steps, initial_mean=prior[0], initial_cov=prior[1])
    dm = TrajectoryDataModule(sim, train_size=n, val_size=2, test_size=test_n, batch_size=n, window=None, shuffle=False)
    options = LearnerOptions(position_index=position_index)
    learner = FilterLearner(KalmanFilter(start), loss, learn=learn, optimizer=lbfgs(max_iter), options=options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        quiet_trainer(max_epochs=1).fit(learner, dm)
    test = dm.dataset("test")
    learned = evaluate_filter(learner.filter, test, position_index=position_index)
    oracle = evaluate_filter(KalmanFilter(truth), test, position_index=position_index)
    return learnable_values(learner.filter), learned, oracle


def _rel(a, b) -> float:
    return float(((a - b).abs() / b.abs()).max())


def test_recovery_cv_nll():
    # In-family 2-D CV, 32 x 100 steps, from q = 5 (10 x) and R = 4 m^2 (1/6 x) by maximum likelihood.
    start = cv_model(q=5.0, r=4.0)
    values, learned, oracle = _recover(cv_model(), start, ["q", "R"], "nll", n=32, steps=100, prior=CV_PRIOR, position_index=[0, 2])
    assert _rel(values["model.measurement.R"].diagonal(), torch.tensor([25.0, 25.0], dtype=f64)) < 0.10
    assert _rel(values["model.dynamics.inner.q"], torch.tensor([0.5, 0.5], dtype=f64)) < 0.25
    assert learned["nll"] - oracle["nll"] < 0.01


def test_recovery_cv_mse_identifies_the_ratio_only():
    # The mse loss sees the posterior mean, i.e. the gain, which depends on Q/R only: it recovers
    # the ratio q/r and the oracle's RMSE, not the scale (which stays wherever it drifts).
    start = cv_model(q=5.0, r=4.0)
    values, learned, oracle = _recover(
        cv_model(), start, ["q", "R"], MSELoss(state_index=[0, 2]), n=32, steps=100, prior=CV_PRIOR, position_index=[0, 2]
    )
    ratio = values["model.dynamics.inner.q"] / values["model.measurement.R"].diagonal()
    assert _rel(ratio, torch.tensor([0.02, 0.02], dtype=f64)) < 0.25
    assert learned["rmse_pos"] < 1.01 * oracle["rmse_pos"]


def test_recovery_singer_tau_small():
    # Singer tau (and sigma_a, the Q scale) from p000's tau = 100 s; R known.
    truth = singer_model(tau=10.0, sigma_a=1.0)
    start = singer_model(tau=100.0, sigma_a=0.3)
    values, learned, oracle = _recover(
        truth, start, ["tau", "sigma_a"], "nll", n=16, steps=100, prior=SINGER_PRIOR, position_index=[0, 3], max_iter=25, test_n=16
    )
    assert _rel(values["model.dynamics.inner.tau"], torch.tensor([10.0, 10.0], dtype=f64)) < 0.20
    assert _rel(values["model.dynamics.inner.sigma_a"], torch.tensor([1.0, 1.0], dtype=f64)) < 0.25
    assert learned["nll"] - oracle["nll"] < 0.01


@pytest.mark.slow
@pytest.mark.parametrize("loss", ["nll", "mse"])
def test_recovery_singer_full_scale(loss):
    truth = singer_model(tau=10.0, sigma_a=1.0, r=25.0)
    start = singer_model(tau=100.0, sigma_a=0.3, r=100.0)
    fn = "nll" if loss == "nll" else MSELoss(state_index=[0, 3])
    values, learned, oracle = _recover(
        truth, start, ["tau", "sigma_a", "R"], fn, n=64, steps=200, prior=SINGER_PRIOR, position_index=[0, 3], max_iter=60, test_n=64
    )
    print(
        f"\n[{loss}] learned { ({k: v.diagonal() if v.ndim == 2 else v for k, v in values.items()}) }\n learned {learned}\n oracle {oracle}"
    )
    tau, sigma, r = values["model.dynamics.inner.tau"], values["model.dynamics.inner.sigma_a"], values["model.measurement.R"].diagonal()
    if loss == "nll":
        assert _rel(r, torch.tensor([25.0, 25.0], dtype=f64)) < 0.10
        assert _rel(sigma, torch.tensor([1.0, 1.0], dtype=f64)) < 0.25
        assert _rel(tau, torch.tensor([10.0, 10.0], dtype=f64)) < 0.20
        assert learned["nll"] - oracle["nll"] < 0.01
    else:  # mse: the gain-relevant ratio sigma_a^2 / R and the oracle's accuracy
        assert _rel(sigma**2 / r, torch.tensor([0.04, 0.04], dtype=f64)) < 0.30
        assert learned["rmse_pos"] < 1.01 * oracle["rmse_pos"]


# -- long trajectories: bounded memory with TBPTT ------------------------------------------------
# Each configuration runs in its own fresh interpreter (tests/memory_probe.py), which reads its
# own peak RSS from /proc/self/status: the pytest process's peak (raised by earlier tests) and the
# ru_maxrss a child inherits from it must not enter the measurement.
needs_proc_status = pytest.mark.skipif(not memory_probe.available(), reason="needs /proc/self/status (Linux)")


def _probe(*args: int) -> tuple[int, int]:
    out = subprocess.run(
        [sys.executable, "-m", "tests.memory_probe", *map(str, args)], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-2000:]
    base, peak = map(int, out.stdout.split())
    return base, peak


@needs_proc_status
def test_memory_probe_measures_only_its_own_process():
    # The parent holds ~256 MiB; a fresh child's peak must not include it (ru_maxrss would).
    held = bytearray(256 * 1024 * 1024)
    held[::4096] = b"\x01" * len(held[::4096])
    assert memory_probe.peak_kib() > 256 * 1024
    child = (
        "from tests import memory_probe as m\n"
        "first = m.peak_kib()\n"
        "x = bytearray(64 * 1024 * 1024); x[::4096] = b'\\x01' * len(x[::4096]); grown = m.peak_kib(); del x\n"
        "reset = m.reset_peak()\n"
        "print(first, grown, m.peak_kib() if reset else -1, m.current_kib())\n"
    )
    out = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, check=True, timeout=120)
    first, grown, after_reset, now = map(int, out.stdout.split())
    del held
    assert first < 128 * 1024  # a bare interpreter, not the parent's 256+ MiB
    assert grown - first > 60 * 1024  # the child's own 64 MiB is seen
    if after_reset >= 0:  # clear_refs accepted: the peak is back near the current RSS
        assert after_reset < now + 8 * 1024
    with pytest.raises(ValueError, match="window must be >= 1"):
        memory_probe.measure(0)
    with pytest.raises(TypeError, match="window must be an int"):
        memory_probe.measure(1.5)


@pytest.mark.slow
@needs_proc_status
def test_tbptt_memory_is_bounded_for_T_5000():
    peaks = {window: _probe(window, 8, 5000) for window in (100, 5000)}  # KiB: after setup, peak of the pass
    growth = {w: p - b for w, (b, p) in peaks.items()}
    print(
        f"\nRSS (KiB), B=8, T=5000, CV Kalman filter, NLL: after setup / peak of the pass: window 100 {peaks[100]},"
        f" full BPTT {peaks[5000]}; growth {growth}"
    )
    assert growth[5000] > 50 * 1024  # the full graph of 5000 steps
    assert growth[100] * 10 < growth[5000]  # 100-step windows: the graph of one window only


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_reevaluating_a_window_starts_from_the_previous_window():
    # LBFGS calls its closure (training_step) several times on the same window.
    dm = _small_dm(n=2, steps=20, window=10)
    dm.setup("fit")
    first, second = list(dm.train_dataloader())
    learner = FilterLearner(KalmanFilter(cv_model(q=2.0)), "nll", learn=["q"])
    learner.training_step(first, 0)
    a = learner.training_step(second, 1).detach()
    b = learner.training_step(second, 1).detach()
    assert float(a) == float(b)
    with pytest.warns(RuntimeWarning, match="without its previous window"):
        FilterLearner(KalmanFilter(cv_model(q=2.0)), "nll", learn=["q"]).training_step(second, 1)


def test_jitter_bound_caps_the_ladder_and_restores_it():
    from difffilter import linalg

    a = torch.tensor([[1.0, 1.0], [1.0, 1.0 - 1e-7]], dtype=f64)  # needs ~1e-7 relative jitter
    assert float(linalg.safe_cholesky(a).jitter) == pytest.approx(1e-6)
    with linalg.jitter_bound(1e-8):
        assert math.isinf(float(linalg.safe_cholesky(a).jitter))
    assert float(linalg.safe_cholesky(a).jitter) == pytest.approx(1e-6)
