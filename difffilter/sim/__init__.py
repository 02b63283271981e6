"""Seeded, batched scenario simulators for the five papers, the smartLoc real-data loader and
synthetic pseudoranges on the smartLoc geometry.

Every simulator returns truth, measurements, masks (True = observed) and per-step controls as
tensors ready for ``filter(measurements, initial_mean, initial_cov, mask=..., controls=...)``.
Imports are lazy so that ``import difffilter.sim`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "simulate_p000": ".p000_gpsdr",
    "GpsDrScenario": ".p000_gpsdr",
    "simulate_p001": ".p001_static",
    "make_p001_model": ".p001_static",
    "P001Scenario": ".p001_static",
    "simulate_p002": ".p002_pdr",
    "simulate_p002_random": ".p002_pdr",
    "PDRScenario": ".p002_pdr",
    "gps_only_positions": ".p002_pdr",
    "pdr_only_positions": ".p002_pdr",
    "p002_track": ".tracks",
    "simulate_p003": ".p003_flight",
    "make_p003_model": ".p003_flight",
    "P003Scenario": ".p003_flight",
    "PAPER_PHASES": ".p003_flight",
    "simulate_p004": ".p004_vehicle",
    "GnssImuScenario": ".p004_vehicle",
    "load_smartloc": ".smartloc",
    "SmartLocData": ".smartloc",
    "single_epoch_wls": ".smartloc",
    "make_smartloc_model": ".smartloc",
    "smartloc_initial_belief": ".smartloc",
    "PseudorangeErrorModel": ".smartloc_synthetic",
    "calibrate_error_model": ".smartloc_synthetic",
    "simulate_smartloc_drives": ".smartloc_synthetic",
    "synthetic_drive": ".smartloc_synthetic",
    "sample_trajectories": ".sampling",
    "ModelSimulator": ".sampling",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
