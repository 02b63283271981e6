"""Kalman-family filters sharing one time loop."""

from .base import Belief, FilterResult, GaussianFilter, StepInfo
from .ekf import EKF
from .kalman import KalmanFilter
from .sigma_points import Cubature, Julier, MerweScaled, SigmaPoints
from .ukf import UKF, SimplifiedUKF
from .square_root import SquareRootUKF

__all__ = [
    "EKF",
    "UKF",
    "Belief",
    "Cubature",
    "FilterResult",
    "GaussianFilter",
    "Julier",
    "KalmanFilter",
    "MerweScaled",
    "SigmaPoints",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StepInfo",
]
