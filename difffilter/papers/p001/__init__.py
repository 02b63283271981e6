"""p001 (Zou, Zhao, Ding): UKF under coloured measurement noise for static GPS single-point
positioning - the static-receiver simulator, the pseudorange model factory and the experiment
set-up (``experiment=p001_colored``).  The coloured-noise UKF is
:class:`difffilter.filters.ColoredNoiseUKF`."""

from .experiment import P001Trajectories, p001_simulator, start_learner
from .simulator import P001_CONFIG, P001Scenario, make_p001_model, simulate_p001

__all__ = ["P001_CONFIG", "P001Scenario", "P001Trajectories", "make_p001_model", "p001_simulator", "simulate_p001", "start_learner"]
