"""Navigation models of the five papers, gathered in one namespace.

Each model lives in its own module (one concept per file); this module re-exports them:

* :mod:`.gpsdr` - p000 GPS/dead-reckoning (Singer / current-statistical manoeuvre model, GPS
  position, gyro yaw rate, odometer).
* :mod:`.pseudorange` - pseudorange (+ rate) measurements with clock bias/drift, inter-system
  bias and Sagnac term (p001, p003, the smartLoc drive), and matching clock dynamics.
* :mod:`.pdr` - p002 pedestrian dead-reckoning step model with GPS and compass.
* :mod:`.sins` - p003 20-state GPS/SINS ultra-tight error model.
* :mod:`.gnss_imu` - p004 GNSS/IMU vehicle model.
"""

from .gnss_imu import GnssImuDynamics, GnssImuModel, GnssMeasurement, PlanarGnssImuDynamics, p004_switching_statistics
from .gpsdr import GpsDrDynamics, GpsDrMeasurement, GpsDrModel
from .pdr import PDRMeasurement, PDRModel, PDRStepDynamics
from .pseudorange import ConstantVelocityClock, GnssStateLayout, OdometryClockDynamics, PseudorangeMeasurement
from .sins import SinsErrorDynamics, SinsPseudorangeMeasurement

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
    "PDRMeasurement",
    "PDRModel",
    "PDRStepDynamics",
    "PlanarGnssImuDynamics",
    "PseudorangeMeasurement",
    "SinsErrorDynamics",
    "SinsPseudorangeMeasurement",
    "p004_switching_statistics",
]
