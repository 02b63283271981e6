"""p004 (Li, Zhu, Wang & Lyu): adaptive EKF/UKF switching for vehicle GNSS/IMU - the drive
simulator, the switching statistics, the experiment set-up (``experiment=p004_blend``) and the
paired comparison.  The GNSS/IMU model is :class:`~experiments.papers.p004.model.GnssImuModel` (model.py), the blend
:class:`difffilter.mixers.Blend`."""

from .experiment import P004Imu, P004Trajectories, blend_filter, gnss_imu_model, p004_simulator
from .paired import paired_report, per_run_errors
from .simulator import P004_SPEED_KNOTS, P004_TURNS, GnssImuScenario, simulate_p004
from .switching import ImuSwitchingStatistics, imu_switching_statistics, switching_statistics

__all__ = [
    "P004_SPEED_KNOTS",
    "P004_TURNS",
    "GnssImuScenario",
    "ImuSwitchingStatistics",
    "P004Imu",
    "P004Trajectories",
    "blend_filter",
    "gnss_imu_model",
    "imu_switching_statistics",
    "p004_simulator",
    "paired_report",
    "per_run_errors",
    "simulate_p004",
    "switching_statistics",
]
