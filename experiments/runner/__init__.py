"""The experiment runner: train -> evaluate -> report for the Hydra entry points, run status and
resume, sweep summaries."""

from .experiment import run_experiment
from .sweep import SweepSummary, summarize_sweep

__all__ = ["SweepSummary", "run_experiment", "summarize_sweep"]
