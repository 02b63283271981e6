"""The evaluation protocol (difffilter.evaluate.evaluation, .intervals, .replicates): per-run
metrics against direct numpy computations, the per-run CSV, paired block bootstrap and gap
closed against Monte Carlo, the seeded initial perturbation, and the replicate seeds."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from scipy import signal

from difffilter.evaluate import metrics as M  # noqa: N812 - short alias in formulas
from difffilter.evaluate.consistency import consistency
from difffilter.evaluate.evaluation import evaluate_runs, read_per_run, write_per_run
from difffilter.evaluate.intervals import block_bootstrap_difference, gap_closed
from difffilter.filters import KalmanFilter
from difffilter.learn.data import TrajectorySet
from difffilter.learn.replicates import perturb_initial_values, replicate_seed
from difffilter.mixers import IMM
from difffilter.models import LinearModel
from difffilter.params import Interval, ScaledMatrix, register_constrained
from difffilter.selection import select_parameters
from difffilter.sim.sampling import sample_trajectories
from experiments.runner.experiment import evaluate_filter, format_results
from tests.test_configs import CONF

f64 = torch.float64


def _cv_model(r: float = 4.0) -> LinearModel:
    F = torch.tensor([[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]], dtype=f64)
    q = 0.3 * torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1]], dtype=f64)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0]], dtype=f64)
    return LinearModel(F=F, H=H, Q=torch.block_diag(q, q), R=r * torch.eye(2, dtype=f64))


def _test_set(model: LinearModel, runs: int = 12, steps: int = 40) -> TrajectorySet:
    data = sample_trajectories(
        model,
        batch_size=runs,
        num_steps=steps,
        initial_mean=torch.zeros(4, dtype=f64),
        initial_cov=10 * torch.eye(4, dtype=f64),
        seed=3,
        missing_prob=0.1,
    )
    data.truth[2, :5, 0] = float("nan")  # a gap in one run's truth
    return TrajectorySet.from_simulation(data, f64)


# -- evaluate_runs ----------------------------------------------------------------------------------
def test_evaluate_runs_per_run_metrics_and_summary_match_direct_computation():
    model = _cv_model()
    data = _test_set(model)
    blocks = {"position": [0, 2], "velocity": [1, 3]}
    ev = evaluate_runs(KalmanFilter(model), data, batch_size=5, position_index=[0, 2], blocks=blocks)
    with torch.no_grad():
        res = KalmanFilter(model)(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask)
    truth, est = data.truth.numpy(), res.mean.numpy()
    valid = np.isfinite(truth).all(-1)
    sq = np.where(valid, ((est - np.nan_to_num(truth))[..., [0, 2]] ** 2).sum(-1), 0.0)
    mse = sq.sum(1) / valid.sum(1)
    np.testing.assert_allclose(ev.per_run["mse_pos"].numpy(), mse, rtol=1e-12)
    np.testing.assert_allclose(ev.per_run["rmse_pos"].numpy(), np.sqrt(mse), rtol=1e-12)
    ne = M.nees(res.mean, res.cov, data.truth).detach().numpy()
    np.testing.assert_allclose(ev.per_run["anees"].numpy(), np.nanmean(ne, 1), rtol=1e-12)
    for name, idx in blocks.items():
        nb = M.nees(res.mean, res.cov, data.truth, idx).detach().numpy()
        np.testing.assert_allclose(ev.per_run[f"nees_{name}"].numpy(), np.nanmean(nb, 1), rtol=1e-12)
        ref = consistency(torch.tensor(nb), 2.0)
        assert ev.summary[f"nees_{name}"] == pytest.approx(ref.mean, rel=1e-12)
        assert ev.summary[f"nees_{name}_run_ci_hi"] == pytest.approx(ref.run_ci.hi, rel=1e-12)
        assert ev.summary[f"nees_{name}_step_band_frac"] == ref.step_band_frac and ev.summary[f"nees_{name}_dof"] == 2.0
    obs = res.num_observed.numpy() > 0
    nis = np.where(obs, res.nis.detach().numpy(), np.nan)
    np.testing.assert_allclose(ev.per_run["nis"].numpy(), np.nanmean(nis, 1), rtol=1e-12)
    np.testing.assert_allclose(ev.per_run["nll"].numpy(), -res.log_likelihood.detach().numpy().sum(1) / obs.sum(1), rtol=1e-12)
    # summary: pooled rmse, run-level anees with its interval; no runs x steps band left
    assert ev.summary["rmse_pos"] == pytest.approx(math.sqrt(sq.sum() / valid.sum()), rel=1e-12)
    assert ev.summary["anees"] == pytest.approx(np.nanmean(np.nanmean(ne, 1)), rel=1e-12) and ev.summary["anees_dof"] == 4.0
    assert ev.summary["anees_run_ci_lo"] < ev.summary["anees"] < ev.summary["anees_run_ci_hi"]
    assert ev.summary["nis_dof"] == 2.0 and not {"anees_lo", "anees_hi", "nis_lo", "nis_hi"} & set(ev.summary)
    assert evaluate_filter(KalmanFilter(model), data, batch_size=5, position_index=[0, 2], blocks=blocks).keys() == ev.summary.keys()
    md = format_results([{"filter": "kf", **ev.summary}])
    assert (
        "| filter | NEES (all) | position | velocity | NIS |" in md
        and "(d = 2)" in md
        and "nees_position" not in md.split("Consistency")[0]
    )


def test_per_run_csv_round_trip(tmp_path):
    per_run = {
        "hand-tuned": {"rmse_pos": torch.tensor([1.0, 2.0, 3.0], dtype=f64), "anees": torch.tensor([4.0, math.nan, 1 / 3], dtype=f64)},
        "learned": {"rmse_pos": torch.tensor([0.5, 1.5, 2.5], dtype=f64)},
    }
    back = read_per_run(write_per_run(per_run, tmp_path / "per_run.csv"))
    assert back.keys() == per_run.keys() and back["learned"].keys() == {"rmse_pos"}
    for f, metrics in per_run.items():
        for k, v in metrics.items():
            torch.testing.assert_close(back[f][k], v, rtol=0, atol=0, equal_nan=True)
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="per-run"):
        read_per_run(tmp_path / "bad.csv")


# -- block bootstrap --------------------------------------------------------------------------------
def test_block_bootstrap_covers_ar1_mean_difference_where_single_steps_do_not():
    """Paired AR(1) error series (phi = 0.9, correlation time ~19 steps) with a true mean
    difference of 0.3: blocks of 100 steps cover it in ~95 % of 300 experiments (tolerance 4
    binomial s.e.), resampling single steps in far fewer."""
    rng = np.random.default_rng(7)
    reps, steps, phi = 300, 2000, 0.9
    cover = {1: 0, 100: 0}
    for k in range(reps):
        x = signal.lfilter([1.0], [1.0, -phi], rng.normal(size=(2, steps)), axis=1)  # x_t = phi x_{t-1} + w_t
        a, b = 1.3 + x[0], 1.0 + 0.5 * x[0] + x[1]
        for block in cover:
            iv = block_bootstrap_difference(torch.tensor(a), torch.tensor(b), statistic="mean", block=block, draws=400, seed=k)
            cover[block] += iv.contains(0.3)
    se = math.sqrt(0.95 * 0.05 / reps)
    assert abs(cover[100] / reps - 0.95) < 4 * se, cover
    assert cover[1] / reps < 0.7, cover
    with pytest.raises(ValueError, match="block"):
        block_bootstrap_difference(torch.zeros(5), torch.zeros(5), block=6)
    with pytest.raises(ValueError, match="paired"):
        block_bootstrap_difference(torch.zeros(5), torch.zeros(4), block=2)


def test_block_bootstrap_statistics_are_paired_differences():
    a = torch.tensor([3.0, 4.0, 0.0, 1.0], dtype=f64)
    b = torch.tensor([1.0, 1.0, 1.0, 1.0], dtype=f64)
    iv = block_bootstrap_difference(a, b, statistic="rms", block=4, draws=50)
    assert iv.estimate == pytest.approx(math.sqrt(26 / 4) - 1.0)
    # one block as long as the series: every resample is a rotation, same rms
    assert iv.lo == pytest.approx(iv.estimate) and iv.hi == pytest.approx(iv.estimate)
    med = block_bootstrap_difference(a, b, statistic="median", block=1, draws=50)
    assert med.estimate == float(a.median() - b.median())


# -- gap closed -------------------------------------------------------------------------------------
def test_gap_closed_value_interval_and_undefined_tie():
    rng = np.random.default_rng(8)
    n, s = 60, 5
    run = rng.normal(0, 1.0, n)  # shared run difficulty: pairing removes it
    hand = 10.0 + run + rng.normal(0, 0.2, n)
    oracle = 8.0 + run + rng.normal(0, 0.2, n)
    learned = 8.5 + run + rng.normal(0, 0.1, (s, 1)) + rng.normal(0, 0.2, (s, n))
    g = gap_closed(hand, learned, oracle, draws=2000)
    expected = (hand.mean() - learned.mean()) / (hand.mean() - oracle.mean())
    assert g.defined and g.value == pytest.approx(expected, rel=1e-12) and g.lo < g.value < g.hi
    assert g.lo > 0.6 and g.hi < 0.9  # true G = 0.75, a tight interval thanks to the pairing
    tie = gap_closed(hand, learned, hand + rng.normal(0, 0.05, n))
    assert not tie.defined and math.isnan(tie.value) and "ties" in tie.reason
    better = gap_closed(oracle, learned, hand)
    assert not better.defined and "better than the oracle" in better.reason
    with pytest.raises(ValueError, match="same runs"):
        gap_closed(hand, learned[:, :10], oracle)


def test_gap_closed_interval_coverage_monte_carlo():
    # true G = 0.5; 200 experiments of 40 runs x 5 seeds (tolerance: 4 binomial s.e.)
    rng = np.random.default_rng(9)
    reps, n, s = 200, 40, 5
    hits = 0
    for k in range(reps):
        run = rng.normal(0, 1.0, n)
        hand = 2.0 + run + rng.normal(0, 0.3, n)
        oracle = 1.0 + run + rng.normal(0, 0.3, n)
        learned = 1.5 + run + rng.normal(0, 0.1, (s, 1)) + rng.normal(0, 0.3, (s, n))
        g = gap_closed(hand, learned, oracle, draws=500, seed=k)
        hits += g.lo <= 0.5 <= g.hi
    se = math.sqrt(0.95 * 0.05 / reps)
    assert abs(hits / reps - 0.95) < 4 * se, hits


# -- replicates -------------------------------------------------------------------------------------
class _Toy(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.model = _cv_model()
        register_constrained(self, "tau", torch.tensor([10.0, 100.0], dtype=f64), Interval(1.0, 1e3))
        register_constrained(self, "S", torch.eye(2, dtype=f64) * 2.0, ScaledMatrix(torch.eye(2, dtype=f64)))


def test_perturb_initial_values_is_seeded_log_scale_and_keeps_constraints():
    toy = _Toy()
    names = select_parameters(toy, ["Q", "R", "tau", "S"])
    before = {n: v.clone() for n, v in {"Q": toy.model.Q, "R": toy.model.R, "tau": toy.tau, "S": toy.S}.items()}
    assert perturb_initial_values(toy, names, 0.0, seed=1) == {}
    assert torch.equal(toy.model.R, before["R"])
    new = perturb_initial_values(toy, names, 0.3, seed=1)
    again = _Toy()
    perturb_initial_values(again, names, 0.3, seed=1)
    assert torch.equal(again.model.Q, toy.model.Q) and torch.equal(again.tau, toy.tau)
    # covariances: each variance scaled, correlations kept, still positive definite
    q0, q1 = before["Q"], toy.model.Q
    corr = lambda c: c / torch.sqrt(torch.diagonal(c)[:, None] * torch.diagonal(c)[None, :])  # noqa: E731
    torch.testing.assert_close(corr(q1), corr(q0))
    assert bool((torch.linalg.eigvalsh(q1) > 0).all()) and not torch.allclose(q1, q0)
    assert bool((toy.tau >= 1.0).all() and (toy.tau <= 1e3).all())
    # a ScaledMatrix can only take a common factor
    factor = (toy.S[0, 0] / before["S"][0, 0]).detach()
    torch.testing.assert_close(toy.S, factor * before["S"])
    assert abs(float(factor) - 1.0) > 1e-6
    assert set(new) == set(names)
    with pytest.raises(ValueError, match="init_perturbation"):
        perturb_initial_values(toy, names, -1.0, seed=0)


def test_perturbation_factors_are_log_normal_with_the_given_sigma():
    model = LinearModel(
        F=torch.eye(400, dtype=f64),
        H=torch.eye(400, dtype=f64),
        Q=torch.eye(400, dtype=f64),
        R=torch.eye(400, dtype=f64),
        Q_structure="diagonal",
    )
    names = select_parameters(model, ["Q"])
    perturb_initial_values(model, names, 0.5, seed=3)
    logs = torch.log(torch.diagonal(model.Q)).detach()
    # 400 draws of N(0, 0.5^2): mean within 4 s.e., std within 4 s.e. (s.e. of a std ~ sigma / sqrt(2 n))
    assert abs(float(logs.mean())) < 4 * 0.5 / 20 and abs(float(logs.std()) - 0.5) < 4 * 0.5 / math.sqrt(800)


def test_perturbation_reaches_imm_transition_rows():
    imm = IMM(
        [KalmanFilter(_cv_model()), KalmanFilter(_cv_model(9.0))],
        transition=torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=f64),
        initial_probs=torch.tensor([0.5, 0.5], dtype=f64),
    )
    names = select_parameters(imm, ["transition"])
    perturb_initial_values(imm, names, 0.4, seed=0)
    torch.testing.assert_close(imm.transition.sum(-1), torch.ones(2, dtype=f64))
    assert not torch.allclose(imm.transition, torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=f64))


def test_seed_drives_train_and_val_data_but_not_the_test_set(tmp_path):
    assert replicate_seed(0, 0) == 0 and replicate_seed(0, 1) == 1 and replicate_seed(3, 1) == 3001
    with pytest.raises(ValueError, match="seed"):
        replicate_seed(-1, 0)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for seed, train, val in ((0, 0, 1), (4, 4000, 4001)):
            for experiment in ("singer2d", "p002_pdr", "p003_imm_sins"):
                cfg = compose("train", overrides=[f"seed={seed}", f"experiment={experiment}", f"paths.output_dir={tmp_path}"])
                seeds = OmegaConf.to_container(cfg.data.seeds, resolve=True)
                assert seeds == {"train": train, "val": val, "test": 2}, (experiment, seeds)
                # p002's overlay perturbs the learned start (0.1 log-scale: seeds vary data and start); others do not
                expected_perturbation = 0.1 if experiment == "p002_pdr" else 0.0
                assert cfg.learner.init_seed == seed and cfg.learner.init_perturbation == expected_perturbation


def test_a_perturbed_start_past_its_bound_is_folded_back_inside_without_a_warning():
    """A log-scale start pushed past its bound is mirrored back inside (no longer clamped next to the
    bound, so no RuntimeWarning); Bounded ones take a logit step (tests/test_replicates_bounded.py)."""
    toy = _Toy()  # tau = [10, 100] in Interval(1, 1e3)
    names = select_parameters(toy, ["tau"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a start well inside the bounds: no warning
        perturb_initial_values(toy, names, 0.01, seed=0)
    far = _Toy()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        perturb_initial_values(far, names, 50.0, seed=0)  # exp(50 z) leaves [1, 1e3] for any |z| > 0.14
    assert bool((far.tau > 1.0).all() and (far.tau < 1e3).all())
    assert not bool(((far.tau - 1.0).abs() < 1e-5).any() or ((far.tau - 1e3).abs() < 1e-2).any())  # not clamped at a bound
