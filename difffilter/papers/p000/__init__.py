"""p000 (Yang & Zhang): UKF for GPS/DR vehicle positioning - the drive simulator and the
experiment set-up (``experiment=p000_gpsdr``).  The GPS/DR model itself is
:class:`difffilter.models.GpsDrModel`."""

from .experiment import P000Trajectories, p000_simulator
from .simulator import SCRIPTED_DRIVE, GpsDrScenario, simulate_p000

__all__ = ["SCRIPTED_DRIVE", "GpsDrScenario", "P000Trajectories", "p000_simulator", "simulate_p000"]
