"""difffilter: batched, differentiable Kalman-family filters in PyTorch."""

from . import linalg, mixers, params, smoothers
from .filters import EKF, RCUKF, UKF, ColoredNoiseUKF, GaussianFilter, KalmanFilter, SimplifiedUKF, SquareRootUKF
from .mixers import IMM, Blend
from .models import FunctionalModel, LinearModel, StateSpaceModel

__all__ = [
    "EKF",
    "IMM",
    "RCUKF",
    "UKF",
    "Blend",
    "ColoredNoiseUKF",
    "FunctionalModel",
    "GaussianFilter",
    "KalmanFilter",
    "LinearModel",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StateSpaceModel",
    "linalg",
    "mixers",
    "params",
    "smoothers",
]
__version__ = "0.1.0"
