"""Generic simulation: draw trajectories from any model (:func:`simulate`) (in-family data,
oracle comparisons), the one trajectory container (:class:`TrajectorySet`) and the signal
helpers the paper simulators share.  The papers' own scenario simulators live in
:mod:`experiments.papers`.
"""

from .sampling import ModelSimulator, SampledTrajectories, sample_trajectories, simulate
from .signals import cumtrapz, moving_average
from .trajectories import TrajectorySet

__all__ = ["ModelSimulator", "SampledTrajectories", "TrajectorySet", "cumtrapz", "moving_average", "sample_trajectories", "simulate"]
