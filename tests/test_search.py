"""Validation search: finds a known optimum, reports every candidate and its cost, is
deterministic, restores or applies values as asked, and refuses bad knobs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.filters import KalmanFilter
from difffilter.learn import grid_search, log_grid, random_search, validation_loss
from difffilter.models import LinearModel
from difffilter.sim import simulate

F64 = torch.float64


def model(q=1.0, r=1.0, **kw):
    return LinearModel(
        F=torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64), H=torch.tensor([[1.0, 0.0]], dtype=F64),
        Q=q * torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1.0]], dtype=F64), R=torch.tensor([[r]], dtype=F64), **kw,
    )  # fmt: skip


def test_log_grid():
    g = log_grid(0.01, 100.0, 5)
    np.testing.assert_allclose(g, [0.01, 0.1, 1.0, 10.0, 100.0], rtol=1e-12)
    assert log_grid(2.0, 5.0, 1) == [2.0]
    with pytest.raises(ValueError, match="low, high"):
        log_grid(0.0, 1.0, 3)


def test_grid_search_finds_the_known_optimum_of_a_synthetic_score():
    kf = KalmanFilter(model())

    def score(f):  # minimum 0 at R = 4, Q = 0.25 I (a scalar sets s I)
        r, q = float(f.model.R[0, 0]), float(f.model.Q[0, 0])
        return math.log(r / 4.0) ** 2 + math.log(q / 0.25) ** 2

    res = grid_search(kf, {"R": log_grid(0.25, 64.0, 9), "Q": log_grid(1 / 64, 4.0, 9)}, score)
    assert res.best == pytest.approx({"R": 4.0, "Q": 0.25}, rel=1e-12)
    assert res.best_score == pytest.approx(0.0, abs=1e-20)
    assert len(res.table) == 81 and all(set(row) == {"R", "Q", "score"} for row in res.table)
    assert res.table[0] == pytest.approx({"R": 0.25, "Q": 1 / 64, "score": score_of(0.25, 1 / 64)})
    assert res.cpu_seconds > 0 and res.method == "grid"
    torch.testing.assert_close(kf.model.R, torch.tensor([[4.0]], dtype=F64))  # best applied
    torch.testing.assert_close(res.values["model.measurement.R"], torch.tensor([[4.0]], dtype=F64))


def score_of(r, q):
    return math.log(r / 4.0) ** 2 + math.log(q / 0.25) ** 2


def test_grid_search_on_validation_nll_matches_brute_force():
    truth = model(q=0.05, r=4.0)
    val = simulate(truth, num_steps=60, batch_size=4, initial_mean=torch.zeros(2, dtype=F64), initial_cov=torch.eye(2, dtype=F64), seed=1)
    score = validation_loss(val.measurements, val.initial_mean, val.initial_cov, kind="nll")
    grid = log_grid(0.25, 64.0, 9)
    kf = KalmanFilter(model(q=0.05, r=1.0))
    res = grid_search(kf, {"R": grid}, score)
    # brute force, written out: the per-step NLL of a Kalman filter for each R
    brute = []
    for r in grid:
        with torch.no_grad():
            res_r = KalmanFilter(model(q=0.05, r=r))(val.measurements, val.initial_mean, val.initial_cov)
        brute.append(float(-res_r.log_likelihood.sum() / res_r.log_likelihood.numel()))
    np.testing.assert_allclose([row["score"] for row in res.table], brute, rtol=1e-12)
    assert res.best["R"] == grid[int(np.argmin(brute))]
    assert 2.0 <= res.best["R"] <= 8.0  # the simulating R = 4 lies within one grid step of the best


def test_rmse_score_and_relative_knob_keep_shape():
    truth = model(q=0.05, r=4.0)
    val = simulate(truth, num_steps=60, batch_size=3, initial_mean=torch.zeros(2, dtype=F64), initial_cov=torch.eye(2, dtype=F64), seed=2)
    score = validation_loss(val.measurements, val.initial_mean, val.initial_cov, truth=val.truth, index=[0])
    kf = KalmanFilter(model(q=1.0, r=4.0))
    q0 = kf.model.Q.detach().clone()
    res = grid_search(kf, {"Q": log_grid(1e-3, 1.0, 7)}, score, relative=True)
    torch.testing.assert_close(kf.model.Q.detach(), q0 * res.best["Q"])  # the shape of Q kept
    assert res.best["Q"] < 1.0  # Q_0 is 20x the truth: a smaller multiple filters better


def test_searches_are_deterministic_and_can_leave_the_filter_unchanged():
    kf = KalmanFilter(model())
    r0 = kf.model.R.detach().clone()

    def score(f):
        return (math.log(float(f.model.R[0, 0])) - 1.0) ** 2

    a = random_search(kf, {"R": (0.1, 100.0)}, score, num_samples=12, seed=3, apply_best=False)
    b = random_search(kf, {"R": (0.1, 100.0)}, score, num_samples=12, seed=3, apply_best=False)
    c = random_search(kf, {"R": (0.1, 100.0)}, score, num_samples=12, seed=4, apply_best=False)
    assert a.table == b.table and a.table != c.table and a.method == "random"
    assert all(0.1 <= row["R"] <= 100.0 for row in a.table) and len(a.table) == 12
    assert a.best_score == min(row["score"] for row in a.table)
    torch.testing.assert_close(kf.model.R.detach(), r0)


def test_bad_knobs_raise():
    kf = KalmanFilter(model())
    with pytest.raises(ValueError, match="knobs"):
        grid_search(kf, {"not_a_parameter": [1.0]}, lambda f: 0.0)
    with pytest.raises(ValueError, match="knobs"):
        grid_search(kf, {}, lambda f: 0.0)
    with pytest.raises(ValueError, match="grid"):
        grid_search(kf, {"R": []}, lambda f: 0.0)
    with pytest.raises(ValueError, match="bounds"):
        random_search(kf, {"R": (2.0, 1.0)}, lambda f: 0.0)
    with pytest.raises(ValueError, match="kind"):
        validation_loss(torch.zeros(1, 2, 1), torch.zeros(2), torch.eye(2), kind="mae")
    with pytest.raises(ValueError, match="truth"):
        validation_loss(torch.zeros(1, 2, 1), torch.zeros(2), torch.eye(2), kind="rmse")


def test_grid_of_whole_values_sets_each_transition_matrix_and_matches_brute_force():
    """A nested-list grid value (an IMM's transition matrix per candidate) is set as given, also
    beside a relative numeric knob; the best candidate is the brute-force argmin of the score."""
    from difffilter.mixers import IMM

    start = {"initial_mean": torch.zeros(2, dtype=F64), "initial_cov": torch.eye(2, dtype=F64)}
    data = simulate(model(q=0.05, r=4.0), num_steps=20, batch_size=2, seed=2, **start)

    def imm():
        modes = [KalmanFilter(model(q=0.01, r=4.0)), KalmanFilter(model(q=1.0, r=4.0))]
        return IMM(modes, transition=torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=F64), initial_probs=torch.tensor([0.5, 0.5], dtype=F64))

    score = validation_loss(data.measurements, data.initial_mean, data.initial_cov, kind="nll")
    pis = [[[0.99, 0.01], [0.5, 0.5]], [[0.9, 0.1], [0.1, 0.9]], [[0.6, 0.4], [0.3, 0.7]]]
    scales = [0.5, 2.0]
    filt = imm()
    res = grid_search(filt, {"filters.1.model.dynamics.Q": scales, "transition": pis}, score, relative=True)
    brute = {}
    for s in scales:
        for k, pi in enumerate(pis):
            ref = imm()
            with torch.no_grad():
                ref.filters[1].model.dynamics.Q = s * ref.filters[1].model.dynamics.Q
            ref.transition = torch.tensor(pi, dtype=F64)
            brute[(s, k)] = score(ref)
    s_best, k_best = min(brute, key=brute.__getitem__)
    assert res.best["filters.1.model.dynamics.Q"] == s_best and res.best["transition"] == pis[k_best]
    assert res.best_score == pytest.approx(brute[(s_best, k_best)], rel=1e-12)
    assert [row["score"] for row in res.table] == pytest.approx([brute[(s, k)] for s in scales for k in range(3)], rel=1e-12)
    torch.testing.assert_close(filt.transition, torch.tensor(pis[k_best], dtype=F64), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(filt.filters[0].model.dynamics.Q, imm().filters[0].model.dynamics.Q)  # only the named mode moved
    with pytest.raises(ValueError, match="finite numbers"):
        grid_search(imm(), {"transition": [[[float("nan"), 1.0], [0.5, 0.5]]]}, score)
