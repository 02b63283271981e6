"""difffilter: batched, differentiable Kalman-family filters in PyTorch."""

# _openmp first: it sets OpenMP's wait policy before anything imports torch;
# engines: registers the DIFFFILTER_ENGINE policy every plain filter call asks
from . import (
    _openmp,  # noqa: F401
    engines,
    filters,
    func,
    linalg,
    mixers,
    models,
    params,
    sim,
    smoothers,
)
from ._util import as_dtype, document_init
from .filters import (
    EKF,
    RCUKF,
    UKF,
    ColoredNoiseUKF,
    Filter,
    GaussianFilter,
    KalmanFilter,
    ParallelKalmanFilter,
    RecursiveFilter,
    SimplifiedUKF,
    SquareRootUKF,
)
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
    "ParallelKalmanFilter",
    "RecursiveFilter",
    "SimplifiedUKF",
    "SquareRootUKF",
    "StateSpaceModel",
    "as_dtype",
    "engines",
    "func",
    "linalg",
    "mixers",
    "params",
    "smoothers",
]
__version__ = "0.2.0.dev0"

# help(UKF.__init__) shows UKF's arguments, not the text nn.Module.__init__ would pass on
document_init(getattr(m, name) for m in (filters, mixers, models, params, sim, smoothers) for name in m.__all__)
