"""Metrics of difffilter.evaluate.metrics against independent references (numpy, scipy,
Monte-Carlo statistics with tolerances from the sample size)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch
from scipy import stats

from difffilter.evaluate import metrics as M  # noqa: N812 - short alias in formulas
from difffilter.evaluate.consistency import consistency, nis_per_step
from difffilter.filters import KalmanFilter
from difffilter.filters.base import FilterResult
from difffilter.models import LinearModel
from difffilter.sim import sample_trajectories

f64 = torch.float64


def _result(mean, cov, nis=None, ll=None, nobs=None) -> FilterResult:
    b, t = mean.shape[:2]
    z = torch.zeros(b, t, dtype=mean.dtype)
    return FilterResult(mean, cov, mean, cov, z if ll is None else ll, z if nis is None else nis, z + 2 if nobs is None else nobs, {})


# -- chi-square bounds ---------------------------------------------------------------------------
@pytest.mark.parametrize("dof", [10.0, 40.0, 400.0, 6000.0])
@pytest.mark.parametrize("prob", [0.025, 0.5, 0.975])
def test_chi2_quantile_matches_scipy_and_wilson_hilferty(dof, prob):
    ref = stats.chi2.ppf(prob, dof)
    assert M.chi2_quantile(prob, dof) == pytest.approx(ref, rel=1e-12)
    assert M.wilson_hilferty(prob, dof) == pytest.approx(ref, rel=0.08 / dof)


def test_chi2_quantile_falls_back_without_scipy(monkeypatch):
    monkeypatch.setitem(sys.modules, "scipy.stats", None)  # import raises ImportError
    assert M.chi2_quantile(0.975, 200.0) == M.wilson_hilferty(0.975, 200.0)
    assert M.chi2_quantile(0.975, 200.0) == pytest.approx(stats.chi2.ppf(0.975, 200.0), rel=1e-3)


def test_chi2_interval_coverage_monte_carlo():
    # Averages of N chi2(d) variables fall inside the 95 % interval 95 % of the time.
    rng = np.random.default_rng(0)
    d, n, runs = 4, 50, 4000
    lo, hi = M.chi2_interval(d, n)
    avg = rng.chisquare(d, size=(runs, n)).mean(1)
    inside = float(((avg >= lo) & (avg <= hi)).mean())
    assert abs(inside - 0.95) < 4 * math.sqrt(0.95 * 0.05 / runs)
    assert lo < d < hi


# -- errors --------------------------------------------------------------------------------------
def test_rmse_matches_numpy_with_indices_and_nan_truth():
    g = torch.Generator().manual_seed(1)
    est = torch.randn(3, 7, 5, generator=g, dtype=f64)
    truth = torch.randn(3, 7, 4, generator=g, dtype=f64)
    truth[1, 2, 0] = float("nan")
    e, t = est.numpy()[..., [0, 3]], truth.numpy()[..., [1, 2]]
    ok = np.isfinite(t).all(-1)
    ref = math.sqrt(((e - t) ** 2).sum(-1)[ok].mean())
    assert float(M.rmse(est, truth, [0, 3], [1, 2])) == pytest.approx(ref, rel=1e-12)
    per = M.rmse(est, truth, [0, 3], [1, 2], per_component=True)
    ref_per = np.sqrt(np.where(ok[..., None], (e - np.nan_to_num(t)) ** 2, 0).sum((0, 1)) / ok.sum())
    np.testing.assert_allclose(per.numpy(), ref_per, rtol=1e-12)
    with pytest.raises(ValueError, match="truth_index"):
        M.rmse(est, truth)  # 5 estimate vs 4 truth components


def test_nees_matches_solve_on_sub_block():
    g = torch.Generator().manual_seed(2)
    a = torch.randn(2, 5, 4, 4, generator=g, dtype=f64)
    cov = a @ a.mT + 0.5 * torch.eye(4, dtype=f64)
    mean = torch.randn(2, 5, 4, generator=g, dtype=f64)
    truth = torch.randn(2, 5, 4, generator=g, dtype=f64)
    got = M.nees(mean, cov, truth, [1, 3])
    e = (mean - truth)[..., [1, 3]].numpy()
    p = cov[..., [1, 3], :][..., [1, 3]].numpy()
    ref = np.einsum("bti,bti->bt", e, np.linalg.solve(p, e[..., None])[..., 0])
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-10)


def test_nees_of_gaussian_errors_is_consistent():
    # Errors drawn from N(0, P): average NEES ~ chi2(N n)/N, inside the 95 % bounds.
    g = torch.Generator().manual_seed(3)
    b, t, n = 40, 50, 3
    a = torch.randn(b, t, n, n, generator=g, dtype=f64)
    cov = a @ a.mT + torch.eye(n, dtype=f64)
    err = (torch.linalg.cholesky(cov) @ torch.randn(b, t, n, 1, generator=g, dtype=f64))[..., 0]
    value = float(M.anees(M.nees(err, cov, torch.zeros_like(err))))
    lo, hi = M.chi2_interval(n, b * t)
    assert lo < value < hi


def test_anis_nll_and_metric_sums_are_additive():
    g = torch.Generator().manual_seed(4)
    mean = torch.randn(4, 6, 2, generator=g, dtype=f64)
    cov = torch.eye(2, dtype=f64).expand(4, 6, 2, 2)
    nis = torch.rand(4, 6, generator=g, dtype=f64) * 3
    ll = -torch.rand(4, 6, generator=g, dtype=f64)
    nobs = torch.full((4, 6), 2.0, dtype=f64)
    nobs[0, :3] = 0
    nis[0, :3] = 0
    ll[0, :3] = 0
    res = _result(mean, cov, nis, ll, nobs)
    truth = torch.randn(4, 6, 2, generator=g, dtype=f64)
    assert float(M.anis(res)) == pytest.approx(float(nis.sum() / 21), rel=1e-12)
    np.testing.assert_allclose(M.nll_per_step(res).numpy(), (-ll.sum(-1) / torch.tensor([3.0, 6, 6, 6], dtype=f64)).numpy())
    whole = M.metric_sums(res, truth)
    halves = [M.metric_sums(_result(mean[s], cov[s], nis[s], ll[s], nobs[s]), truth[s]) for s in (slice(0, 2), slice(2, 4))]
    summed = {k: halves[0][k] + halves[1][k] for k in whole}
    a, b = M.finalize_metrics(whole), M.finalize_metrics(summed)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-12)
    assert a["rmse_pos"] == pytest.approx(float(M.rmse(mean, truth)), rel=1e-12)
    assert a["nis"] == pytest.approx(float(M.anis(res)), rel=1e-12)


def test_oracle_kalman_filter_is_consistent_on_in_family_data():
    # Integration: sampler + KF + metrics; the true-parameter KF passes the consistency verdicts
    # (run-level 95 % t-interval covers d, most steps inside the per-step chi-square band over
    # runs) for NEES and NIS, with missing measurements; a wrong R moves NIS out.  (The runs x
    # steps chi2(d B T)/(B T) band this test used to check treats correlated steps as independent.)
    dt = 1.0
    F = torch.tensor([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]], dtype=f64)
    q = 0.3 * torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=f64)
    Q = torch.block_diag(q, q)
    H = torch.tensor([[1.0, 0, 0, 0], [0, 0, 1, 0]], dtype=f64)
    model = LinearModel(F=F, H=H, Q=Q, R=4.0 * torch.eye(2, dtype=f64))
    data = sample_trajectories(
        model,
        batch_size=40,
        num_steps=60,
        initial_mean=torch.zeros(4, dtype=f64),
        initial_cov=torch.eye(4, dtype=f64) * 10,
        seed=5,
        missing_prob=0.1,
    )
    res = KalmanFilter(model)(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask)
    ne = M.nees(res.mean, res.cov, data.truth).detach()
    nis, nis_dof = nis_per_step(res)
    good = consistency(ne, 4.0), consistency(nis, nis_dof)
    assert all(c.consistent for c in good) and all(c.step_band_frac > 0.85 for c in good)
    assert good[0].dof == 4.0 and good[1].dof == 2.0
    assert good[0].mean == pytest.approx(float(M.anees(ne)), rel=1e-12)  # every run has a truth at every step
    model.R = 25.0 * torch.eye(2, dtype=f64)
    res = KalmanFilter(model)(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask)
    bad = consistency(*nis_per_step(res))
    assert bad.run_ci.hi < 2.0 and bad.step_band_frac < 0.5  # innovations far smaller than claimed


# -- whiteness -----------------------------------------------------------------------------------
def test_whiteness_of_white_noise_and_ar1():
    g = torch.Generator().manual_seed(6)
    white = torch.randn(20, 300, 2, generator=g, dtype=f64)
    w = M.innovation_whiteness(white, max_lag=20)
    # 20 lags x 5 % expected outside; 6 or more would be a > 3-sigma binomial excursion.
    assert w.fraction_outside <= 5 / 20
    assert bool((w.bound > 0).all()) and float(w.bound[0]) == pytest.approx(1.96 / math.sqrt(20 * 299 * 2), rel=0.1)
    phi = 0.5
    ar = torch.zeros_like(white)
    for t in range(1, white.shape[1]):
        ar[:, t] = phi * ar[:, t - 1] + white[:, t]
    w = M.innovation_whiteness(ar, max_lag=3)
    assert float(w.rho[0]) == pytest.approx(phi, abs=0.03)
    assert float(w.rho[1]) == pytest.approx(phi**2, abs=0.03)
    assert w.fraction_outside == 1.0


def test_whiteness_mask_drops_steps():
    g = torch.Generator().manual_seed(7)
    e = torch.randn(5, 100, generator=g, dtype=f64)
    mask = torch.ones(5, 100, dtype=torch.bool)
    mask[:, ::3] = False
    corrupted = e.clone()
    corrupted[~mask] = float("nan")
    a = M.innovation_whiteness(corrupted, mask, max_lag=4)
    b = M.innovation_whiteness(torch.where(mask, e, torch.zeros_like(e)), mask, max_lag=4)
    assert torch.allclose(a.rho, b.rho) and bool(torch.isfinite(a.rho).all())
    with pytest.raises(ValueError, match="max_lag"):
        M.innovation_whiteness(e, max_lag=100)


# -- mode switch delay ---------------------------------------------------------------------------
def test_mode_switch_delay_counts_steps_until_detection():
    t = 30
    modes = torch.zeros(2, t, dtype=torch.long)
    modes[0, 10:20] = 1
    modes[1, 5:] = 1
    probs = torch.zeros(2, t, 2, dtype=f64)
    probs[..., 0] = 1.0
    probs[0, 13:20] = torch.tensor([0.2, 0.8], dtype=f64)  # detected 3 steps after t=10
    probs[0, 20:] = torch.tensor([0.9, 0.1], dtype=f64)  # back to mode 0 at once (delay 0)
    # trajectory 1: never exceeds 0.5 for mode 1 -> NaN
    probs[1, 5:] = torch.tensor([0.5, 0.5], dtype=f64)
    out = M.mode_switch_delay(probs, modes)
    assert out.batch_index.tolist() == [0, 0, 1]
    assert out.start.tolist() == [10, 20, 5]
    assert out.mode.tolist() == [1, 0, 1]
    assert out.delay[:2].tolist() == [3.0, 0.0] and math.isnan(float(out.delay[2]))
    assert out.mean() == pytest.approx(1.5)
    with pytest.raises(ValueError):
        M.mode_switch_delay(probs, modes[:, :5])
