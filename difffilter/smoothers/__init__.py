"""Batched, differentiable smoothers on top of the filters: RTS (extended and unscented),
fixed-lag and IMM smoothing, with the filters' conventions (masks, controls, belief carry-over)."""

from .base import Smoother
from .expectations import measurement_residual_moments, previous_smoothed, transition_residual_moments
from .factory import make_smoother, smoother_spec
from .fixed_lag import FixedLagSmoother
from .imm import IMMSmoother
from .iterated import IteratedSmoother, statistical_linearisation
from .parallel import ParallelRTSSmoother
from .result import SmootherResult
from .rts import RTSSmoother, UnscentedRTSSmoother

__all__ = [
    "FixedLagSmoother",
    "IMMSmoother",
    "IteratedSmoother",
    "ParallelRTSSmoother",
    "RTSSmoother",
    "Smoother",
    "SmootherResult",
    "UnscentedRTSSmoother",
    "make_smoother",
    "measurement_residual_moments",
    "previous_smoothed",
    "smoother_spec",
    "statistical_linearisation",
    "transition_residual_moments",
]
