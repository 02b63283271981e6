"""p002 (GPS+PDR, RC-UKF) and p003 (IMM of simplified UKFs) experiments: the support modules
(fast) and `experiments/train.py experiment=... debug=smoke` end to end (slow)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from experiments.papers.p002 import (
    EstimatorBaseline,
    gps_only_estimate,
    gps_only_positions,
    pdr_model,
    pdr_only_estimate,
    pdr_only_positions,
    simulate_p002,
)
from experiments.papers.p003 import PAPER_PHASES, empirical_transition, model_options, p003_imm, p003_mode_model
from tests.smoke_helpers import read_rows, run_train_smoke

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64


@pytest.mark.parametrize("kind", ["gps", "pdr"])
def test_estimator_baseline_reproduces_the_simulator_rows(kind):
    sc = simulate_p002(3, blockage_prob=0.6, seed=5, num_steps=80)
    est = gps_only_estimate if kind == "gps" else pdr_only_estimate
    filt = EstimatorBaseline(pdr_model(Q_std=[0.06, 0.06, 0.01, 0.5], R_std=[2.67, 2.67, 11.4]), estimator=est)
    res = filt(sc.measurements, sc.initial_mean, sc.initial_cov, mask=sc.mask, controls=sc.controls)
    expected = gps_only_positions(sc) if kind == "gps" else pdr_only_positions(sc)[0]
    torch.testing.assert_close(res.mean[..., :2], expected)
    assert res.cov.shape == (3, 80, 4, 4)
    assert bool((torch.diagonal(res.cov, dim1=-2, dim2=-1) > 0).all())
    assert bool(torch.isnan(res.log_likelihood).all()) and bool(torch.isnan(res.nis).all())
    assert torch.equal(res.num_observed, sc.mask.sum(-1))
    with pytest.raises(ValueError, match="belief"):
        filt(sc.measurements, mask=sc.mask, controls=sc.controls, belief={"mean": sc.initial_mean, "cov": sc.initial_cov})


def test_gps_only_nominal_variance_grows_between_fixes():
    sc = simulate_p002(2, blockage_prob=0.8, seed=1, num_steps=120)
    mean, var = gps_only_estimate(
        measurements=torch.nan_to_num(sc.measurements),
        mask=sc.mask,
        controls=sc.controls,
        initial_mean=sc.initial_mean,
        initial_cov=sc.initial_cov,
    )
    ok = sc.mask[..., 0]
    after_fix = ok.cummax(1).values
    # at a fix the variance is the GPS variance; one step later it is larger by (L0)^2 / 2
    fix_var = var[..., 0][ok]
    torch.testing.assert_close(fix_var, torch.full_like(fix_var, 2.67**2))
    b, t = (ok[:, :-1] & ~ok[:, 1:] & after_fix[:, :-1]).nonzero()[0].tolist()
    torch.testing.assert_close(var[b, t + 1, 0], torch.tensor(2.67**2, dtype=f64) + 0.5 * sc.initial_mean[b, 2] ** 2)


def test_pdr_model_from_standard_deviations():
    m = pdr_model(Q_std=[0.1, 0.2, 0.01, 2.0], R_std=[3.0, 4.0, 10.0])
    torch.testing.assert_close(torch.diagonal(m.Q), torch.tensor([0.01, 0.04, 1e-4, math.radians(2.0) ** 2], dtype=f64))
    torch.testing.assert_close(torch.diagonal(m.R), torch.tensor([9.0, 16.0, math.radians(10.0) ** 2], dtype=f64))


def test_empirical_transition_of_the_paper_profile():
    # 7 manoeuvres of 10 + 30 + 10 + 20 + 20 + 20 + 15 = 125 s; the flight ends level, so 1674 of
    # the 1675 level steps have a successor.
    pi = np.array(empirical_transition(PAPER_PHASES, 1800.0))
    np.testing.assert_allclose(pi, [[1 - 7 / 1674, 7 / 1674], [7 / 125, 1 - 7 / 125]], rtol=1e-12)


def test_mode_models_scale_the_specification():
    spec = p003_mode_model()
    high = p003_mode_model(q_scale=1e4, r_scale=100.0)
    white = p003_mode_model(q_scale=1e4, r_scale=100.0, white_only=True)
    q0, q1, qw = (torch.diagonal(m.dynamics.Q) for m in (spec, high, white))
    torch.testing.assert_close(q1, 1e4 * q0)
    torch.testing.assert_close(qw[3:9], 1e4 * q0[3:9])
    torch.testing.assert_close(qw[:3], q0[:3])
    torch.testing.assert_close(qw[9:], q0[9:])
    torch.testing.assert_close(high.measurement.R, 100.0 * spec.measurement.R)
    torch.testing.assert_close(white.measurement.R, 100.0 * spec.measurement.R)
    imm = p003_imm(filter="standard", transition="paper")
    torch.testing.assert_close(imm.transition, torch.tensor(empirical_transition(), dtype=f64), rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="simplified"):
        p003_imm(filter="cubature")


def test_model_options_from_a_template_or_a_mapping():
    opts = {"num_satellites": 5, "linearized": True, "position_in_metres": False, "discretization": "first"}
    template = p003_mode_model(q_scale=3.0, **opts)
    assert model_options(template) == opts
    assert model_options({"_target_": "x", "q_scale": 2.0, "dtype": "float64", **opts}) == opts
    imm = p003_imm(model=template)
    assert imm.filters[0].model.measurement.num_satellites == 5 and imm.filters[1].model.dynamics.discretization == "first"
    # the template's noise level is not an option: mode 0 is the specification
    torch.testing.assert_close(imm.filters[0].model.dynamics.Q, p003_mode_model(**opts).dynamics.Q)
    with pytest.raises(TypeError, match="SINS"):
        model_options(pdr_model(Q_std=[0.06, 0.06, 0.01, 0.5], R_std=[2.67, 2.67, 11.4]))


def test_group_scaled_covariance():
    from difffilter.params import GroupScaledCovariance

    base = torch.tensor([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 3.0]], dtype=f64)
    groups = torch.tensor([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=f64)
    c = GroupScaledCovariance(base, groups)
    torch.testing.assert_close(c(torch.zeros(2, dtype=f64)), base)
    raw = torch.tensor([math.log(100.0), math.log(0.5)], dtype=f64)
    want = base.clone()
    want[:2, :2] *= 100.0
    want[2, 2] *= 0.5
    torch.testing.assert_close(c(raw), want)  # off-diagonal terms inside a group scale with it
    torch.testing.assert_close(c.right_inverse(want), raw)
    torch.testing.assert_close(c.right_inverse(torch.tensor(7.0, dtype=f64)), torch.full((2,), math.log(7.0), dtype=f64))
    with pytest.raises(ValueError, match="one positive scale per group"):
        c.right_inverse(torch.eye(3, dtype=f64))
    with pytest.raises(ValueError, match="exactly one group"):
        GroupScaledCovariance(base, torch.ones(2, 3, dtype=f64))
    with pytest.raises(ValueError, match="positive"):
        c.right_inverse(torch.tensor(-1.0, dtype=f64))


def test_p003_learner_splits_q_of_the_learned_copy_only():
    import copy

    from experiments.papers.p003 import learned_from_state, p003_learner

    hand = p003_imm(model={"num_satellites": 4})
    q_hand = [f.model.dynamics.Q.detach().clone() for f in hand.filters]
    plain = p003_learner(copy.deepcopy(hand), "nll", learn=["Q", "R", "transition"])
    assert plain.filter.filters[1].model.dynamics.parametrizations.Q.original.shape == ()
    learner = p003_learner(copy.deepcopy(hand), "nll", q_groups="imu_white", learn=["Q", "R", "transition"])
    dyn = learner.filter.filters[1].model.dynamics
    assert dyn.parametrizations.Q.original.shape == (2,)
    torch.testing.assert_close(dyn.Q, q_hand[1])
    with torch.no_grad():
        dyn.parametrizations.Q.original.copy_(torch.tensor([0.0, math.log(1e-4)], dtype=f64))
    q = torch.diagonal(dyn.Q)
    torch.testing.assert_close(q[3:9], torch.diagonal(q_hand[1])[3:9])  # IMU white noises kept
    torch.testing.assert_close(q[9:], 1e-4 * torch.diagonal(q_hand[1])[9:])  # the rest scaled
    for f, q0 in zip(hand.filters, q_hand, strict=True):  # the hand-tuned filter is untouched
        torch.testing.assert_close(f.model.dynamics.Q, q0)
    # the report rebuilds the learned IMM from a checkpoint of this layout
    state = {f"filter.{k}": v for k, v in learner.filter.state_dict().items()}
    rebuilt = learned_from_state(hand, state, "imu_white")
    torch.testing.assert_close(rebuilt.filters[1].model.dynamics.Q, dyn.Q)
    with pytest.raises(ValueError, match="q_groups"):
        p003_learner(copy.deepcopy(hand), "nll", q_groups="all")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("experiment", "expected"),
    [
        ("p002_pdr", ["hand-tuned", "learned", "UKF", "GPS only", "PDR only"]),
        ("p003_imm_sins", ["hand-tuned", "learned", "oracle"]),
        ("p003_modes", ["hand-tuned", "learned", "oracle"]),
        ("p003_physical", ["hand-tuned", "learned"]),
    ],
)
def test_experiment_smoke(tmp_path, experiment, expected):
    rows, md = run_train_smoke(tmp_path, experiment)
    assert [r["filter"] for r in rows] == expected
    for r in rows:
        assert float(r["rmse_pos"]) > 0 and math.isfinite(float(r["rmse_pos"])), r
        assert math.isfinite(float(r["anees"])) and float(r["time_per_step_ms"]) > 0, r
    assert "| hand-tuned |" in md and "| learned |" in md
    if experiment == "p002_pdr":
        # the non-filter baselines have no innovation likelihood
        assert all(math.isnan(float(r["nll"])) for r in rows if r["filter"] in ("GPS only", "PDR only"))
        return
    from experiments.papers.p003 import paper_profile_report

    per_run = read_rows(tmp_path / "per_run.csv")
    assert {"rmse_velocity", "rmse_attitude", "nees_clock"} <= set(per_run[0])
    # the cross-family test on the paper's profile and the switching table, from the run's checkpoint
    md_path = paper_profile_report(tmp_path, out_dir=tmp_path / "paper", runs=3, duration=40)
    switch = read_rows(tmp_path / "paper" / "switching.csv")
    imms = ["hand-tuned", "IMM standard UKF"] + (["oracle"] if experiment == "p003_modes" else []) + ["learned"]
    assert [r["filter"] for r in switch] == imms
    assert "p003" in md_path.read_text() and (tmp_path / "paper" / "summary_rmse_velocity.md").exists()
    paired = read_rows(next((tmp_path / "paper").rglob("per_run.csv")))
    assert {r["filter"] for r in paired} == set(expected) | {"IMM standard UKF"} and len(paired) == 3 * (len(expected) + 1)
