"""Glue between the p004 GNSS/IMU simulator, the EKF/UKF blend and the learning stack
(``experiment=p004_blend``).

* :func:`p004_simulator` wraps :func:`~experiments.papers.p004.simulator.simulate_p004` into
  :class:`P004Trajectories`, which carries the initial belief the data module expects and the
  simulator's true noise levels as ``true_params`` (the oracle's values).  The truth is the
  scripted drive integrated on a fine grid, the filter integrates the same IMU readings, so the
  filter family contains the truth up to the trapezoidal position step (which ``Q`` absorbs)
  (covered by ``sigma_position_step``); the constant biases are modelled with (nearly) zero random
  walks: an oracle row is meaningful.
  The initial belief is consistent with its covariance: its mean of position, velocity and
  heading is the truth plus a draw from ``N(0, P0)`` (the biases' truth is already a draw from
  their prior around the belief's 0); a belief that starts exactly at the truth while claiming
  1 deg of heading uncertainty makes the weakly observable heading look over-estimated in NEES.
  Optionally the initial heading is unknown (``initial_heading_std_deg``): the heading's
  variance is set to that spread (the alignment case where EKF and UKF can differ).
* :func:`blend_filter` builds the :class:`~difffilter.mixers.blend.Blend` of an EKF and a UKF
  that share *one* model (two Hydra nodes interpolating ``${model}`` would build two models with
  separately learned copies of ``Q`` and ``R``).
* p004's switching statistics (the ``statistics`` of the gate and the switch) are in
  :mod:`experiments.papers.p004.switching`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from difffilter._util import as_dtype, generator
from difffilter.filters.ekf import EKF
from difffilter.filters.sigma_points import SigmaPoints
from difffilter.filters.ukf import UKF
from difffilter.mixers.blend import Blend, Statistics
from difffilter.models.base import StateSpaceModel
from difffilter.sim import TrajectorySet
from experiments.papers.p004.model import GnssImuModel

from .simulator import GnssImuScenario, simulate_p004

__all__ = ["P004Imu", "P004Trajectories", "blend_filter", "gnss_imu_model", "p004_simulator"]


@dataclass(kw_only=True)
class P004Trajectories(TrajectorySet):
    """p004 drives in the data module's layout.

    Attributes:
        truth: ``[B, T, 8]`` planar ``[p_e, p_n, v_e, v_n, psi, b_f, b_l, b_g]`` (3-D: ``[B, T, 16]``).
        measurements: ``[B, T, m]`` GNSS fixes (NaN where masked).
        mask: ``[B, T, m]`` True = observed.
        controls: ``{"accel": [B, T, k], "gyro": [B, T, k]}`` IMU readings.
        initial_mean: ``[B, n]``; initial_cov: ``[n, n]``.
        true_params: the simulator's noise levels by filter parameter name.
        scenario: the simulator's own output.
    """

    scenario: GnssImuScenario
    true_params: dict[str, Any] = field(default_factory=dict)

    def make_model(self, **kwargs: Any) -> GnssImuModel:
        """The filter model with the simulator's true noise levels (see
        :meth:`GnssImuScenario.make_model`)."""
        return self.scenario.make_model(**kwargs)


def _true_params(data: GnssImuScenario) -> dict[str, Any]:
    """The simulator's noise by filter parameter name.  Bias walks only where the truth's biases
    walk (constant biases: the filter keeps its own near-zero walks); nothing about the urban
    canyon's correlated GNSS error, which no white-noise filter represents."""
    p = data.params
    d = 2 if data.planar else 3
    r = [p["sigma_gnss"] ** 2] * d
    if p["velocity"]:
        r += [p["sigma_gnss_velocity"] ** 2] * d
    if p["heading"]:
        r += [p["sigma_heading"] ** 2]
    out: dict[str, Any] = {"sigma_accel": p["sigma_accel"], "sigma_gyro": p["sigma_gyro"], "R": r}
    for name in ("accel", "gyro"):
        if p.get(f"true_{name}_bias_walk", 0.0) > 0.0:
            out[f"sigma_{name}_bias_walk"] = p[f"true_{name}_bias_walk"]
    return out


def p004_simulator(
    *,
    batch_size: int,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype | str = torch.float64,
    randomize: bool = False,
    planar: bool = True,
    gnss_outages: Sequence[Sequence[float]] = (),
    initial_heading_std_deg: float | None = None,
    initial_error: bool = True,
    **options: Any,
) -> P004Trajectories:
    """Simulate p004 drives for learning.

    Args:
        batch_size, seed: as :func:`simulate_p004`.
        dtype: dtype (or its name) of every returned tensor.
        randomize: randomised drives (training sets) instead of the fixed p004 script.
        planar: planar 8-state layout (else the 16-state quaternion one).
        gnss_outages: ``(start, end)`` windows in seconds without GNSS.
        initial_heading_std_deg: if given, the initial belief's heading variance is ``std^2``
            (else the simulator's 1 deg, p004's azimuth error).
        initial_error: draw the belief's mean of position, velocity and heading (3-D: position
            and velocity) from ``N(truth, P0)``; ``False``: the mean is the truth (biases 0).
        **options: further :func:`simulate_p004` arguments (``velocity``, noise levels,
            ``bias_walk``, ``canyon_windows``...).
    """
    dt = as_dtype(dtype)
    gen = generator(seed)
    data = simulate_p004(
        batch_size=batch_size,
        seed=gen,
        randomize=randomize,
        planar=planar,
        gnss_outages=[tuple(w) for w in gnss_outages],  # type: ignore[misc]
        dtype=dt,
        **options,
    )
    if not isinstance(initial_error, bool):
        raise TypeError(f"initial_error must be a bool, got {type(initial_error).__name__}")
    mean0, cov0 = data.initial_belief()
    mean0, cov0 = mean0.clone(), cov0.clone()
    if initial_heading_std_deg is not None:
        if not planar:
            raise ValueError("initial_heading_std_deg needs the planar layout (heading is a state there)")
        std = math.radians(float(initial_heading_std_deg))
        if not (math.isfinite(std) and std > 0.0):
            raise ValueError(f"initial_heading_std_deg must be positive, got {initial_heading_std_deg}")
        cov0[4, 4] = std * std
    if initial_error or initial_heading_std_deg is not None:
        k = 5 if planar else 6  # [p, v, psi] / [p, v] (the quaternion keeps the truth)
        std0 = cov0.diagonal()[:k].to(torch.float64).sqrt()
        err = std0 * torch.randn(batch_size, k, generator=gen, dtype=torch.float64)
        if not initial_error:  # only the unknown heading
            err[:, :4] = 0.0
        mean0[:, :k] = mean0[:, :k] + err.to(dt)
    return P004Trajectories(
        truth=data.truth,
        measurements=data.measurements,
        mask=data.mask,
        controls=data.controls,
        initial_mean=mean0,
        initial_cov=cov0,
        scenario=data,
        true_params=_true_params(data),
    )


def blend_filter(
    *,
    model: StateSpaceModel,
    sigma_points: SigmaPoints | None = None,
    redraw_after_predict: bool = True,
    mode: str = "fixed",
    delta: float = 0.85,
    statistics: Statistics | None = None,
    thresholds: Sequence[float] = (3.0, 0.1),
    temperature: float | Sequence[float] = 0.1,
    spread: bool = False,
) -> Blend:
    """:class:`~difffilter.mixers.blend.Blend` of ``EKF(model)`` and ``UKF(model, sigma_points)``
    on the same ``model`` object (one set of learnable ``Q``/``R``); other arguments as
    :class:`Blend`."""
    temps = float(temperature) if isinstance(temperature, int | float) else tuple(float(t) for t in temperature)
    return Blend(
        EKF(model),
        UKF(model, sigma_points=sigma_points, redraw_after_predict=redraw_after_predict),
        mode=mode,
        delta=delta,
        statistics=statistics,
        thresholds=(float(thresholds[0]), float(thresholds[1])),
        temperature=temps,  # type: ignore[arg-type]
        spread=spread,
    )


class P004Imu:
    """In-family inputs of the GNSS/IMU model: ``(batch_size, num_steps, generator, dtype) ->
    {"accel", "gyro"}``, the IMU readings of randomised p004 drives (:func:`simulate_p004`,
    at most 400 steps of 1 s)."""

    def __init__(self, *, planar: bool) -> None:
        self.planar = bool(planar)

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        data = simulate_p004(batch_size=batch_size, seed=gen, randomize=True, planar=self.planar, dtype=dtype)
        if num_steps > data.measurements.shape[1]:
            raise ValueError(f"num_steps must be at most {data.measurements.shape[1]} (p004's drive), got {num_steps}")
        return {k: v[:, :num_steps] for k, v in data.controls.items()}


def gnss_imu_model(**options: Any) -> GnssImuModel:
    """:class:`~experiments.papers.p004.model.GnssImuModel` (``options`` as its keywords) whose defaults draw
    in-family IMU readings from p004's randomised drives (:class:`P004Imu`), for configs."""
    model = GnssImuModel(**options)
    model.defaults = dataclasses.replace(model.defaults, controls=P004Imu(planar=bool(options.get("planar", False))))
    return model
