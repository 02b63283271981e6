"""Properties of the adaptive noise-estimating filters: closed-form limits, convergence of the R
estimate on long linear data, batch = loop, masks, float32, gradients of the hyperparameters
against finite differences, a short learning run, and bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.filters import UKF, CovarianceMatching, KalmanFilter, SageHusa, VBAdaptiveQR, VBAdaptiveR
from difffilter.filters.iterated import IteratedEKF
from difffilter.models import LinearModel

from .filter_contract import cv_matrices, numpy_kalman

BUILDERS = {
    "sage_husa": lambda inner: SageHusa(inner, b=0.9, adapt_q=True),
    "vb_r": lambda inner: VBAdaptiveR(inner, rho=0.9, iterations=2),
    "vb_qr": lambda inner: VBAdaptiveQR(inner, rho=0.9, tau=2.0, iterations=3),
    "cov_match": lambda inner: CovarianceMatching(inner, window=5.0, adapt_q=True),
}
HYPER = {"sage_husa": ["b"], "vb_r": ["rho"], "vb_qr": ["rho", "tau"], "cov_match": ["window"]}


def _model(dtype=torch.float64, r_offdiag: bool = True) -> LinearModel:
    mats = cv_matrices(r=0.5)
    if not r_offdiag:
        mats["R"] = torch.diag(torch.diagonal(mats["R"]))
    return LinearModel(**{k: v.to(dtype) for k, v in mats.items()})


def _simulate(B: int, T: int, r_scale: float, seed: int, dtype=torch.float64):
    """Trajectories of the CV model with measurement noise ``r_scale`` times the model's R."""
    mats = cv_matrices(r=0.5)
    g = torch.Generator().manual_seed(seed)
    lq = torch.linalg.cholesky(mats["Q"])
    lr = torch.linalg.cholesky(r_scale * mats["R"])
    x = torch.zeros(B, 4, dtype=torch.float64)
    zs = []
    for _ in range(T):
        x = x @ mats["F"].mT + torch.randn(B, 4, generator=g, dtype=torch.float64) @ lq.mT
        zs.append(x @ mats["H"].mT + torch.randn(B, 2, generator=g, dtype=torch.float64) @ lr.mT)
    return torch.stack(zs, 1).to(dtype), r_scale * mats["R"]


def _start(dtype=torch.float64):
    return torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype)


# -- closed-form limits ------------------------------------------------------------------------
def test_vb_filters_with_overwhelming_priors_are_the_kalman_filter():
    # VB-R: R stays the prior when its shape is huge; VB-QR: tau, nu huge keep P~ and R
    model = _model(r_offdiag=False)
    z, _ = _simulate(2, 25, 3.0, seed=1)
    m0, p0 = _start()
    mats = {k: v.numpy() for k, v in cv_matrices(r=0.5).items()}
    mats["R"] = np.diag(np.diag(mats["R"]))
    for flt in (VBAdaptiveR(KalmanFilter(model), rho=0.9, prior_shape=1e13), VBAdaptiveQR(KalmanFilter(model), tau=1e13, prior_dof=1e14)):
        res = flt(z, m0, p0)
        for b in range(2):
            mu, cov, ll = numpy_kalman(z[b].numpy(), m0.numpy(), p0.numpy(), **mats)
            assert np.abs(res.mean[b].detach().numpy() - mu).max() < 1e-8
            assert np.abs(res.cov[b].detach().numpy() - cov).max() < 1e-8
            assert np.abs(res.log_likelihood[b].detach().numpy() - ll).max() < 1e-8


@pytest.mark.slow
@pytest.mark.parametrize("name", ["sage_husa", "vb_r", "vb_qr", "cov_match"])
def test_r_estimate_converges_to_the_true_r(name):
    # model R = 0.5 [[1, .2], [.2, 1]], true R = 4x that; long memory (about 200 samples);
    # the estimate averaged over the last 300 steps of 4 trajectories is within 15 % of the truth
    # (relative Frobenius error; sampling error of such an average is about 5 %)
    model = _model(r_offdiag=name != "vb_r")
    z, r_true = _simulate(4, 1500, 4.0, seed=3)
    flt = {
        "sage_husa": lambda: SageHusa(KalmanFilter(model), b=0.995),
        "vb_r": lambda: VBAdaptiveR(KalmanFilter(model), rho=0.9975, iterations=2),
        # the nominal Q is right here: a confident tau (30) keeps P^ from absorbing the excess
        # innovation (with the paper's tau = 3 the error is 24 %, measured)
        "vb_qr": lambda: VBAdaptiveQR(KalmanFilter(model), rho=0.995, tau=30.0, iterations=3),
        "cov_match": lambda: CovarianceMatching(KalmanFilter(model), window=200.0),
    }[name]()
    with torch.no_grad():
        res = flt(z, *_start())
    est = res.noise_R[:, -300:].mean((0, 1))
    target = torch.diag(torch.diagonal(r_true)) if name == "vb_r" else r_true
    rel = float(torch.linalg.matrix_norm(est - target) / torch.linalg.matrix_norm(target))
    start = float(torch.linalg.matrix_norm(model.measurement.R.detach() - target) / torch.linalg.matrix_norm(target))
    assert rel < 0.15 and start > 0.7, (rel, start)


# -- batch, masks, dtypes ------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_batch_equals_loop_and_masks_are_honoured(name):
    model = _model()
    z, _ = _simulate(3, 15, 3.0, seed=5)
    mask = torch.rand(3, 15, 2, generator=torch.Generator().manual_seed(6)) > 0.3
    mask[1, 5:8] = False
    flt = BUILDERS[name](KalmanFilter(model))
    m0, p0 = _start()
    zn = torch.where(mask, z, torch.full_like(z, float("nan")))
    full = flt(zn, m0, p0, mask=mask)
    for b in range(3):
        one = flt(zn[b : b + 1], m0, p0, mask=mask[b : b + 1])
        torch.testing.assert_close(one.mean[0], full.mean[b], rtol=0, atol=1e-10)
        torch.testing.assert_close(one.noise_R[0], full.noise_R[b], rtol=0, atol=1e-10)
        torch.testing.assert_close(one.log_likelihood[0], full.log_likelihood[b], rtol=0, atol=1e-10)
    # a fully missing step leaves every carried statistic unchanged and is predict-only
    # (VB-QR's noise_Q and noise_prior_cov are per-step estimates of the prediction, not carried:
    # at a missing step the prediction is the nominal one)
    if name == "vb_qr":
        torch.testing.assert_close(full.noise_prior_cov[1, 5:8], full.prior_cov[1, 5:8], rtol=0, atol=0)
    per_step = ("noise_Q", "noise_prior_cov") if name == "vb_qr" else ()
    carried = [k for k in full.extras if k.startswith(("noise_", "innovation_cov")) and k not in per_step]
    assert "noise_R" in carried
    for key in carried:
        held = full.extras[key][1, 5:8]
        torch.testing.assert_close(held, full.extras[key][1, 4:5].expand_as(held), rtol=0, atol=0)
    torch.testing.assert_close(full.mean[1, 6], full.prior_mean[1, 6], rtol=0, atol=0)
    assert float(full.log_likelihood[1, 6].detach()) == 0.0
    # NaN under the mask reaches neither values nor gradients; any masked value gives the same run
    full.log_likelihood.sum().backward()
    grads = [p.grad for p in flt.parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
    other = flt(torch.where(mask, z, torch.full_like(z, 1e6)), m0, p0, mask=mask)
    torch.testing.assert_close(other.mean, full.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(other.noise_R, full.noise_R, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_one_bad_trajectory_does_not_contaminate_the_batch(name):
    # an absurd trajectory (overflowing statistics) stays in its own row, values and gradients
    z, _ = _simulate(3, 10, 3.0, seed=19)
    z[1] = z[1] * 1e150
    flt = BUILDERS[name](KalmanFilter(_model()))
    full = flt(z, *_start())
    ref = flt(z[[0, 2]], *_start())
    torch.testing.assert_close(full.mean[[0, 2]], ref.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(full.noise_R[[0, 2]], ref.noise_R, rtol=0, atol=1e-10)
    raws = [getattr(flt.parametrizations, h).original for h in HYPER[name]]
    g_full = torch.autograd.grad(full.log_likelihood[[0, 2]].sum(), raws)
    g_ref = torch.autograd.grad(ref.log_likelihood.sum(), raws)
    for a, b in zip(g_full, g_ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_float32_matches_float64(name):
    z, _ = _simulate(2, 20, 3.0, seed=7)
    r64 = BUILDERS[name](KalmanFilter(_model()))(z, *_start())
    r32 = BUILDERS[name](KalmanFilter(_model(torch.float32)))(z.float(), *_start(torch.float32))
    assert r32.mean.dtype == torch.float32 and r32.noise_R.dtype == torch.float32
    for a, b in ((r32.mean, r64.mean), (r32.noise_R, r64.noise_R), (r32.log_likelihood, r64.log_likelihood)):
        rel = float((a.double() - b).abs().max().detach() / b.abs().max().detach())
        assert rel < 1e-4, rel


def test_window_carry_over_and_step_equal_the_full_run():
    z, _ = _simulate(2, 12, 3.0, seed=9)
    for name, build in BUILDERS.items():
        flt = build(UKF(_model()))
        m0, p0 = _start()
        full = flt(z, m0, p0)
        first = flt(z[:, :5], m0, p0)
        second = flt(z[:, 5:], belief=first.final_belief)
        torch.testing.assert_close(second.mean, full.mean[:, 5:], rtol=0, atol=1e-12, msg=name)
        torch.testing.assert_close(second.noise_R, full.noise_R[:, 5:], rtol=0, atol=1e-12, msg=name)
        belief = flt.initial_belief(m0, p0, batch_size=2)
        for t in range(3):
            belief, _, info = flt.step(belief, z[:, t])
            torch.testing.assert_close(info.log_likelihood, full.log_likelihood[:, t], rtol=0, atol=1e-12, msg=name)


# -- gradients and learning ----------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_gradcheck_hyperparameters_and_noise(name):
    model = _model()
    flt = BUILDERS[name](UKF(model) if name == "sage_husa" else KalmanFilter(model))
    z, _ = _simulate(1, 6, 3.0, seed=11)
    mask = torch.ones(1, 6, 2, dtype=torch.bool)
    mask[0, 2, 1] = False
    m0, p0 = _start()
    # the hyperparameters and the model's raw R (and raw Q where Q is estimated from it; VB-QR's
    # nominal Q is left out to keep the check short)
    named = [(n, p) for n, p in flt.named_parameters() if n.endswith("original") and not (name == "vb_qr" and "dynamics" in n)]
    assert any("measurement" in n for n, _ in named)
    assert {h for h in HYPER[name]} <= {n.split(".")[1] for n, _ in named if n.startswith("parametrizations.")}
    names = [n for n, _ in named]

    def loglik(*values):
        out = torch.func.functional_call(flt, dict(zip(names, values, strict=True)), (z, m0, p0), {"mask": mask})
        return out.log_likelihood.sum() + (out.mean**2).sum()

    inputs = tuple(p.detach().clone().requires_grad_(True) for _, p in named)
    assert torch.autograd.gradcheck(loglik, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def _jump_data():
    z1, _ = _simulate(2, 30, 1.0, seed=13)
    z2, _ = _simulate(2, 30, 16.0, seed=14)
    return torch.cat([z1, z2 + (z1[:, -1:] - z2[:, :1])], 1)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_one_gradient_step_on_the_hyperparameters_lowers_the_loss(name):
    # every hyperparameter receives a gradient, and a small step against it lowers the NLL
    flt = BUILDERS[name](KalmanFilter(_model()))
    z = _jump_data()[:, 20:45]
    m0, p0 = _start()
    raws = [getattr(flt.parametrizations, h).original for h in HYPER[name]]
    loss = -flt(z, m0, p0).log_likelihood.mean()
    grads = torch.autograd.grad(loss, raws)
    assert all(float(g.abs()) > 0 for g in grads)
    with torch.no_grad():
        for raw, g in zip(raws, grads, strict=True):
            raw -= 0.05 * g / max(float(torch.stack([x.abs() for x in grads]).max()), 1e-12)
        after = -flt(z, m0, p0).log_likelihood.mean()
    assert float(after) < float(loss)


@pytest.mark.slow
def test_learned_forgetting_factor_moves_and_improves_the_loss():
    # the measurement noise jumps x16 halfway: the best memory is neither short nor frozen
    # (a grid over b gives its minimum near 0.95 on these data).  Start from b = 0.7 and learn b
    # alone on the negative log-likelihood.
    model = _model()
    z = _jump_data()
    flt = SageHusa(KalmanFilter(model), b=0.7)
    m0, p0 = _start()
    opt = torch.optim.Adam([flt.parametrizations.b.original], lr=0.4)
    losses = []
    for _ in range(6):
        opt.zero_grad()
        loss = -flt(z, m0, p0).log_likelihood.mean()
        loss.backward()
        opt.step()
        losses.append(float(loss))
    with torch.no_grad():
        final = float(-flt(z, m0, p0).log_likelihood.mean())
        kf = float(-KalmanFilter(model)(z, m0, p0).log_likelihood.mean())
    assert float(flt.b) > 0.85, float(flt.b)
    assert final < losses[0] - 0.5, (losses[0], final)
    assert final < kf  # the learned adaptive filter beats the KF with the model's R


# -- bad inputs ----------------------------------------------------------------------------
def test_bad_arguments_raise_naming_the_argument():
    model = _model()
    kf = KalmanFilter(model)
    for bad in (0.0, 1.0, -0.2, 1.5):
        with pytest.raises(ValueError, match="b "):
            SageHusa(kf, b=bad)
        with pytest.raises(ValueError, match="rho"):
            VBAdaptiveR(kf, rho=bad)
        with pytest.raises(ValueError, match="rho"):
            VBAdaptiveQR(kf, rho=bad)
    for bad in (1.0, 0.5, 0.0, -3.0):
        with pytest.raises(ValueError, match="window"):
            CovarianceMatching(kf, window=bad)
    with pytest.raises(ValueError, match="tau"):
        VBAdaptiveQR(kf, tau=0.0)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="iterations"):
            VBAdaptiveR(kf, iterations=bad)
    with pytest.raises(ValueError, match="prior_shape"):
        VBAdaptiveR(kf, prior_shape=0.0)
    with pytest.raises(ValueError, match="prior_dof"):
        VBAdaptiveQR(kf, prior_dof=-1.0)
    with pytest.raises(ValueError, match="pd_floor"):
        SageHusa(kf, pd_floor=-1.0)
    with pytest.raises(TypeError, match="inner"):
        SageHusa(IteratedEKF(model))
    with pytest.raises(TypeError, match="inner"):
        CovarianceMatching(model)
    with pytest.raises(ValueError, match="redraw_after_predict"):
        VBAdaptiveR(UKF(model, redraw_after_predict=False))
    flt = SageHusa(kf)
    z, _ = _simulate(2, 5, 1.0, seed=0)
    m0, p0 = _start()
    with pytest.raises(ValueError, match="measurements"):
        flt(z[..., :1], m0, p0)
    with pytest.raises(ValueError, match="initial_mean"):
        flt(z, torch.zeros(3, dtype=torch.float64), p0)
    with pytest.raises(ValueError, match="mask"):
        flt(z, m0, p0, mask=torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="b must lie"):
        flt.b = torch.tensor(1.5, dtype=torch.float64)
