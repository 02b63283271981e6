"""Evaluating filters: metrics (RMSE, NEES, NIS, NLL), consistency bands, confidence intervals
(paired t, block bootstrap, gap closed) and per-run tables.  The real-data protocol built on them
(blocked folds, validation-based selection) is the research tree's ``experiments.holdout``."""

from .consistency import Consistency, consistency
from .evaluation import evaluate_filter, evaluate_runs
from .intervals import GapClosed, Interval, block_bootstrap_difference, crossed_interval, gap_closed, t_interval
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
    "Consistency",
    "GapClosed",
    "Interval",
    "anees",
    "anis",
    "block_bootstrap_difference",
    "chi2_interval",
    "consistency",
    "crossed_interval",
    "evaluate_filter",
    "evaluate_runs",
    "finalize_metrics",
    "gap_closed",
    "innovation_whiteness",
    "metric_sums",
    "mode_switch_delay",
    "nees",
    "nll_per_step",
    "rmse",
    "t_interval",
]
