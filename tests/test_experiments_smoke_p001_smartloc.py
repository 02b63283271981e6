"""p001 (coloured-noise UKF) and smartLoc (real drive) experiments: smoke runs of the Hydra
experiments, and fast checks of their support modules (simulator adapter, learner start,
shared-Psi coloured UKF, snapshot WLS baseline, real-data windows)."""

from __future__ import annotations

import copy
import csv
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from difffilter.filters import UKF
from difffilter.filters.colored import ColoredNoiseUKF
from difffilter.filters.sigma_points import MerweScaled
from difffilter.selection import assign_parameters
from experiments.papers.p001 import p001_simulator, start_learner
from experiments.papers.smartloc import default_smartloc_path
from experiments.runner.experiment import run_experiment

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64
HAVE_SMARTLOC = (default_smartloc_path() / "Berlin_Potsdamer_Platz_Input.txt").exists()
needs_smartloc = pytest.mark.skipif(not HAVE_SMARTLOC, reason="smartLoc data folder ../shared/data/real not present")


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _sp() -> MerweScaled:
    return MerweScaled(alpha=1.0, beta=2.0, kappa=0.0)


# -- p001 -------------------------------------------------------------------------------------
def test_p001_simulator_layout_and_true_params() -> None:
    data = p001_simulator(batch_size=3, seed=5, dtype="float32", num_steps=12)
    assert data.measurements.shape == (3, 12, 7) and data.truth.shape == (3, 12, 8)
    assert data.mask.all() and data.measurements.dtype == torch.float32
    assert data.controls["sat_pos"].shape == (3, 12, 7, 3) and data.initial_cov.shape == (8, 8)
    tp = data.true_params
    assert tp["psi"] == pytest.approx(0.7) and tp["R"] == [9.0] * 7
    # the same seed gives the same trajectories; the random geometry differs per trajectory
    again = p001_simulator(batch_size=3, seed=5, dtype="float32", num_steps=12)
    assert torch.equal(again.measurements, data.measurements)
    rand = p001_simulator(batch_size=2, seed=1, randomize=True, num_steps=5)
    assert not torch.allclose(rand.controls["sat_pos"][0, 0], rand.controls["sat_pos"][1, 0])
    # make_model carries the truth's noise: R = 9 I, clock PSDs of the simulated receiver
    model = data.make_model()
    assert torch.allclose(model.measurement.R, 9.0 * torch.eye(7, dtype=torch.float32))
    assert float(model.dynamics.clock_bias_psd.detach()) == pytest.approx(0.01)


def test_p001_oracle_beats_white_noise_ukf() -> None:
    """The coloured UKF with the true Psi has a higher likelihood and a smaller error than the
    paper's white-noise UKF on the paper's geometry (64 x 100 epochs: differences >> noise)."""
    data = p001_simulator(batch_size=32, seed=2)
    model = data.make_model()
    run = lambda f: f(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask, controls=data.controls)  # noqa: E731
    with torch.no_grad():
        col = run(ColoredNoiseUKF(model, psi=0.7, sigma_points=_sp()))
        white = run(UKF(model, sigma_points=_sp()))
    rmse = lambda r: float((r.mean[..., :3] - data.truth[..., :3]).pow(2).sum(-1).mean().sqrt())  # noqa: E731
    assert float(col.log_likelihood.mean()) > float(white.log_likelihood.mean()) + 1.0
    assert rmse(col) < 0.98 * rmse(white)  # measured 6.00 vs 6.36 m


def test_start_learner_sets_the_start_values_on_the_learner_copy_only() -> None:
    model = p001_simulator(batch_size=1, seed=0, num_steps=3).make_model()
    hand = ColoredNoiseUKF(model, psi=0.7, sigma_points=_sp())
    learner = start_learner(copy.deepcopy(hand), "nll", start_params={"psi": 0.0}, learn=["psi", "R"])
    assert torch.allclose(learner.filter.psi, torch.zeros(7, dtype=F64))
    assert torch.allclose(hand.psi, torch.full((7,), 0.7, dtype=F64))
    plain = start_learner(copy.deepcopy(hand), "nll", start_params=None, learn=["psi"])
    assert torch.allclose(plain.filter.psi, hand.psi)


# -- smartLoc ---------------------------------------------------------------------------------
@needs_smartloc
def test_smartloc_windows_follow_the_segments() -> None:
    from experiments.papers.smartloc import smartloc_simulator

    segments = {
        "train": {"start": 0.0, "stop": 0.6, "length": 200, "stride": 50},
        "val": {"start": 0.0, "stop": 0.6, "length": None, "stride": None},
        "test": {"start": 0.6, "stop": 1.0, "length": None, "stride": None},
    }
    train = smartloc_simulator(batch_size=64, seed=0, segments=segments)
    test = smartloc_simulator(batch_size=64, seed=2, segments=segments, dtype="float32")
    assert train.start.tolist() == list(range(0, 601, 50)) and train.measurements.shape == (13, 200, 19)
    assert int(train.start.max()) + 200 <= 823 and test.start.tolist() == [823]
    assert test.measurements.shape == (1, 549, 19) and test.measurements.dtype == torch.float32
    assert torch.equal(train.truth[2].double(), train.data.truth_enu[100:300])
    assert train.initial_mean.shape == (13, 7) and train.initial_cov.shape == (13, 7, 7)
    assert bool((train.data.elevation[100:300][train.mask[2]] >= 15.0).all())
    capped = smartloc_simulator(batch_size=2, seed=0, segments=segments, num_steps=30)
    assert capped.measurements.shape == (2, 30, 19)
    with pytest.raises(ValueError, match="names no split"):
        smartloc_simulator(batch_size=1, seed=7, segments=segments)


@needs_smartloc
def test_shared_psi_and_snapshot_baseline() -> None:
    from experiments.papers.smartloc import SharedPsiColoredUKF, SnapshotWLS, single_epoch_wls, smartloc_model, smartloc_simulator

    model = smartloc_model()
    filt = SharedPsiColoredUKF(model, psi=0.3, sigma_points=_sp())
    assert filt.psi.shape == (19,) and torch.allclose(filt.psi, torch.full((19,), 0.3, dtype=F64))
    assign_parameters(filt, {"psi": 0.6})
    assert torch.allclose(filt.psi, torch.full((19,), 0.6, dtype=F64))
    assert filt.parametrizations.psi.original.shape == ()  # one raw scalar behind the 19 values
    with pytest.raises(ValueError):
        filt.psi = torch.linspace(0.1, 0.5, 19, dtype=F64)
    # shared Psi = 0 reproduces the plain UKF; the snapshot baseline reproduces single_epoch_wls
    seg = {"test": {"start": 300, "stop": 340}}
    data = smartloc_simulator(batch_size=1, seed=2, segments=seg)
    args = (data.measurements, data.initial_mean, data.initial_cov)
    with torch.no_grad():
        zero = SharedPsiColoredUKF(model, psi=0.0, sigma_points=_sp())(*args, mask=data.mask, controls=data.controls)
        ukf = UKF(model, sigma_points=_sp())(*args, mask=data.mask, controls=data.controls)
        snap = SnapshotWLS(model)(*args, mask=data.mask, controls=data.controls)
    assert torch.allclose(zero.mean, ukf.mean, atol=1e-6)
    ref = single_epoch_wls(data.data, robust="cauchy", threshold=1.5)
    assert torch.allclose(snap.mean[0, :, :3], ref.enu[300:340], atol=1e-6)
    assert torch.isnan(snap.log_likelihood).all() and (snap.num_observed > 4).all()
    assert torch.linalg.eigvalsh(snap.cov[0, :, :3, :3]).min() > 0


# -- the Hydra experiments (smoke size) -------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize(
    ("experiment", "rows", "extra"),
    [
        ("p001_colored", ["hand-tuned", "learned", "oracle", "standard-ukf", "white-ukf-stationary-R"], []),
        pytest.param(
            "smartloc_real",
            ["hand-tuned", "learned", "ekf-gated", "ekf-no-gate", "snapshot-wls"],
            ["pos_err_p50", "pos_err_p95"],
            marks=needs_smartloc,
        ),
    ],
)
def test_experiment_smoke(tmp_path: Path, experiment: str, rows: list[str], extra: list[str]) -> None:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                f"experiment={experiment}",
                "debug=smoke",
                f"paths.output_dir={tmp_path}",
                f"paths.log_dir={tmp_path}/logs",
            ],
        )
    out = run_experiment(cfg)
    with (tmp_path / "results.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert [r["filter"] for r in table] == rows
    for col in ["rmse_pos", "anees", "time_per_step_ms", *extra]:
        assert all(float(r[col]) > 0 for r in table), col
    assert out["metric"] == pytest.approx(float(table[1][cfg.experiment.metric]))
    md = (tmp_path / "results.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| filter |"))
    assert all(f" {c} " in header for c in ["rmse_pos", "anees", *extra])
    assert all(f"| {r} |" in md for r in rows)


@needs_smartloc
def test_constant_gate_keeps_estimates_and_drops_the_rejected_gradient() -> None:
    from experiments.papers.smartloc import SharedPsiColoredUKF, smartloc_model, smartloc_simulator

    seg = {"test": {"start": 650, "stop": 720}}  # inside the canyon: ranges get rejected
    data = smartloc_simulator(batch_size=1, seed=2, segments=seg)
    args = (data.measurements, data.initial_mean, data.initial_cov)
    out, grads = {}, {}
    for flag in (True, False):
        filt = SharedPsiColoredUKF(smartloc_model(gate_gradient=flag), psi=0.3, sigma_points=_sp())
        res = filt(*args, mask=data.mask, controls=data.controls)
        (-res.log_likelihood.sum()).backward()
        out[flag] = res
        grads[flag] = float(filt.model.measurement.parametrizations.noise_scale.original.grad)
    torch.testing.assert_close(out[False].mean, out[True].mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(out[False].log_likelihood, out[True].log_likelihood, rtol=0, atol=1e-9)
    # with gradients, each rejected range adds d/ds log(1e6 s var) / 2 > 0 to d(-log L)/ds, so
    # descent shrinks the scale; without them that push is gone (here the sign even flips)
    assert grads[True] > grads[False] + 1.0, grads
    with pytest.raises(ValueError, match="gate_gradient"):
        smartloc_model(gate_gradient=False, robust="huber")
    with pytest.raises(TypeError, match="gate_gradient"):
        smartloc_model(gate_gradient="no")


@needs_smartloc
def test_smartloc_learner_softens_the_gate_of_the_learned_copy_only() -> None:
    import copy

    from experiments.papers.smartloc import SharedPsiColoredUKF, smartloc_learner, smartloc_model

    hand = SharedPsiColoredUKF(smartloc_model(), psi=0.0, sigma_points=_sp())
    plain = smartloc_learner(copy.deepcopy(hand), "nll", learn=["psi", "noise_scale"])
    assert not plain.filter.model.measurement.soft_gate  # gate_softness=None: the model's (hard) gate
    learner = smartloc_learner(copy.deepcopy(hand), "nll", gate_softness=0.2, start_params={"psi": 0.1}, learn=["psi", "gate_softness"])
    meas = learner.filter.model.measurement
    assert meas.soft_gate and float(meas.gate_softness.detach()) == pytest.approx(0.2)
    assert meas.robust_gate.parametrizations.gate_softness.original.requires_grad  # the gate lives in robust_gate
    assert float(learner.filter.psi[0].detach()) == pytest.approx(0.1)
    assert not hand.model.measurement.soft_gate and float(hand.psi[0].detach()) == 0.0
    assert smartloc_model(gate_softness=0.0).measurement.soft_gate is False
    with pytest.raises(ValueError, match="gate_softness"):
        smartloc_model(gate_gradient=False, gate_softness=0.2)
    with pytest.raises(ValueError, match="gate_softness"):
        smartloc_learner(SharedPsiColoredUKF(smartloc_model(gate_gradient=False), sigma_points=_sp()), "nll", gate_softness=0.2)
