"""difffilter: batched, differentiable Kalman-family filters in PyTorch."""

from . import linalg, params
from .filters import EKF, UKF, GaussianFilter, KalmanFilter, SimplifiedUKF, SquareRootUKF
from .models import FunctionalModel, LinearModel, StateSpaceModel

__all__ = [
    "EKF",
    "UKF",
    "FunctionalModel",
    "GaussianFilter",
    "KalmanFilter",
    "LinearModel",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StateSpaceModel",
    "linalg",
    "params",
]
__version__ = "0.1.0"
