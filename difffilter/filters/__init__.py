"""Kalman-family filters: the :class:`Filter` contract and the recursive filters sharing one time loop."""

from .adaptive import RCUKF
from .adaptive_noise import AdaptiveNoiseFilter, CovarianceMatching, SageHusa, VBAdaptiveQR, VBAdaptiveR
from .base import Belief, FilterResult, GaussianFilter, RecursiveFilter, StepInfo
from .colored import ColoredNoiseUKF
from .ekf import EKF
from .gated import GatedEKF
from .iterated import IteratedEKF
from .kalman import KalmanFilter
from .parallel import ParallelKalmanFilter
from .protocol import Filter
from .sequential import SequentialUpdate
from .sigma_points import Cubature, Julier, MerweScaled, SigmaPoints
from .square_root import SquareRootUKF
from .ukf import UKF, SimplifiedUKF

__all__ = [
    "AdaptiveNoiseFilter",
    "CovarianceMatching",
    "SageHusa",
    "VBAdaptiveQR",
    "VBAdaptiveR",
    "EKF",
    "GatedEKF",
    "RCUKF",
    "UKF",
    "ColoredNoiseUKF",
    "Belief",
    "Cubature",
    "Filter",
    "FilterResult",
    "GaussianFilter",
    "IteratedEKF",
    "Julier",
    "KalmanFilter",
    "MerweScaled",
    "ParallelKalmanFilter",
    "SequentialUpdate",
    "RecursiveFilter",
    "SigmaPoints",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StepInfo",
]
