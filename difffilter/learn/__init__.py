"""Learning filter parameters by back-propagation through the filter: the Lightning learner, the
trajectory data module (TBPTT windows), losses, metrics, figures and the experiment protocol
(``run_experiment``: hand-tuned vs learned vs oracle).  Generic only: the papers' set-ups live in
:mod:`difffilter.papers`."""

from ..selection import assign_parameters, learnable_values, match_parameters, select_parameters
from .data import TrajectoryDataModule, TrajectorySet, WindowedTrajectories
from .experiment import evaluate_filter, run_experiment
from .learner import FilterLearner
from .losses import CompositeLoss, HuberLoss, LogNormalPrior, MSELoss, NEESLoss, NLLLoss, NormalPrior
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

__all__ = [
    "CompositeLoss",
    "FilterLearner",
    "HuberLoss",
    "LogNormalPrior",
    "MSELoss",
    "NEESLoss",
    "NLLLoss",
    "NormalPrior",
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
