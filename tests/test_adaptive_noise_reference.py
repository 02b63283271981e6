"""The adaptive noise-estimating filters against plain-numpy references written from the papers'
equations (tests/adaptive_noise_reference.py), to 1e-10 in float64: around the KF and the UKF
on a linear model, around the EKF and the UKF on a range model (three beacons), with and
without partial masks and missing steps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, UKF, CovarianceMatching, KalmanFilter, SageHusa, VBAdaptiveQR, VBAdaptiveR
from difffilter.filters.adaptive_noise import covariance_matching as covariance_matching_module
from difffilter.filters.adaptive_noise import sage_husa as sage_husa_module
from difffilter.filters.adaptive_noise.base import is_positive_definite
from difffilter.models import FunctionalModel, LinearModel

from . import adaptive_noise_reference as ref
from .filter_contract import cv_matrices

BEACONS = np.array([[-3.0, 1.0], [4.0, -2.0], [0.5, 6.0]])


def _range_h(x):
    return np.sqrt(((x[[0, 2]] - BEACONS) ** 2).sum(-1))


def _range_hj(x):
    d = x[[0, 2]] - BEACONS
    rng = np.sqrt((d**2).sum(-1))
    out = np.zeros((3, 4))
    out[:, 0], out[:, 2] = d[:, 0] / rng, d[:, 1] / rng
    return out


def _range_h_torch(x):
    beacons = torch.tensor(BEACONS, dtype=x.dtype)
    pos = x[..., [0, 2]]
    return torch.sqrt(((pos[..., None, :] - beacons) ** 2).sum(-1))


def _case(kind: str, seed: int = 0, T: int = 30):
    """(model, inner filter, numpy (F, Q, R, h, hj), z [2, T, m], m0, P0)."""
    mats = cv_matrices(r=0.5)
    F, Q = mats["F"], mats["Q"]
    g = torch.Generator().manual_seed(seed)
    if kind.startswith("range"):
        R = torch.diag(torch.tensor([0.3, 0.5, 0.4], dtype=torch.float64))
        model = FunctionalModel(f=lambda x: x @ F.mT, h=_range_h_torch, Q=Q, R=R, f_jacobian=lambda x: F.expand(*x.shape[:-1], 4, 4))
        h, hj = _range_h, _range_hj
    else:
        R = mats["R"]
        model = LinearModel(F=F, H=mats["H"], Q=Q, R=R)
        H = mats["H"].numpy()
        h, hj = (lambda x: H @ x), (lambda x: H)
    unscented = kind in ("ukf", "range_ukf")
    inner = UKF(model) if unscented else EKF(model) if kind == "range" else KalmanFilter(model)
    mom = ref.unscented_moments(h) if unscented else ref.ekf_moments(h, hj)
    # simulated with noise 3x the model's R: the estimators have something to find
    m = R.shape[0]
    x = torch.tensor([1.0, 0.3, -0.5, 0.2], dtype=torch.float64).expand(2, 4)
    zs = []
    for _ in range(T):
        x = x @ F.mT + 0.3 * torch.randn(2, 4, generator=g, dtype=torch.float64)
        zt = _range_h_torch(x) if kind.startswith("range") else x @ mats["H"].mT
        zs.append(zt + 3.0**0.5 * torch.randn(2, m, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(R).mT)
    z = torch.stack(zs, 1)
    m0 = torch.tensor([0.8, 0.2, -0.3, 0.1], dtype=torch.float64)
    P0 = torch.diag(torch.tensor([1.0, 0.5, 1.0, 0.5], dtype=torch.float64))
    npm = (F.numpy(), Q.numpy(), R.numpy(), mom)
    return model, inner, npm, z, m0, P0


def _mask(z, seed=1):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(z.shape, generator=g) > 0.3
    mask[:, 4:6] = False  # fully missing steps
    return mask


FILTERS = {
    "sage_husa": (
        lambda inner: SageHusa(inner, b=0.9, adapt_q=True),
        lambda z, m0, P0, npm, mk: ref.sage_husa(z, m0, P0, *npm, b=0.9, mask=mk, adapt_q=True),
    ),
    "sage_husa_r": (lambda inner: SageHusa(inner, b=0.8), lambda z, m0, P0, npm, mk: ref.sage_husa(z, m0, P0, *npm, b=0.8, mask=mk)),
    "vb_r": (
        lambda inner: VBAdaptiveR(inner, rho=0.9, iterations=3, prior_shape=2.0),
        lambda z, m0, P0, npm, mk: ref.vb_r(z, m0, P0, *npm, rho=0.9, iterations=3, prior_shape=2.0, mask=mk),
    ),
    "vb_qr": (
        lambda inner: VBAdaptiveQR(inner, rho=0.9, tau=2.0, iterations=4, prior_dof=3.0),
        lambda z, m0, P0, npm, mk: ref.vb_qr(z, m0, P0, *npm, rho=0.9, tau=2.0, iterations=4, prior_dof=3.0, mask=mk),
    ),
    "cov_match": (
        lambda inner: CovarianceMatching(inner, window=6.0),
        lambda z, m0, P0, npm, mk: ref.covariance_matching(z, m0, P0, *npm, window=6.0, mask=mk),
    ),
    "cov_match_q": (
        lambda inner: CovarianceMatching(inner, window=8.0, adapt_q=True),
        lambda z, m0, P0, npm, mk: ref.covariance_matching(z, m0, P0, *npm, window=8.0, mask=mk, adapt_q=True),
    ),
}


@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
@pytest.mark.parametrize("kind", ["kf", "ukf", "range", "range_ukf"])
@pytest.mark.parametrize("name", sorted(FILTERS))
def test_equals_numpy_reference(name, kind, masked):
    build, reference = FILTERS[name]
    model, inner, npm, z, m0, P0 = _case(kind)
    mask = _mask(z) if masked else None
    zin = z if mask is None else torch.where(mask, z, torch.full_like(z, float("nan")))
    res = build(inner)(zin, m0, P0, mask=mask)
    keys = {"R": "noise_R", "Q": "noise_Q", "P": "noise_prior_cov"}
    for b in range(z.shape[0]):
        want = reference(z[b].numpy(), m0.numpy(), P0.numpy(), npm, None if mask is None else mask[b].numpy())
        got = {"mean": res.mean[b], "cov": res.cov[b], "ll": res.log_likelihood[b]}
        got.update({k: res.extras[v][b] for k, v in keys.items() if v in res.extras and k in want})
        for key, val in got.items():
            if key == "Q" and name.startswith(("sage_husa_r", "vb_r", "cov_match")) and not name.endswith("_q"):
                continue
            err = np.abs(val.detach().numpy() - want[key]).max()
            assert err < 1e-10, f"{name}/{kind}: {key} differs by {err:.3g}"
        if name.startswith("cov_match"):
            np.testing.assert_allclose(res.innovation_cov_estimate[b].detach().numpy(), want["C"], rtol=0, atol=1e-10)
            if mask is None:  # the recursion is the explicit exponential-window average
                np.testing.assert_allclose(want["C"], want["sums"], rtol=0, atol=1e-10)


def test_reference_cases_adapt(monkeypatch):
    # the estimates move away from the model's R (else the comparisons above would be vacuous),
    # and the safeguards of Sage-Husa and covariance matching take both branches on these data
    decisions = []

    def spy(a, floor):
        ok = is_positive_definite(a, floor)
        decisions.append(ok)
        return ok

    monkeypatch.setattr(sage_husa_module, "is_positive_definite", spy)
    monkeypatch.setattr(covariance_matching_module, "is_positive_definite", spy)
    for name in FILTERS:
        build, _ = FILTERS[name]
        model, inner, _, z, m0, P0 = _case("kf")
        decisions.clear()
        with torch.no_grad():
            res = build(inner)(z, m0, P0)
        change = (res.noise_R[:, -1] - model.measurement.R.detach()).abs().max()
        assert float(change) > 0.1, name
        if name.startswith(("sage_husa", "cov_match")):
            taken = torch.cat(decisions)
            assert bool(taken.any()) and not bool(taken.all()), name
