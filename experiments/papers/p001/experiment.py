"""Glue between the p001 static-receiver simulator and the learning stack (``experiment=p001_colored``).

:func:`~experiments.papers.p001.simulator.simulate_p001` returns a :class:`P001Scenario` without the
``true_params`` an oracle needs.  :func:`p001_simulator` wraps it into :class:`P001Trajectories`
(a data-module simulator through a Hydra ``_partial_``: ``batch_size``, ``seed``, ``dtype`` and
the data module's ``num_steps``) whose ``true_params`` name the filter's parameters:

* ``psi`` - the AR(1) coefficient of the pseudorange noise (0.7),
* ``R`` - the variance of the white driving noise ``eta`` per satellite (``[K]``, 9 m^2),
* the same noise as the elevation law's values (``sigma_zenith``, ``tau_zenith``, exponents 0;
  :func:`~experiments.papers.p001.elevation.paper_law`), or, under an elevation-dependent noise
  (``config["elevation_noise"]``), only the law's four values,
* ``clock_bias_psd``, ``clock_drift_psd`` - the simulator's receiver clock random walk,
* ``accel_psd`` - the receiver does not move, so the true acceleration PSD is zero; the filter's
  ``Positive`` constraint needs a positive value, hence ``static_accel_psd`` (1e-10 m^2/s^3).

:func:`start_learner` builds a :class:`~difffilter.learn.learner.FilterLearner` whose filter copy
starts from other values than the hand-tuned ones (``start_params``), e.g. the learned
"from Psi = 0" run of p001: the hand-tuned row keeps the paper's known Psi = 0.7 while the
learner starts from the standard UKF's white-noise assumption.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from difffilter._util import as_dtype
from difffilter.filters.protocol import Filter
from difffilter.learn.learner import FilterLearner
from difffilter.selection import assign_parameters
from difffilter.sim import TrajectorySet

from .elevation import paper_law
from .simulator import LAW_KEYS, P001Scenario, make_p001_model, simulate_p001

__all__ = ["P001Trajectories", "p001_simulator", "start_learner"]


@dataclass(kw_only=True)
class P001Trajectories(TrajectorySet):
    """p001 epochs in the data module's layout.

    Attributes:
        truth: ``[B, T, 8]`` ``[p (3, offset from the known point), v (3, zero), clock bias, drift]``.
        measurements: ``[B, T, K]`` reduced pseudoranges.
        mask: ``[B, T, K]`` (all True).
        controls: ``sat_pos [B, T, K, 3]``, ``dt [B, T, 1]``.
        initial_mean: ``[B, 8]`` truth at ``t_0`` perturbed (10 m position, clock drawn from P0).
        initial_cov: ``[8, 8]`` P0 of the paper file.
        true_params: the simulator's noise parameters in the filter's names (module doc).
        scenario: the simulator's own output.
    """

    true_params: dict[str, Any]
    scenario: P001Scenario
    model_options: dict[str, Any] = field(default_factory=dict)

    def make_model(self) -> torch.nn.Module:
        """The p001 CV + clock pseudorange model with the true ``R``/``Q`` of this data (its
        elevation law under an elevation-dependent noise)."""
        tp = self.true_params
        law = self.scenario.config.get("elevation_noise")
        return make_p001_model(
            num_satellites=int(self.measurements.shape[-1]),
            dt=float(self.scenario.dt),
            eta_sigma=None if law else float(tp["R"][0]) ** 0.5,
            elevation_noise={n: tp[n] for n in LAW_KEYS} if law else None,
            accel_psd=float(tp["accel_psd"]),
            clock_bias_psd=float(tp["clock_bias_psd"]),
            clock_drift_psd=float(tp["clock_drift_psd"]),
            dtype=self.measurements.dtype,
            **self.model_options,
        )


def p001_simulator(
    *,
    batch_size: int,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    num_epochs: int = 100,
    randomize: bool = False,
    num_satellites: int = 7,
    config: Mapping[str, Any] | None = None,
    static_accel_psd: float = 1e-10,
) -> P001Trajectories:
    """Simulate p001 static receivers for learning.

    Args:
        batch_size, seed: as :func:`simulate_p001` (an int seed is deterministic).
        dtype: dtype (or its name) of every returned tensor.
        num_steps: overrides ``num_epochs`` (the data module passes it for shortened debug runs).
        num_epochs: epochs per trajectory (p001: 100 at 10 s).
        randomize: random location and satellite geometry per trajectory (training sets); else
            p001's fixed 7-satellite geometry (PDOP ~1.9, the paper's test).
        num_satellites: ``K`` with ``randomize`` (the fixed geometry has 7).
        config: overrides of :data:`~experiments.papers.p001.simulator.P001_CONFIG` (``psi``, ``eta_sigma``...).
        static_accel_psd: the oracle's acceleration PSD (module doc).
    """
    dt = as_dtype(dtype)
    sc = simulate_p001(
        batch_size,
        seed,
        dt,
        randomize=randomize,
        num_satellites=num_satellites,
        num_epochs=int(num_steps if num_steps is not None else num_epochs),
        config=dict(config or {}),
    )
    k = int(sc.measurements.shape[-1])
    cfg = sc.config
    true_params: dict[str, Any] = {
        "clock_bias_psd": float(cfg["clock_bias_psd"]),  # type: ignore[arg-type]
        "clock_drift_psd": float(cfg["clock_drift_psd"]),  # type: ignore[arg-type]
        "accel_psd": float(static_accel_psd),
    }
    law = cfg.get("elevation_noise")
    if law:
        true_params.update({n: float(law[n]) for n in LAW_KEYS})  # type: ignore[index]
    else:
        psi = sc.psi.to(torch.float64)
        if not bool(torch.allclose(psi, psi[0].expand_as(psi))):
            raise ValueError("p001_simulator draws one Psi for the whole set (random_psi is not supported: no single oracle)")
        true_params.update({"psi": float(psi[0]), "R": [float(sc.eta_var)] * k})
        # the same truth in the elevation family's names (exponents 0)
        true_params.update(paper_law(psi=float(psi[0]), eta_sigma=float(sc.eta_var) ** 0.5, dt=float(sc.dt)))
    return P001Trajectories(
        truth=sc.truth,
        measurements=sc.measurements,
        mask=sc.mask,
        controls=sc.controls,
        initial_mean=sc.initial_mean,
        initial_cov=sc.initial_cov,
        true_params=true_params,
        scenario=sc,
    )


def start_learner(filter: Filter, loss: Any, *, start_params: Mapping[str, Any] | None = None, **learner_kwargs: Any) -> FilterLearner:  # noqa: A002
    """A :class:`~difffilter.learn.learner.FilterLearner` on ``filter`` after setting
    ``start_params`` (constrained values by name, as ``experiment.hand_tuned``) on it.

    ``run_experiment`` hands the learner a copy of the hand-tuned filter, so the hand-tuned row is
    unaffected; use as ``learner._target_`` with ``start_params: {psi: 0.0}``.
    """
    if start_params:
        assign_parameters(filter, dict(start_params))
    return FilterLearner(filter, loss, **learner_kwargs)
