"""p001's scenario families: the injected coloured noise has the stated statistics (paper, longer
multipath, elevation law), the elevation law at p001's values is p001's filter to rounding, the
coloured UKF with per-step Psi is exact for linear models (dense joint Gaussian), and the
oracle's values come from the simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from difffilter.filters import ColoredNoiseUKF, Julier, MerweScaled
from difffilter.models import FunctionalModel
from difffilter.models.base import MeasurementModel, StateSpaceModel
from difffilter.selection import assign_parameters
from experiments.papers.p001 import (
    LAW_KEYS,
    P001_CONFIG,
    ElevationPseudorange,
    elevation_noise,
    make_p001_model,
    p001_simulator,
    paper_law,
    simulate_p001,
)

from .filter_contract import cv_matrices, make_data
from .test_colored import _dense_posteriors

F64 = torch.float64
ELEVATION_LAW = {
    "sigma_zenith": 3.0,
    "sigma_exponent": 1.0,
    "tau_zenith": 28.036732520571,
    "tau_exponent": 1.0,
}  # experiments/papers/p001/conf/scenario/p001_elevation_*.yaml


def _ar1_statistics(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per satellite: lag-1 autocorrelation and variance of ``v [B, T, K]`` over runs and steps."""
    var = v.pow(2).mean((0, 1))
    lag1 = (v[:, 1:] * v[:, :-1]).mean((0, 1)) / var
    return lag1, var


def test_elevation_law_closed_form_and_paper_member() -> None:
    el = torch.deg2rad(torch.tensor([90.0, 30.0, 10.0], dtype=F64))
    psi, r = elevation_noise(el, 10.0, sigma_zenith=2.0, sigma_exponent=1.5, tau_zenith=20.0, tau_exponent=0.5)
    for i, deg in enumerate((90.0, 30.0, 10.0)):
        s = 1.0 / math.sin(math.radians(deg))
        sig, tau = 2.0 * s**1.5, 20.0 * s**0.5
        p = math.exp(-10.0 / tau)
        assert float(psi[i]) == pytest.approx(p, rel=1e-12)
        assert float(r[i]) == pytest.approx(sig**2 * (1 - p * p), rel=1e-12)
    law = paper_law(psi=0.7, eta_sigma=3.0, dt=10.0)
    psi, r = elevation_noise(torch.deg2rad(torch.tensor([5.0, 45.0, 85.0], dtype=F64)), 10.0, **law)
    torch.testing.assert_close(psi, torch.full((3,), 0.7, dtype=F64))
    torch.testing.assert_close(r, torch.full((3,), 9.0, dtype=F64))
    with pytest.raises(ValueError, match="psi"):
        paper_law(psi=1.0, eta_sigma=3.0, dt=10.0)


@pytest.mark.parametrize(
    ("config", "psi", "sigma"),
    [({}, 0.7, 3.0 / math.sqrt(1 - 0.49)), ({"psi": 0.9, "eta_sigma": 1.5}, 0.9, 1.5 / math.sqrt(1 - 0.81))],
    ids=["paper", "multipath"],
)
def test_constant_families_inject_the_stated_ar1_noise(config, psi, sigma) -> None:
    sc = simulate_p001(300, seed=7, config=config)
    lag1, var = _ar1_statistics(sc.noise.to(F64))
    n = sc.noise.shape[0] * sc.noise.shape[1]
    # correlated samples: effective size ~ n (1 - psi) / (1 + psi); 5 standard errors
    eff = n * (1 - psi) / (1 + psi)
    assert bool(((lag1 - psi).abs() < 5 * (1 - psi**2) / math.sqrt(eff)).all()), lag1
    assert bool(((var / sigma**2 - 1).abs() < 5 * math.sqrt(2 / eff)).all()), var
    torch.testing.assert_close(sc.ar_coefficient, torch.full_like(sc.ar_coefficient, psi))


def test_elevation_family_injects_the_elevation_law() -> None:
    sc = simulate_p001(300, seed=8, config={"elevation_noise": ELEVATION_LAW})
    lag1, var = _ar1_statistics(sc.noise.to(F64))
    n = sc.noise.shape[0] * sc.noise.shape[1]
    for j, deg in enumerate(P001_CONFIG["elevation_deg"]):  # type: ignore[arg-type]
        s = 1.0 / math.sin(math.radians(deg))
        psi, sigma = math.exp(-10.0 / (28.036732520571 * s)), 3.0 * s
        eff = n * (1 - psi) / (1 + psi)
        assert abs(float(lag1[j]) - psi) < 5 * (1 - psi**2) / math.sqrt(eff), (deg, float(lag1[j]), psi)
        assert abs(float(var[j]) / sigma**2 - 1) < 5 * math.sqrt(2 / eff), (deg, float(var[j]), sigma**2)
        assert float(sc.ar_coefficient[0, j]) == pytest.approx(psi, rel=1e-10)
    el = sc.controls["elevation"]
    torch.testing.assert_close(torch.rad2deg(el[0, 0]), torch.tensor(P001_CONFIG["elevation_deg"], dtype=F64))
    assert bool(torch.isnan(sc.psi).all()) and math.isnan(sc.eta_var)
    with pytest.raises(ValueError, match="exclude"):
        simulate_p001(2, seed=1, random_psi=(0.3, 0.9), config={"elevation_noise": ELEVATION_LAW})


def test_random_geometry_elevations_drive_the_noise() -> None:
    sc = simulate_p001(4, seed=3, randomize=True, num_epochs=5, config={"elevation_noise": ELEVATION_LAW})
    el = sc.controls["elevation"][:, 0]
    psi, r = elevation_noise(el.to(F64), 10.0, **ELEVATION_LAW)
    torch.testing.assert_close(sc.ar_coefficient, psi)
    torch.testing.assert_close(sc.eta_variance, r)
    assert float(el.min()) >= math.radians(10.0) - 1e-12 and float(el.max()) <= math.radians(85.0) + 1e-12


@pytest.mark.parametrize("sp", [Julier(kappa=-5.0), MerweScaled(alpha=1.0)], ids=repr)
def test_elevation_filter_at_paper_values_is_p001s_filter(sp) -> None:
    data = p001_simulator(batch_size=4, seed=5, num_steps=30, config={"elevation_noise": ELEVATION_LAW})
    paper = ColoredNoiseUKF(make_p001_model(), psi=0.7, sigma_points=sp)
    elev = ColoredNoiseUKF(make_p001_model(elevation_noise=paper_law(psi=0.7, eta_sigma=3.0, dt=10.0)), psi=None, sigma_points=sp)
    assert not hasattr(elev, "psi") and "psi" not in dict(elev.named_parameters())
    args = (data.measurements, data.initial_mean, data.initial_cov)
    a, b = paper(*args, controls=data.controls), elev(*args, controls=data.controls)
    for key in ("mean", "cov", "log_likelihood", "nis"):
        torch.testing.assert_close(getattr(a, key), getattr(b, key), rtol=0, atol=1e-9)


def test_psi_from_model_needs_an_ar_coefficient() -> None:
    with pytest.raises(TypeError, match="ar_coefficient"):
        ColoredNoiseUKF(make_p001_model(), psi=None)
    with pytest.raises(ValueError, match="sigma_exponent"):
        make_p001_model(elevation_noise={**ELEVATION_LAW, "sigma_exponent": 5.0})
    with pytest.raises(ValueError, match="tau_zenith"):
        make_p001_model(elevation_noise={**ELEVATION_LAW, "tau_zenith": 0.0})
    meas = make_p001_model(elevation_noise=ELEVATION_LAW).measurement
    assert isinstance(meas, ElevationPseudorange)
    with pytest.raises(KeyError, match="elevation"):
        meas.ar_coefficient({"dt": torch.ones(1, 1, dtype=F64)})


class _LinearArMeasurement(MeasurementModel):
    """``z_t = diag(g_t) H x_t + v_t`` with per-step AR coefficients and driving-noise variances
    read from the inputs (``u["gain"]``, ``u["psi"]``, ``u["rvar"]``, each ``[..., 2]``)."""

    def __init__(self, H: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("H", H)
        self.measurement_dim = H.shape[0]

    def forward(self, x, u=None):
        return (x @ self.H.mT) * u["gain"]  # the filter adds the sigma-point axis to u

    def measurement_noise(self, x, u=None):
        return torch.diag_embed(u["rvar"])

    def ar_coefficient(self, u):
        return u["psi"]


def test_per_step_psi_matches_dense_joint_gaussian() -> None:
    mats = {k: v.numpy() for k, v in cv_matrices().items()}
    F, H, Q = mats["F"], mats["H"], mats["Q"]
    T, B = 8, 2
    g = torch.Generator().manual_seed(4)
    u = {
        "gain": 1.0 + 0.3 * torch.rand(B, T, 2, generator=g, dtype=F64),
        "psi": -0.5 + 1.4 * torch.rand(B, T, 2, generator=g, dtype=F64),
        "rvar": 0.2 + torch.rand(B, T, 2, generator=g, dtype=F64),
    }
    lin = FunctionalModel(f=lambda x: x @ torch.tensor(F).mT, h=lambda x: x[..., :2], Q=torch.tensor(Q), R=torch.eye(2, dtype=F64))
    model = StateSpaceModel(lin.dynamics, _LinearArMeasurement(torch.tensor(H)))
    z = make_data(B, T, 2, seed=9)
    m0, P0 = np.array([0.5, 1.0, -1.0, 0.2]), np.diag([2.0, 0.5, 2.0, 0.5])
    res = ColoredNoiseUKF(model, psi=None, sigma_points=MerweScaled(alpha=1.0))(z, torch.tensor(m0), torch.tensor(P0), controls=u)
    for b in range(B):
        hs = [np.diag(u["gain"][b, t].numpy()) @ H for t in range(T)]
        rs = np.stack([np.diag(u["rvar"][b, t].numpy()) for t in range(T)])
        mu, cov, ll = _dense_posteriors(F, hs, Q, rs, u["psi"][b].numpy(), m0, P0, z[b].numpy())
        np.testing.assert_allclose(res.mean[b].detach().numpy(), mu, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.cov[b].detach().numpy(), cov, rtol=0, atol=1e-9)
        assert abs(res.log_likelihood[b].sum().item() - ll) < 1e-8


def test_oracle_values_of_each_family() -> None:
    paper = p001_simulator(batch_size=2, seed=1, num_steps=4)
    assert paper.true_params["psi"] == pytest.approx(0.7) and paper.true_params["R"] == [pytest.approx(9.0)] * 7
    for k, v in paper_law(psi=0.7, eta_sigma=3.0, dt=10.0).items():
        assert paper.true_params[k] == pytest.approx(v)
    multi = p001_simulator(batch_size=2, seed=1, num_steps=4, config={"psi": 0.9, "eta_sigma": 1.5})
    assert multi.true_params["psi"] == pytest.approx(0.9) and multi.true_params["R"][0] == pytest.approx(2.25)
    elev = p001_simulator(batch_size=2, seed=1, num_steps=4, config={"elevation_noise": ELEVATION_LAW})
    assert {k: elev.true_params[k] for k in LAW_KEYS} == ELEVATION_LAW and "psi" not in elev.true_params
    # the oracle filter built from the simulator's values reproduces the truth's noise law
    oracle = ColoredNoiseUKF(make_p001_model(elevation_noise=paper_law(psi=0.7, eta_sigma=3.0, dt=10.0)), psi=None)
    assign_parameters(oracle, {k: elev.true_params[k] for k in LAW_KEYS})
    u = {k: v[:, 0] for k, v in elev.controls.items()}
    torch.testing.assert_close(oracle.ar_coefficients(u), elev.scenario.ar_coefficient)
    torch.testing.assert_close(
        torch.diagonal(oracle.model.measurement.measurement_noise(None, u), dim1=-2, dim2=-1), elev.scenario.eta_variance
    )
    model = elev.make_model()
    assert isinstance(model.measurement, ElevationPseudorange) and float(model.measurement.sigma_exponent.detach()) == pytest.approx(1.0)
