"""Learning filter parameters by back-propagation through the filter.

Light modules (losses, metrics, parameter selection, builders) import eagerly; the ones that
need PyTorch Lightning (:class:`FilterLearner`, :class:`TrajectoryDataModule`,
:func:`run_experiment`) are imported on first access, so that ``difffilter.sim`` and
``difffilter.learn.metrics`` stay cheap to import.
"""

from __future__ import annotations

import importlib
from typing import Any

from .losses import CompositeLoss, HuberLoss, LogNormalPrior, MSELoss, NEESLoss, NLLLoss, NormalPrior, StateNLLLoss
from .metrics import (
    anees,
    anis,
    chi2_interval,
    finalize_metrics,
    innovation_whiteness,
    metric_sums,
    mode_switch_delay,
    nees,
    nll_per_step,
    rmse,
)
from .selection import assign_parameters, learnable_values, match_parameters, select_parameters

__all__ = [
    "CompositeLoss",
    "FilterLearner",
    "HuberLoss",
    "LogNormalPrior",
    "MSELoss",
    "NEESLoss",
    "NLLLoss",
    "NormalPrior",
    "StateNLLLoss",
    "TrajectoryDataModule",
    "TrajectorySet",
    "WindowedTrajectories",
    "anees",
    "anis",
    "assign_parameters",
    "chi2_interval",
    "evaluate_filter",
    "finalize_metrics",
    "innovation_whiteness",
    "learnable_values",
    "match_parameters",
    "metric_sums",
    "mode_switch_delay",
    "nees",
    "nll_per_step",
    "rmse",
    "run_experiment",
    "select_parameters",
]

_LAZY = {
    "FilterLearner": ".learner",
    "TrajectoryDataModule": ".data",
    "TrajectorySet": ".data",
    "WindowedTrajectories": ".data",
    "evaluate_filter": ".experiment",
    "run_experiment": ".experiment",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
