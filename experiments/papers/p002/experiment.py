"""p002 (Niu & Lian 2017, GPS + PDR fused by the RC-UKF): the model factory of
``experiment=p002_pdr`` and the in-family walks of ``experiment=p002_infamily``."""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from difffilter._util import as_dtype, generator
from difffilter.selection import assign_parameters
from difffilter.sim.sampling import SampledTrajectories, sample_trajectories
from experiments.papers.p002.model import PDRModel

from .simulator import gps_availability, simulate_p002_random

__all__ = ["P002Steps", "p002_infamily", "pdr_model"]


def pdr_model(
    *,
    Q_std: Sequence[float],
    R_std: Sequence[float],
    Q_structure: str = "diagonal",
    R_structure: str = "diagonal",
    dtype: torch.dtype | str = "float64",
) -> PDRModel:
    """p002's PDR model from standard deviations.

    Args:
        Q_std: per-step process noise ``[E m, N m, L m, theta deg]``.
        R_std: ``[GPS east m, GPS north m, compass deg]``.
        Q_structure, R_structure: learnable structure (``"diagonal"``...).
        dtype: ``"float64"`` or a torch dtype.
    """
    dt = as_dtype(dtype)
    q = torch.as_tensor(list(Q_std), dtype=dt).clone()
    r = torch.as_tensor(list(R_std), dtype=dt).clone()
    if q.shape != (4,) or r.shape != (3,):
        raise ValueError(f"Q_std needs 4 and R_std 3 entries, got {tuple(q.shape)}, {tuple(r.shape)}")
    q[3], r[2] = math.radians(float(q[3])), math.radians(float(r[2]))
    model = PDRModel(Q=torch.diag(q * q), R=torch.diag(r * r), Q_structure=Q_structure, R_structure=R_structure, dtype=dt)
    model.defaults = dataclasses.replace(model.defaults, controls=P002Steps())
    return model


class P002Steps:
    """In-family inputs of the PDR model: ``(batch_size, num_steps, generator, dtype) ->
    {"dtheta", "dt", "step_length"}`` of randomised p002 walks (:func:`simulate_p002_random`)."""

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        return simulate_p002_random(batch_size, seed=gen, dtype=dtype, num_steps=num_steps).controls


def p002_infamily(
    *,
    model: PDRModel,
    batch_size: int,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype | str = "float64",
    num_steps: int = 514,
    true_params: Mapping[str, Any] | None = None,
    blockage_prob: float = 0.4,
    cold_start: float = 5.0,
    gps_interval: float = 1.0,
    outage_window: float = 5.0,
) -> SampledTrajectories:
    """In-family p002 walks: states and measurements drawn from the filter's own PDR model (a copy
    with ``true_params`` set) driven by the gyro increments and step timing of randomised p002
    walks (:func:`simulate_p002_random`), with p002's GPS availability: a fix every
    ``gps_interval`` seconds from ``cold_start`` on, 5 s windows blocked with probability
    ``blockage_prob`` (:func:`gps_availability`); the compass is read at every step.  The belief
    before the first step is the model's default (``model.defaults``), from which the initial state
    is drawn, so the filter with ``true_params`` is the oracle (``true_params`` of the result)."""
    gen = generator(seed)
    walks = simulate_p002_random(batch_size, seed=gen, dtype=torch.float64, num_steps=num_steps)
    truth_model = copy.deepcopy(model).to(torch.float64)
    if true_params:
        assign_parameters(truth_model, dict(true_params))
    defaults = truth_model.defaults
    data = sample_trajectories(
        truth_model,
        batch_size=batch_size,
        num_steps=num_steps,
        initial_mean=list(defaults.initial_mean),
        initial_cov=list(defaults.initial_var),
        seed=gen,
        dtype=torch.float64,
        controls=walks.controls,
    )
    times = torch.cat([torch.zeros(batch_size, 1, dtype=torch.float64), walks.controls["dt"][..., 0].cumsum(1)], 1)
    probs = torch.full((batch_size,), float(blockage_prob), dtype=torch.float64)
    cold = torch.full((batch_size,), float(cold_start), dtype=torch.float64)
    gps_ok, _ = gps_availability(gen, times, cold, probs, gps_interval=gps_interval, outage_window=outage_window)
    mask = torch.stack([gps_ok, gps_ok, torch.ones_like(gps_ok)], -1)
    z = torch.where(mask, data.measurements, torch.full_like(data.measurements, float("nan")))
    out = as_dtype(dtype)
    cast = {k: v.to(out) for k, v in walks.controls.items()}
    return dataclasses.replace(
        data,
        measurements=z.to(out),
        mask=mask,
        truth=data.truth.to(out),
        controls=cast,
        initial_mean=data.initial_mean.to(out),
        initial_cov=data.initial_cov.to(out),
        initial_state=data.initial_state.to(out),
        true_params={k: v.to(out) for k, v in data.true_params.items()},
    )
