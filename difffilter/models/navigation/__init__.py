"""Navigation models, gathered in one namespace.

Each model lives in its own module (one concept per file); this package re-exports them:

* :mod:`.pseudorange` - pseudorange (+ rate) measurements with clock bias/drift, inter-system
  bias and Sagnac term (p001, the smartLoc drive); :mod:`.clock` - the receiver dynamics that
  go with them.
* :mod:`.ranging2d` - 2-D ranging to fixed anchors with odometry (range bias, noise scale, robust gate).
* :mod:`.ranging3d` - 3-D ranging to fixed anchors, with 3-D odometry or the library's constant
  velocity (:class:`~difffilter.models.motion.ConstantVelocity`).
"""

from .clock import ConstantVelocityClock, OdometryClockDynamics, clock_process_noise
from .pseudorange import GnssStateLayout, PseudorangeMeasurement
from .ranging2d import OdometryDynamics2D, RangeMeasurement2D, make_ranging_model, multilateration
from .ranging3d import OdometryDynamics3D, RangeMeasurement3D, make_ranging3d_model

__all__ = [
    "ConstantVelocityClock",
    "GnssStateLayout",
    "OdometryClockDynamics",
    "OdometryDynamics2D",
    "OdometryDynamics3D",
    "PseudorangeMeasurement",
    "RangeMeasurement2D",
    "RangeMeasurement3D",
    "clock_process_noise",
    "make_ranging3d_model",
    "make_ranging_model",
    "multilateration",
]

# The papers' own vehicle models live beside their studies: p000's GPS/dead reckoning in
# experiments/papers/p000/model.py, p002's pedestrian dead reckoning in
# experiments/papers/p002/model.py, p004's GNSS/IMU vehicle in experiments/papers/p004/model.py,
# p003's GPS/SINS error-state model in experiments/papers/p003/sins.py and sins_measurement.py.
