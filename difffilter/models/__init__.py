"""State-space models: interfaces, motion models and navigation models."""

from .base import Controls, DynamicsModel, FunctionalModel, LinearModel, MeasurementModel, StateSpaceModel
from .motion import ConstantAcceleration, ConstantVelocity, CurrentStatistical, Singer, singer_process_noise, singer_transition
from .navigation import *  # noqa: F403
from .navigation import __all__ as _navigation_all
from .noise import NonAdditiveModel
from .sensors import MultiSensorMeasurement, SensorGrid, align_streams, event_times

__all__ = [
    "ConstantAcceleration",
    "ConstantVelocity",
    "Controls",
    "CurrentStatistical",
    "DynamicsModel",
    "FunctionalModel",
    "LinearModel",
    "MeasurementModel",
    "MultiSensorMeasurement",
    "NonAdditiveModel",
    "SensorGrid",
    "Singer",
    "StateSpaceModel",
    "align_streams",
    "event_times",
    "singer_process_noise",
    "singer_transition",
    *_navigation_all,
]
