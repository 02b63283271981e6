"""Learning filter parameters by back-propagation through the filter: the Lightning learner, the
trajectory data module (TBPTT windows), losses, figures, callbacks and checkpoints, and the
baselines that need no back-propagation: EM for the noise covariances (:func:`fit_em`) and
validation search over a few knobs (:func:`grid_search`, :func:`random_search`).  Evaluation
(metrics, consistency, intervals, per-run tables) is :mod:`difffilter.evaluate`; the papers'
studies and the experiment runner live in the research tree (``experiments/``)."""

from ..selection import assign_parameters, learnable_values, match_parameters, select_parameters
from . import replicates  # noqa: F401 - registers the `replicate_seed` resolver of the configs
from .checkpoints import best_checkpoint
from .data import TrajectoryDataModule, TrajectorySet, WindowedTrajectories
from .em import EMResult, fit_em
from .learner import FilterLearner, LearnerOptions, load_filter
from .losses import CompositeLoss, HuberLoss, LogNormalPrior, LogPrior, MSELoss, NEESLoss, NLLLoss, NormalPrior, StateNLLLoss
from .plots import DiagnosticFigures
from .search import SearchResult, grid_search, log_grid, random_search, validation_loss

__all__ = [
    "CompositeLoss",
    "DiagnosticFigures",
    "EMResult",
    "FilterLearner",
    "HuberLoss",
    "LearnerOptions",
    "LogNormalPrior",
    "LogPrior",
    "MSELoss",
    "NEESLoss",
    "NLLLoss",
    "NormalPrior",
    "SearchResult",
    "StateNLLLoss",
    "TrajectoryDataModule",
    "TrajectorySet",
    "WindowedTrajectories",
    "assign_parameters",
    "best_checkpoint",
    "fit_em",
    "grid_search",
    "learnable_values",
    "load_filter",
    "log_grid",
    "match_parameters",
    "random_search",
    "select_parameters",
    "validation_loss",
]
