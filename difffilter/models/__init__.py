"""State-space models: interfaces, motion models, navigation models of the papers, factories for
configs and the state layout every model carries."""

from .affine import TimeVaryingLinearModel
from .base import Controls, DynamicsModel, FunctionalModel, LinearModel, MeasurementModel, StateSpaceModel
from .heteroscedastic import (
    CN0Variance,
    ElevationVariance,
    HeteroscedasticMeasurement,
    MonotoneVariance,
    RobustGate,
    ScaledVariance,
    SideInformationVariance,
    SumVariance,
)
from .layout import ModelDefaults, StateLayout, describe, model_defaults
from .motion import ConstantAcceleration, ConstantVelocity, CurrentStatistical, Singer, singer_process_noise, singer_transition
from .navigation import *  # noqa: F403
from .navigation import __all__ as _navigation_all
from .noise import NonAdditiveModel
from .sensors import MultiSensorMeasurement, SensorGrid, align_streams, event_times
from .tracking import TimeInvariantDynamics, linear_measurement, tracking_model

__all__ = [
    "CN0Variance",
    "ConstantAcceleration",
    "ConstantVelocity",
    "Controls",
    "CurrentStatistical",
    "DynamicsModel",
    "ElevationVariance",
    "FunctionalModel",
    "HeteroscedasticMeasurement",
    "LinearModel",
    "MeasurementModel",
    "MultiSensorMeasurement",
    "NonAdditiveModel",
    "SensorGrid",
    "ModelDefaults",
    "MonotoneVariance",
    "RobustGate",
    "ScaledVariance",
    "SideInformationVariance",
    "Singer",
    "StateLayout",
    "StateSpaceModel",
    "SumVariance",
    "align_streams",
    "event_times",
    "TimeInvariantDynamics",
    "TimeVaryingLinearModel",
    "describe",
    "linear_measurement",
    "model_defaults",
    "singer_process_noise",
    "singer_transition",
    "tracking_model",
    *_navigation_all,
]
