"""Generic simulation: draw trajectories from any model (:func:`simulate`) (in-family data, oracle comparisons) and
the signal helpers the paper simulators share.  The papers' own scenario simulators live in
:mod:`experiments.papers`.
"""

from .sampling import ModelSimulator, SampledTrajectories, sample_trajectories, simulate
from .signals import cumtrapz, moving_average

__all__ = ["ModelSimulator", "SampledTrajectories", "cumtrapz", "moving_average", "sample_trajectories", "simulate"]
