"""Inputs: every bad one refused naming the argument or config key, every legitimate one accepted.

Decisions (issue 27):

* controls given to a model none of whose parts uses them: ``ValueError`` (they used to be
  silently ignored);
* float64 controls into a float32 filter: cast to float32, as a float32 measurement would be
  (they used to raise an unrelated ``RuntimeError`` from a matmul);
* ``trainer.max_epochs=two`` / ``optimizer.lr=abc``: ``ValueError`` naming the key, before
  anything is built;
* a covariance below the float32 variance floor (``R = 1e-20 I``, ``Q = 1e-30 I``) and the
  semi-definite textbook white-noise-acceleration ``Q`` are accepted by the default
  ``*_structure="auto"`` (as ``"scalar"`` and ``"factor"``, holding the given value exactly);
  an explicit structure that cannot hold them is refused with the real reason and the option;
* a measurement whose ``residual`` wraps a component it does not declare ``angular``: the
  unscented filters refuse it (it gave a silently wrong posterior).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from difffilter.constraints import FactorCovariance
from difffilter.filters import UKF, KalmanFilter, SquareRootUKF
from difffilter.models import FunctionalModel, LinearModel
from difffilter.models.base import MeasurementModel, StateSpaceModel, wrap_angle
from difffilter.params import ScaledMatrix
from experiments.papers.p004.model import GnssMeasurement
from experiments.runner.config_check import check_config

from .filter_contract import cv_matrices, numpy_kalman
from .smoke_helpers import config_files

F64, F32 = torch.float64, torch.float32
CONF = Path(__file__).resolve().parents[1] / "conf"


def _run(filt, dtype=F64, **kw):  # type: ignore[no-untyped-def]
    z = torch.randn(2, 5, 2, generator=torch.Generator().manual_seed(0), dtype=F64).to(dtype)
    return filt(z, torch.zeros(4, dtype=dtype), torch.eye(4, dtype=dtype), **kw)


# -- controls -----------------------------------------------------------------------------------
def test_controls_for_a_model_that_uses_none_are_refused() -> None:
    u = torch.ones(2, 5, 2, dtype=F64)
    with pytest.raises(ValueError, match=r"controls were given, but no part of the model uses them.*LinearModel\(B=\.\.\.\)"):
        _run(KalmanFilter(LinearModel(**cv_matrices())), controls=u)
    m = cv_matrices()
    functional = FunctionalModel(f=lambda x: x @ m["F"].mT, h=lambda x: x @ m["H"].mT, Q=m["Q"], R=m["R"])
    with pytest.raises(ValueError, match="controls were given"):
        _run(UKF(functional), controls=u)
    _run(KalmanFilter(LinearModel(**m, B=torch.ones(4, 2, dtype=F64))), controls=u)  # a model with inputs takes them


def test_float64_controls_into_a_float32_filter_are_cast() -> None:
    m = {k: v.float() for k, v in cv_matrices().items()}
    filt = KalmanFilter(LinearModel(**m, B=torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.5], [0.0, 1.0]])))
    u64 = 0.1 * torch.randn(2, 5, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    got = _run(filt, F32, controls=u64)
    want = _run(filt, F32, controls=u64.float())
    assert got.mean.dtype == F32
    torch.testing.assert_close(got.mean, want.mean, rtol=0, atol=0)


# -- config keys --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [("trainer.max_epochs", "two", "an integer"), ("optimizer.lr", "abc", "a positive number"), ("data.batch_size", 0, "an integer >= 1")],
)
def test_a_config_value_of_the_wrong_type_names_its_key(key: str, value: object, expected: str) -> None:
    cfg = OmegaConf.create({"trainer": {"max_epochs": 2}, "optimizer": {"lr": 0.1}, "data": {"batch_size": 4}})
    OmegaConf.update(cfg, key, value)
    with pytest.raises(ValueError, match=rf"config key {key} must be {expected}.*got {value!r}"):
        check_config(cfg)


@pytest.mark.slow
def test_every_shipped_experiment_passes_the_config_check(tmp_path: Path) -> None:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for path in config_files("experiment"):
            for debug in ([], ["debug=smoke"]):
                cfg = compose(config_name="train", overrides=[f"experiment={path.stem}", f"paths.output_dir={tmp_path}", *debug])
                check_config(cfg)


# -- covariances --------------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "value"), [("R", 1e-20), ("Q", 1e-30)])
def test_tiny_float32_covariances_are_accepted_by_default(name: str, value: float) -> None:
    m = {k: v.float() for k, v in cv_matrices().items()}
    m[name] = value * torch.eye(m[name].shape[0])
    model = LinearModel(**m)
    part = model.measurement if name == "R" else model.dynamics
    assert isinstance(part.parametrizations[name][0], ScaledMatrix)  # "auto" picked the scalar structure
    torch.testing.assert_close(getattr(part, name), m[name], rtol=1e-6, atol=0)
    res = _run(KalmanFilter(model), F32)
    assert torch.isfinite(res.mean).all() and torch.isfinite(res.log_likelihood).all()
    for structure in ("full", "diagonal"):
        with pytest.raises(ValueError, match=rf"{name}.*1\.08e-19 is the variance floor.*{name}_structure='scalar'"):
            LinearModel(**{**m, f"{name}_structure": structure}, **({"R_structure": "fixed"} if name == "Q" else {}))


def _wna(dt: float = 0.5, q: float = 0.3) -> torch.Tensor:
    g = torch.tensor([[dt * dt / 2], [dt]], dtype=F64)
    return torch.block_diag(q * g @ g.mT, q * g @ g.mT)


def test_the_semi_definite_white_noise_acceleration_q_is_accepted_by_default() -> None:
    m = {**cv_matrices(), "Q": _wna()}
    model = LinearModel(**m)
    assert isinstance(model.dynamics.parametrizations.Q[0], FactorCovariance)  # a learnable factor of rank 2
    torch.testing.assert_close(model.dynamics.Q, m["Q"], rtol=1e-12, atol=1e-15)
    res = _run(KalmanFilter(model))
    z = res.mean.new_tensor(torch.randn(2, 5, 2, generator=torch.Generator().manual_seed(0), dtype=F64))
    ref, _, _ = numpy_kalman(z[0].numpy(), np.zeros(4), np.eye(4), *(m[k].numpy() for k in "FHQR"))
    np.testing.assert_allclose(res.mean[0].detach().numpy(), ref, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match=r"Q must be positive definite for Q_structure='full'.*Q_structure='factor'"):
        LinearModel(**m, Q_structure="full")


def test_an_indefinite_covariance_is_still_refused_by_name() -> None:
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        LinearModel(**{**cv_matrices(), "Q": -torch.eye(4, dtype=F64)})


# -- angular declarations -----------------------------------------------------------------------
class _Bearing(MeasurementModel):
    """Bearing to the origin from a 4-state CV position; residual wraps, angular declared or not."""

    def __init__(self, declare: bool) -> None:
        super().__init__()
        self.measurement_dim = 1
        self.angular = (0,) if declare else ()
        self.R = torch.full((1, 1), 0.01, dtype=F64)

    def forward(self, x: torch.Tensor, u=None) -> torch.Tensor:  # type: ignore[no-untyped-def]
        return torch.atan2(x[..., 2:3], x[..., 0:1])

    def residual(self, z: torch.Tensor, z_ref: torch.Tensor) -> torch.Tensor:
        return wrap_angle(z - z_ref)


def _bearing_model(declare: bool) -> StateSpaceModel:
    m = cv_matrices()
    return StateSpaceModel(LinearModel(**m).dynamics, _Bearing(declare))


@pytest.mark.parametrize("cls", [UKF, SquareRootUKF])
def test_a_wrapping_residual_without_an_angular_declaration_is_refused(cls) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=r"_Bearing\.residual changes components \[0\].*angular = \(\).*angular = \(0,\)"):
        cls(_bearing_model(declare=False))
    cls(_bearing_model(declare=True))


def test_the_shipped_heading_measurement_declares_its_angle() -> None:
    meas = GnssMeasurement(planar=True, heading=True, dtype=F64)
    assert meas.angular == (meas.measurement_dim - 1,)
