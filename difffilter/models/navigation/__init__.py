"""Navigation models of the papers, gathered in one namespace.

Each model lives in its own module (one concept per file); this package re-exports them:

* :mod:`.gpsdr` - p000 GPS/dead-reckoning (Singer / current-statistical manoeuvre model, GPS
  position, gyro yaw rate, odometer).
* :mod:`.pseudorange` - pseudorange (+ rate) measurements with clock bias/drift, inter-system
  bias and Sagnac term (p001, the smartLoc drive); :mod:`.clock` - the receiver dynamics that
  go with them.
* :mod:`.pdr` - p002 pedestrian dead-reckoning step model with GPS and compass.
* :mod:`.sins`, :mod:`.sins_measurement` - p003 20-state GPS/SINS ultra-tight error model.
* :mod:`.gnss_imu` - p004 GNSS/IMU vehicle model.
* :mod:`.ranging2d` - 2-D ranging to fixed anchors with odometry (range bias, noise scale, robust gate).
"""

from .clock import ConstantVelocityClock, OdometryClockDynamics, clock_process_noise
from .gnss_imu import GnssImuDynamics, GnssImuModel, GnssMeasurement, PlanarGnssImuDynamics
from .gpsdr import GpsDrDynamics, GpsDrMeasurement, GpsDrModel
from .pdr import PDRMeasurement, PDRModel, PDRStepDynamics
from .pseudorange import GnssStateLayout, PseudorangeMeasurement
from .ranging2d import OdometryDynamics2D, RangeMeasurement2D, make_ranging_model, multilateration
from .sins import SinsErrorDynamics
from .sins_measurement import SinsPseudorangeMeasurement

__all__ = [
    "ConstantVelocityClock",
    "GnssImuDynamics",
    "GnssImuModel",
    "GnssMeasurement",
    "GnssStateLayout",
    "GpsDrDynamics",
    "GpsDrMeasurement",
    "GpsDrModel",
    "OdometryClockDynamics",
    "OdometryDynamics2D",
    "PDRMeasurement",
    "PDRModel",
    "PDRStepDynamics",
    "PlanarGnssImuDynamics",
    "PseudorangeMeasurement",
    "RangeMeasurement2D",
    "SinsErrorDynamics",
    "SinsPseudorangeMeasurement",
    "clock_process_noise",
    "make_ranging_model",
    "multilateration",
]
