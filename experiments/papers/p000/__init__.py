"""p000 (Yang & Zhang): UKF for GPS/DR vehicle positioning - the drive simulator, the sensor error
processes of its mis-specified scenario families, the paper's literal UKF, the sigma_a sweep of
its EKF-vs-UKF comparison and the experiment set-up (``experiment=p000_gpsdr``,
``experiment=p000_infamily``).  The GPS/DR model itself is :class:`~experiments.papers.p000.model.GpsDrModel` (model.py)."""

from .errors import SensorErrors, gauss_markov, random_windows
from .experiment import P000Trajectories, p000_simulator
from .filters import LiteralReuseUKF
from .sigma_sweep import SIGMAS, per_axis_metrics, sigma_sweep, sweep_table
from .simulator import SCRIPTED_DRIVE, GpsDrScenario, simulate_p000

__all__ = [
    "SCRIPTED_DRIVE",
    "SIGMAS",
    "GpsDrScenario",
    "LiteralReuseUKF",
    "P000Trajectories",
    "SensorErrors",
    "gauss_markov",
    "p000_simulator",
    "per_axis_metrics",
    "random_windows",
    "sigma_sweep",
    "simulate_p000",
    "sweep_table",
]
