"""p001 (Zou, Zhao, Ding): UKF under coloured measurement noise for static GPS single-point
positioning - the static-receiver simulator, the pseudorange model factory and the experiment
set-up (``experiment=p001_colored``, ``p001_multipath``, ``p001_elevation``), and the
elevation-dependent noise law of the mis-specified family.  The coloured-noise UKF is
:class:`difffilter.filters.ColoredNoiseUKF`."""

from .elevation import ElevationPseudorange, elevation_noise, paper_law
from .experiment import P001Trajectories, p001_simulator, start_learner
from .simulator import LAW_KEYS, P001_CONFIG, P001Scenario, make_p001_model, simulate_p001

__all__ = [
    "LAW_KEYS",
    "P001_CONFIG",
    "ElevationPseudorange",
    "P001Scenario",
    "P001Trajectories",
    "elevation_noise",
    "make_p001_model",
    "p001_simulator",
    "paper_law",
    "simulate_p001",
    "start_learner",
]
