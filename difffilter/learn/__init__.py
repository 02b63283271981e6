"""Learning filter parameters by back-propagation through the filter: the Lightning learner, the
trajectory data module (TBPTT windows), losses, figures, callbacks and checkpoints.  Evaluation
(metrics, consistency, intervals, per-run tables) is :mod:`difffilter.evaluate`; the papers'
studies and the experiment runner live in the research tree (``experiments/``)."""

from ..selection import assign_parameters, learnable_values, match_parameters, select_parameters
from . import replicates  # noqa: F401 - registers the `replicate_seed` resolver of the configs
from .checkpoints import best_checkpoint
from .data import TrajectoryDataModule, TrajectorySet, WindowedTrajectories
from .learner import FilterLearner, load_filter
from .losses import CompositeLoss, HuberLoss, LogNormalPrior, MSELoss, NEESLoss, NLLLoss, NormalPrior, StateNLLLoss

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
    "assign_parameters",
    "best_checkpoint",
    "learnable_values",
    "load_filter",
    "match_parameters",
    "select_parameters",
]
