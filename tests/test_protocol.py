"""The Filter contract: recursive filters, mixers and the papers' baselines all satisfy it; only the
recursive ones are RecursiveFilters; every one runs the base constructor."""

from __future__ import annotations

import pytest
import torch

from difffilter.filters import UKF, Filter, GaussianFilter, KalmanFilter, RecursiveFilter
from difffilter.filters.protocol import Filter as ProtocolFilter
from difffilter.mixers import IMM, Blend
from difffilter.models import LinearModel
from experiments.papers.p002 import EstimatorBaseline, gps_only_estimate, pdr_model

F64 = torch.float64


def _cv() -> LinearModel:
    f = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    return LinearModel(F=f, H=torch.tensor([[1.0, 0.0]], dtype=F64), Q=0.1 * torch.eye(2, dtype=F64), R=torch.eye(1, dtype=F64))


def test_every_estimator_is_a_filter_and_only_recursive_ones_are_recursive():
    kf = KalmanFilter(_cv())
    imm = IMM(
        [kf, KalmanFilter(_cv())], transition=torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=F64), initial_probs=torch.tensor([0.5, 0.5])
    )
    model = pdr_model(Q_std=[0.06, 0.06, 0.01, 0.5], R_std=[2.67, 2.67, 11.4])
    baseline = EstimatorBaseline(model, estimator=gps_only_estimate)
    assert GaussianFilter is RecursiveFilter and Filter is ProtocolFilter
    for f in (kf, imm, Blend(model, model), UKF(model), baseline):
        assert isinstance(f, Filter)
    assert isinstance(imm, RecursiveFilter) and not isinstance(baseline, RecursiveFilter)
    assert imm.carries_belief and not baseline.carries_belief
    z = torch.zeros(2, 4, 3, dtype=F64)
    with pytest.raises(ValueError, match="belief"):
        baseline(z, belief={"mean": torch.zeros(2, 4, dtype=F64), "cov": torch.eye(4, dtype=F64).expand(2, 4, 4)})


def test_imm_runs_the_base_constructor(monkeypatch):
    calls = []
    original = ProtocolFilter.__init__

    def spy(self, model=None):  # noqa: ANN001, ANN202
        calls.append(type(self).__name__)
        original(self, model)

    monkeypatch.setattr(ProtocolFilter, "__init__", spy)
    IMM([KalmanFilter(_cv()), KalmanFilter(_cv())], transition=torch.eye(2, dtype=F64) * 0.8 + 0.1, initial_probs=torch.tensor([0.5, 0.5]))
    assert calls.count("IMM") == 1 and calls.count("KalmanFilter") == 2


def test_the_contract_rejects_what_it_cannot_run():
    with pytest.raises(TypeError, match="StateSpaceModel"):
        ProtocolFilter(model=torch.nn.Linear(2, 2))  # type: ignore[arg-type]
    with pytest.raises(NotImplementedError):
        ProtocolFilter(model=_cv())(torch.zeros(1, 3, 1, dtype=F64), torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(AttributeError):
        _ = ProtocolFilter().state_dim  # no model: a combining filter must define its dimensions
