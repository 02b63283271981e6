"""State-space models: interfaces, motion models and navigation models."""

from .base import Controls, DynamicsModel, FunctionalModel, LinearModel, MeasurementModel, StateSpaceModel

__all__ = ["Controls", "DynamicsModel", "FunctionalModel", "LinearModel", "MeasurementModel", "StateSpaceModel"]
