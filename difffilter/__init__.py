"""difffilter: batched, differentiable Kalman-family filters in PyTorch."""

from . import linalg, mixers, params, smoothers
from ._util import as_dtype
from .filters import EKF, RCUKF, UKF, ColoredNoiseUKF, Filter, GaussianFilter, KalmanFilter, RecursiveFilter, SimplifiedUKF, SquareRootUKF
from .mixers import IMM, Blend
from .models import FunctionalModel, LinearModel, StateSpaceModel

__all__ = [
    "EKF",
    "IMM",
    "RCUKF",
    "UKF",
    "Blend",
    "ColoredNoiseUKF",
    "Filter",
    "FunctionalModel",
    "GaussianFilter",
    "KalmanFilter",
    "LinearModel",
    "RecursiveFilter",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StateSpaceModel",
    "as_dtype",
    "linalg",
    "mixers",
    "params",
    "smoothers",
]
__version__ = "0.1.0"
