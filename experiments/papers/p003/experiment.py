"""Experiment set-up for p003 (IMM of simplified UKFs, GPS/SINS ultra-tight): builders, simulator
wrapper, oracles and transition matrices (the paired evaluation with switching delays is in
:mod:`experiments.papers.p003.paired`).

* :func:`p003_mode_model` - the 20-state error model of one IMM mode, its ``Q`` (continuous-time PSD)
  and ``R`` learnable as *scales* on the sensor specification (:func:`~experiments.papers.p003.model.make_p003_model`,
  ``"scalar"`` structure), or, with ``white_only``, the high mode the simulator really uses (only the
  IMU white noises scaled).
* :func:`p003_imm` / :func:`p003_single` - the IMM of two modes (``filter``: ``"simplified"`` =
  p003's UTCUKF, ``"standard"`` = additive-noise UKF, ``"augmented"`` = augmented UKF) and a
  single-mode filter, from plain config values.
* :func:`p003_learner` - the learner, optionally with each mode's ``Q`` and ``R`` split into
  log-scaled groups (IMU white noises / everything else; ranges / rates) on the learned copy only;
  :func:`learned_from_state` rebuilds a learned IMM from a checkpoint.
* :func:`p003_oracle` - the filter with a scenario family's true parameters.
* :func:`simulate` - :func:`~experiments.papers.p003.simulator.simulate_p003` in metres with ``num_steps``
  (what the data module passes for short debug runs) mapped to the duration.
* :func:`empirical_transition` - the maximum-likelihood Markov matrix of a phase schedule's mode
  sequence (the scripted profile's oracle ``Pi``); :func:`sojourn_transition` - the IMM design
  rule ``p_ii = 1 - T / tau_i`` (the hand-tuned ``Pi``, which p003 does not state).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch.nn.utils import parametrize

from difffilter._util import as_dtype
from difffilter.filters import UKF, SimplifiedUKF
from difffilter.filters.base import RecursiveFilter
from difffilter.filters.protocol import Filter
from difffilter.filters.sigma_points import MerweScaled
from difffilter.learn.learner import FilterLearner
from difffilter.mixers import IMM
from difffilter.params import GroupScaledCovariance, register_constrained
from experiments.papers.p003.sins import SinsErrorDynamics
from experiments.papers.p003.sins_measurement import SinsPseudorangeMeasurement

from .flight import PAPER_PHASES, manoeuvre_flags
from .model import make_p003_model, sojourn_transition
from .noise import NOISE_DEFAULTS, true_transition
from .simulator import P003Scenario, simulate_p003

__all__ = [
    "P003Flights",
    "empirical_transition",
    "group_scale_q",
    "learned_from_state",
    "model_options",
    "p003_imm",
    "p003_learner",
    "p003_mode_model",
    "p003_oracle",
    "p003_single",
    "simulate",
    "sojourn_transition",
]

_WHITE = slice(3, 9)  # accelerometer and gyro white-noise PSD entries of experiments.papers.p003.sins


def p003_mode_model(
    *,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    white_only: bool = False,
    num_satellites: int = 8,
    linearized: bool = False,
    position_in_metres: bool = True,
    discretization: str = "expm",
    dtype: torch.dtype | str = "float64",
) -> torch.nn.Module:
    """One mode's model: :func:`make_p003_model` at the sensor specification, then

    * ``white_only=False``: ``Q = q_scale Q_spec``, ``R = r_scale R_spec`` with learnable scales
      (``"scalar"`` structure: ``Q``/``R`` values are scale x spec, the scale starts at the given one);
    * ``white_only=True``: only the IMU white-noise PSD entries scaled by ``q_scale`` (the
      simulator's manoeuvre noise), ``"diagonal"`` structure.
    """
    dt = as_dtype(dtype)
    opts = {"num_satellites": int(num_satellites), "linearized": linearized, "position_in_metres": position_in_metres}
    opts["discretization"] = discretization
    model = make_p003_model(Q_structure="diagonal" if white_only else "scalar", dtype=dt, **opts)  # type: ignore[arg-type]
    with torch.no_grad():
        if white_only:
            q = torch.diagonal(model.dynamics.Q).clone()
            q[_WHITE] = q[_WHITE] * q_scale
            model.dynamics.Q = torch.diag(q)
        else:
            model.dynamics.Q = torch.tensor(float(q_scale), dtype=dt)
        model.measurement.R = torch.tensor(float(r_scale), dtype=dt)
    flights = P003Flights(num_satellites=int(num_satellites), position_in_metres=position_in_metres)
    model.defaults = dataclasses.replace(model.defaults, controls=flights)
    return model


class P003Flights:
    """In-family inputs of the SINS model: ``(batch_size, num_steps, generator, dtype) ->`` the
    INS and satellite controls of random open-loop flights of ``num_steps`` seconds
    (:func:`simulate_p003` with ``profile="random"``)."""

    def __init__(self, *, num_satellites: int, position_in_metres: bool) -> None:
        self.num_satellites, self.position_in_metres = int(num_satellites), bool(position_in_metres)

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        sc = simulate_p003(
            batch_size, gen, dtype, profile="random", duration=float(num_steps), num_satellites=self.num_satellites,
            position_in_metres=self.position_in_metres,
        )  # fmt: skip
        return sc.controls


def _log_groups(module: torch.nn.Module, name: str, groups: torch.Tensor) -> None:
    """Re-register ``module.<name>`` (a learnable covariance) as :class:`GroupScaledCovariance`
    on its current value with log scales for ``groups``, all starting at 1."""
    if not parametrize.is_parametrized(module, name):
        raise TypeError(f"log-scaled groups need a learnable {name} (a parametrized {type(module).__name__}.{name})")
    value = getattr(module, name).detach().clone()
    register_constrained(module, name, torch.ones((), dtype=value.dtype), GroupScaledCovariance(value, groups.to(value)))


def group_scale_q(imm: Filter, q_groups: str | None, r_groups: str | None = None) -> Filter:
    """Re-parametrize every mode's ``Q`` (``q_groups``) and ``R`` (``r_groups``) of ``imm`` in
    place as :func:`p003_learner` describes (``None``: that one is left alone); returns ``imm``.
    A filter without modes (no ``filters``) is treated as one mode: its own model, or the model of
    the filter it wraps (``inner``, e.g. an adaptive noise filter around :func:`p003_single`)."""
    if q_groups not in (None, "imu_white"):
        raise ValueError(f"q_groups must be None or 'imu_white', got {q_groups!r}")
    if r_groups not in (None, "one", "range_rate"):
        raise ValueError(f"r_groups must be None, 'one' or 'range_rate', got {r_groups!r}")
    if q_groups is None and r_groups is None:
        return imm
    modes = getattr(imm, "filters", None)
    if modes is None:
        modes = [getattr(imm, "inner", imm)]
    for mode in modes:
        dyn, meas = mode.model.dynamics, mode.model.measurement
        if not isinstance(dyn, SinsErrorDynamics) or not isinstance(meas, SinsPseudorangeMeasurement):
            raise TypeError(f"q_groups/r_groups need SINS modes, got {type(dyn).__name__} / {type(meas).__name__}")
        if q_groups is not None:
            white = torch.zeros(dyn.Q.shape[-1], dtype=torch.float64)
            white[_WHITE] = 1.0
            _log_groups(dyn, "Q", torch.stack([white, 1.0 - white]))
        if r_groups is not None:
            ranges = (torch.arange(2 * meas.num_satellites) < meas.num_satellites).to(torch.float64)
            _log_groups(
                meas, "R", torch.ones(1, ranges.numel(), dtype=torch.float64) if r_groups == "one" else torch.stack([ranges, 1.0 - ranges])
            )
    return imm


def p003_learner(
    filter: Filter,  # noqa: A002 - the field's word
    loss: Any,
    *,
    q_groups: str | None = None,
    r_groups: str | None = None,
    **learner_kwargs: Any,
) -> FilterLearner:
    """A :class:`~difffilter.learn.learner.FilterLearner` on ``filter`` (``run_experiment`` hands
    it a copy of the hand-tuned IMM).

    ``q_groups=None`` and ``r_groups=None``: exactly ``FilterLearner(filter, loss, ...)`` (p003's
    family: one softplus scale per mode on ``Q`` and on ``R``).  ``q_groups="imu_white"``: every
    mode's ``Q`` becomes a :class:`GroupScaledCovariance` on its current (hand-tuned) value with
    two log-scaled groups, the IMU white-noise PSD entries (accelerometer and gyro) and all other
    entries (position floors, sensor-bias drivers, clock), both starting at 1.  ``r_groups``:
    ``"one"`` (one log scale per mode) or ``"range_rate"`` (pseudorange and pseudorange-rate
    variances scaled apart: code and carrier tracking noise need not move together).  The
    parameters keep their names ``Q``/``R``.  The two-group ``Q`` contains noise that grows only in
    the IMU white noises, which one scalar per mode cannot express; log space lets a scale move by
    orders of magnitude at Adam's step size.
    """
    group_scale_q(filter, q_groups, r_groups)
    return FilterLearner(filter, loss, **learner_kwargs)


def learned_from_state(hand: Filter, state: Mapping[str, torch.Tensor], q_groups: str | None = None, r_groups: str | None = None) -> Filter:
    """A copy of ``hand`` in the learner's layout (``q_groups``/``r_groups``, see
    :func:`p003_learner`) carrying the ``filter.*`` entries of a learner's ``state`` (a checkpoint's
    ``state_dict``)."""
    learned = group_scale_q(copy.deepcopy(hand), q_groups, r_groups)
    learned.load_state_dict({k.removeprefix("filter."): v for k, v in state.items() if k.startswith("filter.")})
    return learned


def _mode_filter(kind: str, model: torch.nn.Module, alpha: float, beta: float, kappa: float) -> RecursiveFilter:
    points = MerweScaled(alpha=alpha, beta=beta, kappa=kappa)
    if kind == "simplified":
        return SimplifiedUKF(model, sigma_points=points)  # type: ignore[arg-type]
    if kind == "standard":
        return UKF(model, sigma_points=points, redraw_after_predict=True)  # type: ignore[arg-type]
    if kind == "augmented":
        return UKF(model, sigma_points=points, redraw_after_predict=True, noise="augmented")  # type: ignore[arg-type]
    raise ValueError(f"filter must be 'simplified', 'standard' or 'augmented', got {kind!r}")


ModelOptions = Mapping[str, Any] | torch.nn.Module | None


def model_options(model: ModelOptions) -> dict[str, Any]:
    """Structure options of :func:`p003_mode_model` (``num_satellites``, ``linearized``,
    ``position_in_metres``, ``discretization``) from a mapping (returned as is, ``_target_``/
    ``q_scale``/``r_scale``/``dtype`` dropped) or read off a SINS model built by it (its noise
    levels are not options: every mode is the specification times its scales)."""
    if model is None:
        return {}
    if isinstance(model, Mapping):
        return {k: v for k, v in model.items() if k not in ("_target_", "q_scale", "r_scale", "white_only", "dtype")}
    meas, dyn = getattr(model, "measurement", None), getattr(model, "dynamics", None)
    if not isinstance(meas, SinsPseudorangeMeasurement) or not isinstance(dyn, SinsErrorDynamics):
        raise TypeError(f"model must be p003 options or a SINS StateSpaceModel (p003_mode_model), got {type(model).__name__}")
    return {
        "num_satellites": meas.num_satellites,
        "linearized": meas.linearized,
        "position_in_metres": meas.position_in_metres,
        "discretization": dyn.discretization,
    }


def empirical_transition(phases: Sequence[tuple[float, float, str, float]] = PAPER_PHASES, duration: float = 1800.0) -> list[list[float]]:
    """Maximum-likelihood ``Pi [2, 2]`` (mode 0 = level/static, 1 = manoeuvre) of the 1 Hz mode
    sequence of ``phases`` (the flags of :func:`simulate_p003`: step ``k`` in a manoeuvre when
    ``k - 0.5 s`` lies inside one)."""
    flags = manoeuvre_flags(list(phases), np.arange(1, int(round(duration)) + 1) - 0.5).astype(int)
    counts = np.zeros((2, 2))
    np.add.at(counts, (flags[:-1], flags[1:]), 1.0)
    rows = counts.sum(1, keepdims=True)
    if (rows == 0).any():
        raise ValueError("the schedule never visits one of the two modes")
    return (counts / rows).tolist()


def p003_imm(
    *,
    filter: str = "simplified",  # noqa: A002 - config key
    model: ModelOptions = None,
    q_scales: Sequence[float] = (1.0, 1.0e4),
    r_scales: Sequence[float] = (1.0, 100.0),
    white_only_high: bool = False,
    transition: Sequence[Sequence[float]] | str = ((0.95, 0.05), (0.05, 0.95)),
    initial_probs: Sequence[float] = (0.9, 0.1),
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
    prob_floor: float = 1.0e-6,
    dtype: torch.dtype | str = "float64",
) -> IMM:
    """p003's two-mode IMM (mode 0 low noise, mode 1 high noise) of ``filter`` mode filters.

    Args:
        model: options of :func:`p003_mode_model` shared by the modes (``num_satellites``,
            ``linearized``, ``position_in_metres``, ``discretization``), or a model built by it
            whose options are used (:func:`model_options`).
        q_scales, r_scales: per-mode scales on the spec ``Q`` (PSD, i.e. ``sigma_Q^2``) and ``R``.
        white_only_high: the high mode scales only the IMU white noises (the simulator's truth).
        transition: ``[2, 2]`` ``Pi`` or ``"paper"`` (:func:`empirical_transition` of the paper profile).
    """
    dt = as_dtype(dtype)
    opts = model_options(model)
    modes = []
    for j, (qs, rs) in enumerate(zip(q_scales, r_scales, strict=True)):
        m = p003_mode_model(q_scale=qs, r_scale=rs, white_only=white_only_high and j > 0, dtype=dt, **opts)
        modes.append(_mode_filter(filter, m, alpha, beta, kappa))
    pi = empirical_transition() if isinstance(transition, str) and transition == "paper" else transition
    if isinstance(pi, str):
        raise ValueError(f"transition must be a [2, 2] matrix or 'paper', got {pi!r}")
    imm = IMM(
        modes, transition=torch.tensor(pi, dtype=dt), initial_probs=torch.tensor(list(initial_probs), dtype=dt), prob_floor=prob_floor
    )
    return imm.to(dt)


def p003_single(
    *,
    filter: str = "simplified",  # noqa: A002 - config key
    model: ModelOptions = None,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
    dtype: torch.dtype | str = "float64",
) -> RecursiveFilter:
    """A single-mode filter with the given noise scales (p003's single-model comparison)."""
    dt = as_dtype(dtype)
    m = p003_mode_model(q_scale=q_scale, r_scale=r_scale, dtype=dt, **model_options(model))
    return _mode_filter(filter, m, alpha, beta, kappa).to(dt)


def p003_oracle(
    *,
    noise: str,
    profile: str,
    config: Mapping[str, float] | None = None,
    duration: float = 1800.0,
    filter: str = "simplified",  # noqa: A002 - config key
    model: ModelOptions = None,
    initial_probs: Sequence[float] = (0.9, 0.1),
    dtype: torch.dtype | str = "float64",
) -> Filter:
    """The filter with the simulator's true parameters for a scenario family (see
    :mod:`~experiments.papers.p003.noise`):

    * ``noise="nominal"``: nothing switches, so the truth is the single filter at the specification
      (the IMM family with ``Pi[0, 0] = 1``): :func:`p003_single`;
    * ``noise="modes"``: the IMM with the true mode levels - high mode = IMU white-noise PSD x
      ``mode_imu_scale**2`` (the rest of ``Q`` as specified) and ``R`` x ``mode_gnss_scale**2`` - and
      the true ``Pi``: the generating chain (:func:`~experiments.papers.p003.noise.true_transition`)
      for ``profile="markov"``, else the maximum-likelihood matrix of the scripted profile's mode
      sequence (:func:`empirical_transition`; approximate: scripted switching is not Markov);
    * ``noise="physical"``: ``ValueError`` (load-dependent, per-satellite noise is outside the
      family: that family has no oracle).
    """
    cfg = {**NOISE_DEFAULTS, **(config or {})}
    if noise == "nominal":
        return p003_single(filter=filter, model=model, dtype=dtype)
    if noise != "modes":
        raise ValueError(f"no oracle for noise={noise!r}: only 'nominal' and 'modes' put the truth in the filter's family")
    if profile == "markov":
        pi: list[list[float]] = true_transition(cfg["markov_enter"], cfg["markov_leave"])
    elif profile == "paper":
        pi = empirical_transition(PAPER_PHASES, duration)
    else:
        raise ValueError(f"the 'modes' oracle needs profile 'markov' or 'paper' (a Markov or fixed schedule), got {profile!r}")
    return p003_imm(
        filter=filter, model=model, q_scales=(1.0, cfg["mode_imu_scale"] ** 2), r_scales=(1.0, cfg["mode_gnss_scale"] ** 2),
        white_only_high=True, transition=pi, initial_probs=initial_probs, dtype=dtype,
    )  # fmt: skip


def simulate(
    batch_size: int = 1,
    seed: int | torch.Generator | None = 0,
    dtype: torch.dtype = torch.float64,
    *,
    num_steps: int | None = None,
    duration: float = 1800.0,
    profile: str = "paper",
    position_in_metres: bool = True,
    **kwargs: Any,
) -> P003Scenario:
    """:func:`simulate_p003` with ``num_steps`` (1 Hz steps) overriding ``duration``; metres by default."""
    dur = float(num_steps) if num_steps is not None else float(duration)
    return simulate_p003(batch_size, seed, dtype, profile=profile, duration=dur, position_in_metres=position_in_metres, **kwargs)
