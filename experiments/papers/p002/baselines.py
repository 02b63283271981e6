"""p002's baselines that are not Gaussian filters: "GPS only" and "PDR only".

* :class:`EstimatorBaseline` lets an estimator that is a function of the whole measurement record
  appear as a baseline row of :func:`experiments.runner.experiment.run_experiment`: it is a
  :class:`~difffilter.filters.protocol.Filter` (not a recursive one) whose ``forward`` calls
  ``estimator(measurements=, mask=, controls=, initial_mean=, initial_cov=) -> (mean [B, T, n],
  variance [B, T, n])``.  The result's ``log_likelihood`` and ``nis`` are NaN (such estimators
  have no innovation model), so the ``nll``/``nis`` columns read ``nan``; ``rmse`` columns are
  exact, and ``anees`` refers to the estimator's own *nominal* variance.
* :func:`gps_only_positions` / :func:`pdr_only_positions` are p002's "GPS only" and "PDR only"
  rows on a simulated walk; :func:`gps_only_estimate` / :func:`pdr_only_estimate` wrap them as
  estimators with a nominal variance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace

import torch
from torch import Tensor

from difffilter.filters.protocol import Belief, Filter, FilterResult
from difffilter.models.base import Controls, StateSpaceModel
from experiments.papers.p002.model import wrap_angle

from .simulator import PDRScenario

__all__ = [
    "EstimatorBaseline",
    "gps_only_estimate",
    "gps_only_positions",
    "pdr_only_estimate",
    "pdr_only_positions",
    "position_rmse",
]

Estimator = Callable[..., tuple[Tensor, Tensor]]


class EstimatorBaseline(Filter):
    """A whole-trajectory estimator presented as a filter, for baseline rows (see the module docstring).

    ``model`` only fixes the state/measurement dimensions and the dtype check; ``estimator`` gets
    the validated inputs (masked measurements zeroed, ``mask [B, T, m]`` or ``None``,
    ``initial_mean [B, n]``, ``initial_cov [B, n, n]``) and returns ``mean [B, T, n]`` and the
    nominal per-component ``variance [B, T, n]``.  Prior = posterior.  No ``belief=`` carry-over
    (it is not a recursive filter).
    """

    carries_belief = False

    def __init__(self, model: StateSpaceModel, *, estimator: Estimator) -> None:
        super().__init__(model)
        if not callable(estimator):
            raise TypeError(f"estimator must be callable, got {type(estimator).__name__}")
        self.estimator = estimator

    def forward(  # type: ignore[override]
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        if belief is not None:
            raise ValueError("EstimatorBaseline works on whole trajectories: belief= is not supported")
        z, mask3, mean0, cov0 = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if mean0 is None or cov0 is None:
            raise ValueError("initial_mean and initial_cov are required")
        mean, var = self.estimator(measurements=z, mask=mask3, controls=controls, initial_mean=mean0, initial_cov=cov0)
        cov = torch.diag_embed(var)
        bsz, steps = z.shape[:2]
        nan = torch.full((bsz, steps), math.nan, dtype=z.dtype, device=z.device)
        observed = torch.full((bsz, steps), z.shape[-1], device=z.device) if mask3 is None else mask3.sum(-1)
        return FilterResult(
            mean=mean,
            cov=cov,
            prior_mean=mean,
            prior_cov=cov,
            log_likelihood=nan,
            nis=nan,
            num_observed=observed,
            final_belief={"mean": mean[:, -1], "cov": cov[:, -1]},
        )


def _observed_gps(measurements: Tensor, mask: Tensor | None) -> Tensor:
    if mask is None:
        return torch.ones(measurements.shape[:2], dtype=torch.bool, device=measurements.device)
    return mask[..., 0] & mask[..., 1]


def _steps_since_fix(ok: Tensor) -> Tensor:
    """``[B, T]`` steps since the last fix (counted from step -1 before the first one)."""
    steps = ok.shape[1]
    idx = torch.arange(1, steps + 1, device=ok.device).expand_as(ok)
    last = torch.where(ok, idx, torch.zeros_like(idx)).cummax(1).values
    return idx - last


def gps_only_estimate(
    *,
    measurements: Tensor,
    mask: Tensor | None,
    controls: Controls,
    initial_mean: Tensor,
    initial_cov: Tensor,
    gps_std: float = 2.67,
    compass_std_deg: float = 11.4,
) -> tuple[Tensor, Tensor]:
    """p002's "GPS only": the last fix held between fixes (:func:`gps_only_positions`); step length
    held at its initial value, heading = compass.  Nominal variance per axis: ``gps_std^2 +
    (L0 k)^2 / 2`` ``k`` steps after a fix (a walk of unknown direction), the initial variance
    instead of ``gps_std^2`` before the first fix."""
    ok = _observed_gps(measurements, mask)
    initial_cov = initial_cov.expand(ok.shape[0], 4, 4)
    scen = SimpleNamespace(mask=ok[..., None], measurements=measurements, initial_mean=initial_mean)
    pos = gps_only_positions(scen)  # type: ignore[arg-type]
    bsz, steps = ok.shape
    step0 = initial_mean[:, None, 2].expand(bsz, steps)
    k = _steps_since_fix(ok).to(measurements.dtype)
    ever = ok.cummax(1).values
    base = torch.where(ever, torch.full_like(k, gps_std**2), initial_cov[:, None, 0, 0].expand(bsz, steps))
    pvar = base + 0.5 * (step0 * k) ** 2
    heading_var = torch.full_like(k, math.radians(compass_std_deg) ** 2)
    var = torch.stack([pvar, pvar, initial_cov[:, None, 2, 2].expand(bsz, steps), heading_var], -1)
    mean = torch.cat([pos, step0[..., None], measurements[..., 2:3]], -1)
    return mean, var


def pdr_only_estimate(
    *,
    measurements: Tensor,
    mask: Tensor | None,
    controls: Controls,
    initial_mean: Tensor,
    initial_cov: Tensor,
    compass_gain: float = 0.05,
    heading_std_deg: float = 5.0,
    step_scale_std: float = 0.03,
) -> tuple[Tensor, Tensor]:
    """p002's "PDR only": dead reckoning with the accelerometer step lengths and a compass-corrected
    gyro heading (:func:`pdr_only_positions`, gain ``compass_gain``).  Nominal variance per axis
    after a walked distance ``d``: initial variance ``+ ((heading_std d)^2 + (step_scale_std d)^2) / 2``."""
    if not isinstance(controls, dict) or not {"dtheta", "step_length"} <= set(controls):
        raise ValueError("pdr_only_estimate needs controls {'dtheta', 'step_length'} [B, T, 1] (the p002 simulator's)")
    initial_cov = initial_cov.expand(measurements.shape[0], 4, 4)
    scen = SimpleNamespace(controls=controls, measurements=measurements, initial_mean=initial_mean)
    pos, heading = pdr_only_positions(scen, compass_gain=compass_gain)  # type: ignore[arg-type]
    steps = controls["step_length"][..., 0]
    dist = steps.cumsum(1)
    pvar = initial_cov[:, None, 0, 0] + 0.5 * ((math.radians(heading_std_deg) * dist) ** 2 + (step_scale_std * dist) ** 2)
    svar = torch.full_like(dist, step_scale_std**2) * steps**2 + 0.03**2
    var = torch.stack([pvar, pvar, svar, torch.full_like(dist, math.radians(heading_std_deg) ** 2)], -1)
    return torch.cat([pos, steps[..., None], heading[..., None]], -1), var


def gps_only_positions(scenario: PDRScenario) -> Tensor:
    """The "GPS only" row of p002: the last surviving fix held between fixes (the initial-belief
    position before the first one).  Returns ``[B, T, 2]``."""
    ok = scenario.mask[..., 0]
    B, T = ok.shape
    gps = torch.cat([scenario.initial_mean[:, None, :2], torch.nan_to_num(scenario.measurements[..., :2])], 1)
    idx = torch.where(ok, torch.arange(1, T + 1).expand(B, T), torch.zeros(B, T, dtype=torch.long))
    last = idx.cummax(1).values
    return torch.gather(gps, 1, last[..., None].expand(B, T, 2))


def pdr_only_positions(scenario: PDRScenario, *, compass_gain: float = 0.05) -> tuple[Tensor, Tensor]:
    """The "PDR only" row of p002: dead reckoning from the initial-belief position and heading with
    the accelerometer step lengths and a closed-loop heading (gyro increments corrected towards
    the compass with gain ``compass_gain`` per step).

    Returns positions ``[B, T, 2]`` and headings ``[B, T]``.
    """
    dtheta = scenario.controls["dtheta"][..., 0]
    steps = scenario.controls["step_length"][..., 0]
    compass = scenario.measurements[..., 2]
    pos = scenario.initial_mean[:, :2]
    psi = scenario.initial_mean[:, 3]
    positions, headings = [], []
    for k in range(dtheta.shape[1]):
        pos = pos + steps[:, k, None] * torch.stack([torch.sin(psi), torch.cos(psi)], -1)
        psi = psi + dtheta[:, k]
        psi = psi + compass_gain * wrap_angle(compass[:, k] - psi)
        positions.append(pos)
        headings.append(psi)
    return torch.stack(positions, 1), torch.stack(headings, 1)


def position_rmse(estimate: Tensor, truth: Tensor) -> Tensor:
    """Per-run horizontal position RMSE ``sqrt(mean_t |p_hat - p|^2)`` ``[B]`` from
    ``estimate [B, T, >=2]`` and ``truth [B, T, >=2]`` (first two components E, N)."""
    d = estimate[..., :2] - truth[..., :2]
    return torch.sqrt((d * d).sum(-1).mean(-1))
