"""Glue between the p000 GPS/DR simulator and the learning stack (``experiment=p000_gpsdr``).

:func:`~experiments.papers.p000.simulator.simulate_p000` returns its initial state and leaves the
initial belief to a method; the data module wants ``initial_mean``/``initial_cov`` attributes.
:func:`p000_simulator` wraps it into :class:`P000Trajectories`, with p000's belief
``X(0|0) = truth at t = 0``, ``P(0|0) = I_8`` (or the diagonal ``initial_std^2``), so a Hydra
``_partial_`` of it is a data-module simulator (``batch_size``, ``seed``, ``dtype`` and the
data module's ``num_steps``).

The truth is p000's scripted or randomised drive, which is *not* drawn from the filter's Singer
model, so there is no oracle parameter set: ``true_params`` is left out on purpose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from difffilter._util import as_dtype
from difffilter.sim import TrajectorySet
from experiments.papers.p000.model import GpsDrModel

from .errors import SensorErrors
from .simulator import GpsDrScenario, simulate_p000

__all__ = ["P000Trajectories", "p000_simulator"]


@dataclass(kw_only=True)
class P000Trajectories(TrajectorySet):
    """p000 trajectories in the data module's layout.

    Attributes:
        truth: ``[B, T, 8]`` ``[s_e, v_e, a_e, s_n, v_n, a_n, eps, psi]``.
        measurements: ``[B, T, 4]`` GPS east/north, gyro, odometer (NaN where masked).
        mask: ``[B, T, 4]`` True = observed.
        initial_mean: ``[B, 8]`` truth at ``t = 0`` (p000: the filter starts at the truth).
        initial_cov: ``[8, 8]``.
        scenario: the simulator's own output (sensor settings, ``make_model``).
    """

    scenario: GpsDrScenario

    def make_model(self, **kwargs: Any) -> GpsDrModel:
        """The hand-tuned p000 model for this data (see :meth:`GpsDrScenario.make_model`)."""
        return self.scenario.make_model(**kwargs)


def p000_simulator(
    *,
    batch_size: int,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    steps: int = 5000,
    scenario: str = "random",
    initial_std: Sequence[float] | None = None,
    gps_outages: Sequence[Sequence[float]] = (),
    errors: Mapping[str, Any] | None = None,
    **options: Any,
) -> P000Trajectories:
    """Simulate p000 drives for learning.

    Args:
        batch_size, seed: as :func:`simulate_p000`.
        dtype: dtype (or its name) of every returned tensor.
        num_steps: overrides ``steps`` (the data module passes it for shortened debug runs).
        steps: samples per trajectory (5000 = p000's 500 s at 0.1 s).
        scenario: ``"straight"``, ``"scripted"`` or ``"random"``.
        initial_std: ``[8]`` standard deviations of ``P(0|0)`` (default p000's ``I_8``).
        gps_outages: ``(start, end)`` windows in seconds without GPS.
        errors: keyword arguments of :class:`~experiments.papers.p000.errors.SensorErrors` (the
            error processes of a mis-specified family; ranges as ``[lo, hi]`` lists); ``None``: none.
        **options: further :func:`simulate_p000` arguments (``g``, ``sigma_gps``, ...).
    """
    dt = as_dtype(dtype)
    data = simulate_p000(
        batch_size=batch_size,
        seed=seed,
        scenario=scenario,
        steps=int(num_steps if num_steps is not None else steps),
        gps_outages=[tuple(w) for w in gps_outages],  # type: ignore[misc]
        errors=None if errors is None else SensorErrors(**{k: tuple(v) if isinstance(v, Sequence) else v for k, v in errors.items()}),
        dtype=dt,
        **options,
    )
    mean0, cov0 = data.initial_belief(None if initial_std is None else list(initial_std))
    return P000Trajectories(
        truth=data.truth,
        measurements=data.measurements,
        mask=data.mask,
        initial_mean=mean0,
        initial_cov=cov0,
        scenario=data,
    )
