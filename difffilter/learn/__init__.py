"""Learning filter parameters by back-propagation through the filter: the Lightning learner, the
trajectory data module (TBPTT windows), losses, metrics, figures and the experiment protocol
(``run_experiment``: hand-tuned vs learned vs oracle), and the non-learned baselines: EM for the
noise covariances (:func:`fit_em`) and validation search over a few knobs (:func:`grid_search`).  Generic only: the papers' set-ups live in
:mod:`difffilter.papers`."""

from ..selection import assign_parameters, learnable_values, match_parameters, select_parameters
from . import replicates  # noqa: F401 - registers the `replicate_seed` resolver of the configs
from .checkpoints import best_checkpoint
from .consistency import Consistency, consistency
from .data import TrajectoryDataModule, TrajectorySet, WindowedTrajectories
from .em import EMResult, fit_em
from .evaluation import evaluate_runs
from .experiment import evaluate_filter, run_experiment
from .intervals import GapClosed, Interval, block_bootstrap_difference, crossed_interval, gap_closed, t_interval
from .learner import FilterLearner, load_filter
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
from .search import SearchResult, grid_search, log_grid, random_search, validation_loss
from .sweep import SweepSummary, summarize_sweep

__all__ = [
    "CompositeLoss",
    "Consistency",
    "EMResult",
    "FilterLearner",
    "GapClosed",
    "HuberLoss",
    "Interval",
    "LogNormalPrior",
    "MSELoss",
    "NEESLoss",
    "NLLLoss",
    "NormalPrior",
    "SearchResult",
    "StateNLLLoss",
    "SweepSummary",
    "TrajectoryDataModule",
    "TrajectorySet",
    "WindowedTrajectories",
    "anees",
    "anis",
    "assign_parameters",
    "best_checkpoint",
    "block_bootstrap_difference",
    "chi2_interval",
    "consistency",
    "crossed_interval",
    "evaluate_filter",
    "evaluate_runs",
    "finalize_metrics",
    "fit_em",
    "gap_closed",
    "grid_search",
    "innovation_whiteness",
    "learnable_values",
    "load_filter",
    "log_grid",
    "match_parameters",
    "metric_sums",
    "mode_switch_delay",
    "nees",
    "nll_per_step",
    "random_search",
    "rmse",
    "run_experiment",
    "select_parameters",
    "summarize_sweep",
    "t_interval",
    "validation_loss",
]
