"""p002 (Niu & Lian 2017): GPS + pedestrian dead reckoning fused by the residual-constrained UKF
- the walk simulator and its path, its abrupt heading disturbances, the model factory and the
in-family walks, the "GPS only" / "PDR only" baselines and the sweep table (``experiment=p002_pdr``,
``experiment=p002_infamily``).  The RC-UKF is :class:`difffilter.filters.RCUKF`."""

from .baselines import EstimatorBaseline, gps_only_estimate, gps_only_positions, pdr_only_estimate, pdr_only_positions, position_rmse
from .disturbances import arc_bursts, turn_heading_error
from .experiment import p002_infamily, pdr_model
from .report import PAPER_RMSE, sweep_table
from .simulator import BLOCKAGE_PROBS, PDRScenario, gps_availability, simulate_p002, simulate_p002_random
from .track import Track, TrackSegment, p002_track

__all__ = [
    "BLOCKAGE_PROBS",
    "PAPER_RMSE",
    "EstimatorBaseline",
    "PDRScenario",
    "Track",
    "TrackSegment",
    "arc_bursts",
    "gps_only_estimate",
    "gps_availability",
    "gps_only_positions",
    "p002_infamily",
    "p002_track",
    "pdr_model",
    "pdr_only_estimate",
    "pdr_only_positions",
    "position_rmse",
    "simulate_p002",
    "simulate_p002_random",
    "sweep_table",
    "turn_heading_error",
]
