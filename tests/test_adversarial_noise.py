"""Issue 17, defect 2: positive semi-definite process noise is accepted and filtered exactly.

The textbook rank-deficient white-noise-acceleration ``Q = q g g^T``, ``g = [dt^2/2, dt]``
(filterpy's ``Q_discrete_white_noise``) was accepted or refused depending on rounding.
References: filterpy's ``Q_discrete_white_noise`` for the structure and a numpy Kalman filter
(``tests/filter_contract.numpy_kalman``) for the filtering.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difffilter.filters import EKF, UKF, ColoredNoiseUKF, Cubature, Julier, KalmanFilter, SimplifiedUKF, SquareRootUKF
from difffilter.models import ConstantVelocity, FunctionalModel, LinearModel
from difffilter.models.base import StateSpaceModel
from difffilter.params import FactorCovariance, register_covariance

from .filter_contract import make_data, numpy_kalman

F64 = torch.float64


def wna(q: float, dt: float = 1.0) -> np.ndarray:
    g = np.array([dt * dt / 2, dt])
    return np.kron(np.eye(2), q * np.outer(g, g))


def mats(q: float) -> dict[str, np.ndarray]:
    f1 = np.array([[1.0, 1.0], [0.0, 1.0]])
    return {"F": np.kron(np.eye(2), f1), "H": np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]), "Q": wna(q), "R": 0.5 * np.eye(2)}


@pytest.mark.parametrize("q", [0.5, 50.0, 1e4, 3.7e-3])
def test_rank_deficient_q_is_accepted_for_any_intensity(q):
    m = {k: torch.tensor(v, dtype=F64) for k, v in mats(q).items()}
    assert np.linalg.matrix_rank(m["Q"].numpy()) == 2
    LinearModel(**m, Q_structure="fixed")
    LinearModel(**m, Q_structure="factor")
    LinearModel(**m, Q_structure="scalar")
    FunctionalModel(f=lambda x: x @ m["F"].mT, h=lambda x: x @ m["H"].mT, Q=m["Q"], R=m["R"], Q_structure="fixed")
    LinearModel(**m)  # the default structure "auto" holds it as a factor (issue 27)
    with pytest.raises(ValueError, match="Q.*semi-definite.*Q_structure='factor'.*'fixed'"):
        LinearModel(**m, Q_structure="full")  # the full log-Cholesky structure cannot hold it: the message says what can


def test_indefinite_q_is_still_refused():
    m = {k: torch.tensor(v, dtype=F64) for k, v in mats(1.0).items()}
    m["Q"] = m["Q"] - 1e-3 * torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        LinearModel(**m, Q_structure="fixed")


def test_discrete_white_noise_matches_filterpy():
    common = pytest.importorskip("filterpy.common")
    cv = ConstantVelocity(axes=2, dt=0.7, q=3.0, noise="discrete", dtype=F64)
    ref = np.kron(np.eye(2), common.Q_discrete_white_noise(dim=2, dt=0.7, var=3.0))
    np.testing.assert_allclose(cv.Q.detach().numpy(), ref, rtol=1e-14, atol=0)
    u = {"dt": torch.full((3, 1), 0.2, dtype=F64)}
    ref2 = np.kron(np.eye(2), common.Q_discrete_white_noise(dim=2, dt=0.2, var=3.0))
    np.testing.assert_allclose(cv.process_noise(torch.zeros(3, 4, dtype=F64), u)[1].detach().numpy(), ref2, rtol=1e-14, atol=0)


FILTERS = {
    "kf": lambda m: KalmanFilter(m),
    "ekf": lambda m: EKF(m),
    "ukf": lambda m: UKF(m),
    "ukf_julier_reuse": lambda m: UKF(m, sigma_points=Julier(kappa=-1.0), redraw_after_predict=False),
    "ukf_augmented": lambda m: UKF(m, sigma_points=Cubature(), noise="augmented"),
    "sukf": lambda m: SimplifiedUKF(m),
    "srukf": lambda m: SquareRootUKF(m),
    "colored0": lambda m: ColoredNoiseUKF(m, psi=0.0),
}


@pytest.mark.parametrize("name", list(FILTERS))
@pytest.mark.parametrize("structure", ["fixed", "factor"])
def test_filters_with_rank_deficient_q_equal_closed_form(name, structure):
    np_m = mats(50.0)
    m = {k: torch.tensor(v, dtype=F64) for k, v in np_m.items()}
    model = LinearModel(**m, Q_structure=structure)
    z = make_data(2, 30, 2, seed=3)
    m0 = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=F64)
    p0 = torch.diag(torch.tensor([4.0, 1.0, 4.0, 1.0], dtype=F64))
    res = FILTERS[name](model)(z, m0, p0)
    for b in range(2):
        mu, cov, ll = numpy_kalman(z[b].numpy(), m0.numpy(), p0.numpy(), **np_m)
        np.testing.assert_allclose(res.mean[b].detach().numpy(), mu, rtol=0, atol=1e-8 * max(1.0, float(np.abs(mu).max())))
        np.testing.assert_allclose(res.cov[b].detach().numpy(), cov, rtol=0, atol=1e-8 * float(np.abs(cov).max()))
        np.testing.assert_allclose(res.log_likelihood[b].detach().numpy(), ll, rtol=0, atol=1e-7)


def test_learnable_structured_q_and_factor_q_have_finite_exact_gradients():
    cv = ConstantVelocity(axes=2, dt=1.0, q=2.0, noise="discrete", dtype=F64)
    h = LinearModel(**{k: torch.tensor(v, dtype=F64) for k, v in mats(1.0).items()}, Q_structure="fixed").measurement
    model = StateSpaceModel(cv, h)
    z = make_data(2, 8, 2, seed=5)
    m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    for flt in (UKF(model), SquareRootUKF(model), KalmanFilter(model)):
        raw = cv.parametrizations.q.original

        def fn(r, flt=flt):
            return torch.func.functional_call(flt, {"model.dynamics.parametrizations.q.original": r}, (z, m0, p0)).log_likelihood.sum()

        assert torch.autograd.gradcheck(fn, (raw.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-4)
    lin = LinearModel(**{k: torch.tensor(v, dtype=F64) for k, v in mats(3.0).items()}, Q_structure="factor")
    raw = lin.dynamics.parametrizations.Q.original
    assert raw.shape == (4, 2)  # rank-2 factor: learning stays in the semi-definite set
    flt = UKF(lin)

    def gn(r):
        return torch.func.functional_call(flt, {"model.dynamics.parametrizations.Q.original": r}, (z, m0, p0)).log_likelihood.sum()

    assert torch.autograd.gradcheck(gn, (raw.detach().clone().requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_factor_covariance_round_trip_and_rank_check():
    m = torch.nn.Module()
    q = torch.tensor(wna(7.0), dtype=F64)
    register_covariance(m, "Q", q, "factor")
    assert isinstance(m.parametrizations.Q[0], FactorCovariance) and m.parametrizations.Q[0].rank == 2
    torch.testing.assert_close(m.Q, q, rtol=0, atol=1e-12 * float(q.abs().max()))
    m.Q = 2.0 * q
    torch.testing.assert_close(m.Q, 2.0 * q, rtol=0, atol=1e-12 * float(q.abs().max()))
    with pytest.raises(ValueError, match="Q must have rank <= 2"):
        m.Q = torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        m.Q = -q


def test_semi_definite_r_with_fixed_structure():
    np_m = mats(1.0)
    np_m["R"] = np.array([[0.5, 0.5], [0.5, 0.5]])  # one noise source seen by both components
    m = {k: torch.tensor(v, dtype=F64) for k, v in np_m.items()}
    z = make_data(1, 15, 2, seed=9)
    m0, p0 = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    mu, _, ll = numpy_kalman(z[0].numpy(), m0.numpy(), p0.numpy(), **np_m)
    for flt in (
        KalmanFilter(LinearModel(**m, Q_structure="fixed", R_structure="fixed")),
        UKF(LinearModel(**m, Q_structure="factor", R_structure="fixed")),
    ):
        res = flt(z, m0, p0)
        np.testing.assert_allclose(res.mean[0].detach().numpy(), mu, atol=1e-8 * max(1.0, float(np.abs(mu).max())))
        np.testing.assert_allclose(res.log_likelihood[0].detach().numpy(), ll, atol=1e-7)
