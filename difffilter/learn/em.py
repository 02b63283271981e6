"""Maximum-likelihood noise covariances (and IMM mode probabilities) by expectation-maximisation.

For ``x_t = f(x_{t-1}, u_t) + w_t``, ``w_t ~ N(0, Q)``, ``z_t = h(x_t, u_t) + v_t``,
``v_t ~ N(0, R)``, ``x_{-1} ~ N(m_0, P_0)``, one EM iteration is

1. **E-step**: run the filter's fixed-interval smoother (:func:`~difffilter.smoothers.make_smoother`)
   and form the expected residual moments ``A_t = E[(x_t - f(x_{t-1}))(...)^T]`` and
   ``M_t = E[(z_t - h(x_t))(...)^T]`` under the smoothed Gaussians, including the lag-one
   cross-covariance ``P_{t-1,t|T} = G_t P_{t|T}``
   (:mod:`difffilter.smoothers.expectations`);
2. **M-step**: the closed-form maximiser of the expected complete-data log-likelihood for each
   estimated quantity, pooled over all trajectories (:mod:`difffilter.learn.em_mstep`):
   ``Q = sum A_t / N`` (full; its diagonal, or a scale of a fixed matrix, for the other
   structures), ``R`` likewise over the observed steps, ``m_0 = mean_b x_{-1|T}``,
   ``P_0 = mean_b [P_{-1|T} + (x_{-1|T} - m_0)(...)^T]``.  When the filter starts from a diffuse
   prior (:mod:`difffilter.filters.diffuse`), the first transition ``x_{-1} -> x_0`` is left out
   of ``Q``'s statistics and the initial moments are not estimated.

For a :class:`~difffilter.filters.KalmanFilter` on a linear model this is exact EM (Shumway and
Stoffer 1982): the innovation log-likelihood never decreases.  For the EKF/UKF families the
E-step uses the smoother's linearisation or sigma points, an approximation: the likelihood
usually rises but is not guaranteed to.  For an :class:`~difffilter.mixers.IMM` the transition
matrix and initial mode probabilities are estimated from the expected transition counts of
Kim's IMM smoother (:class:`~difffilter.smoothers.IMMSmoother`), which approximates
``P(mode j at t-1, mode i at t | all)`` by ``P(i at t | all) P(j at t-1 | i at t, z_{<t})``;
this too is approximate EM.

The estimates are written into the filter's constrained parameters (``model.Q = ...``), so the
same filter can be used at once, or trained further by back-propagation (EM as a warm start).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import torch
from torch import Tensor, nn

from ..filters.base import RecursiveFilter
from ..filters.diffuse import DIFFUSE_COV
from ..filters.ekf import EKF
from ..filters.kalman import KalmanFilter
from ..mixers.imm import IMM
from ..models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from ..selection import match_parameters, parameter_owners
from ..smoothers import make_smoother
from ..smoothers.expectations import measurement_residual_moments, observed_components, transition_residual_moments
from ..smoothers.result import SmootherResult
from ..smoothers.transition import predicting_filter
from .em_mstep import covariance_structure, markov_step, measurement_noise_step, process_noise_step, to_constraint_set

__all__ = ["EMResult", "fit_em"]

#: Names of the initial belief's moments in ``learn=`` (they are arguments, not parameters).
INITIAL = ("initial_mean", "initial_cov")


@dataclass
class EMResult:
    """What :func:`fit_em` did.

    Attributes:
        log_likelihoods: total innovation log-likelihood (summed over trajectories and steps)
            with the starting values, then after each M-step.
        values: the estimated constrained values ``{dotted name: tensor}`` (as also written into
            the filter), plus ``initial_mean``/``initial_cov`` when estimated.
        initial_mean, initial_cov: the initial belief after EM ``[n]``/``[B, n]``, ``[n, n]``/``[B, n, n]``
            (the given one unless estimated; an estimate is pooled: ``[n]``, ``[n, n]``).
        num_iters: M-steps taken.
        converged: whether the relative change of the log-likelihood fell below ``tol``.
        best_iteration: index into ``log_likelihoods`` of the returned values: the iterate with
            the highest log-likelihood.  Exact EM never lowers it, so this is the last one for a
            linear model; with an approximate E-step (extended/unscented smoothers, an IMM) an
            M-step can lower it, and the parameters of the best iterate are restored.
        monotone: whether the log-likelihood never fell from one iterate to the next (by more
            than ``tol`` relative); ``False`` is worth a look (the E-step's approximation).
        cpu_seconds: process CPU time spent (the tuning cost).
        filter: the filter whose parameters were set.
    """

    log_likelihoods: list[float]
    values: dict[str, Tensor]
    initial_mean: Tensor
    initial_cov: Tensor
    num_iters: int
    converged: bool
    cpu_seconds: float
    filter: RecursiveFilter = field(repr=False)
    best_iteration: int = 0
    monotone: bool = True


@dataclass
class _Target:
    name: str
    kind: str  # "Q", "R", "transition", "initial_probs"
    owner: nn.Module
    attr: str
    structure: str = "probs"

    @property
    def constraint(self) -> nn.Module:
        return _constraint(self.owner, self.attr)

    @property
    def base(self) -> Tensor | None:
        """The fixed matrix of a ``scalar`` structure (``None`` for the others)."""
        return cast(Tensor, self.constraint.base) if self.structure == "scalar" else None

    def assign(self, value: Tensor) -> Tensor:
        value = to_constraint_set(value, self.constraint)
        setattr(self.owner, self.attr, value)
        return getattr(self.owner, self.attr).detach().clone()


def _constraint(owner: nn.Module, attr: str) -> nn.Module:
    """The constraint module of the parametrized attribute ``owner.<attr>``."""
    # parametrizations is a ModuleDict on a parametrized module; nn.Module's __getattr__ types it
    # as Tensor | Module, which is not indexable by a name
    return cast(nn.Module, owner.parametrizations[attr][0])  # type: ignore[index]


def _as_filter(filter_or_model: RecursiveFilter | StateSpaceModel) -> RecursiveFilter:
    if isinstance(filter_or_model, RecursiveFilter):
        return filter_or_model
    if isinstance(filter_or_model, StateSpaceModel):
        linear = type(filter_or_model.dynamics).matrix is not DynamicsModel.matrix and (
            type(filter_or_model.measurement).matrix is not MeasurementModel.matrix
        )
        return KalmanFilter(filter_or_model) if linear else EKF(filter_or_model)
    raise TypeError(f"filter_or_model must be a difffilter RecursiveFilter or StateSpaceModel, got {type(filter_or_model).__name__}")


def _target(filt: RecursiveFilter, name: str, owner: nn.Module, attr: str) -> _Target | None:
    """The EM target behind a dotted parameter name, or ``None`` if EM cannot estimate it."""
    if isinstance(filt, IMM):
        if owner is filt and attr in ("transition", "initial_probs"):
            return _Target(name, attr, owner, attr)
        return None
    model = predicting_filter(filt).model
    if owner is model.dynamics and attr == "Q":
        if type(owner).process_noise is not DynamicsModel.process_noise or not owner.additive_noise:
            raise TypeError(f"EM cannot estimate {name}: the dynamics' process noise is not the additive constant Q")
        return _Target(name, "Q", owner, attr, covariance_structure(_constraint(owner, attr)))
    if owner is model.measurement and attr == "R":
        if type(owner).measurement_noise is not MeasurementModel.measurement_noise or not owner.additive_noise:
            raise TypeError(f"EM cannot estimate {name}: the measurement noise is not the additive constant R")
        return _Target(name, "R", owner, attr, covariance_structure(_constraint(owner, attr)))
    return None


def _targets(filt: RecursiveFilter, learn: Sequence[str] | None) -> tuple[list[_Target], set[str]]:
    owners = parameter_owners(filt)
    if learn is None:
        found = []
        for name, (owner, attr, _) in owners.items():
            try:
                t = _target(filt, name, owner, attr)
            except (TypeError, ValueError):
                continue
            if t is not None:
                found.append(t)
        if not found:
            raise ValueError("learn=None: this filter has no parameter EM can estimate (Q, R, an IMM's transition/initial_probs)")
        return found, set()
    if isinstance(learn, str) or not all(isinstance(x, str) for x in learn) or not learn:
        raise ValueError(f"learn must be a non-empty sequence of parameter names or None, got {learn!r}")
    initial = {x for x in learn if x in INITIAL}
    names = [x for x in learn if x not in INITIAL]
    try:
        hits = match_parameters(filt, names)
    except ValueError as exc:
        raise ValueError(f"learn: {exc} (fixed covariances are buffers, not parameters; also accepted: {list(INITIAL)})") from exc
    found = []
    for pattern, dotted in hits.items():
        for name in dotted:
            t = _target(filt, name, *owners[name][:2])
            if t is None:
                raise ValueError(
                    f"learn: EM cannot estimate {name!r} (from {pattern!r}); it estimates Q and R of the filter's model, "
                    f"an IMM's transition and initial_probs, and {list(INITIAL)}"
                )
            found.append(t)
    return found, initial


def _check_args(num_iters: int, tol: float, measurements: Tensor) -> None:
    if isinstance(num_iters, bool) or not isinstance(num_iters, int) or num_iters < 1:
        raise ValueError(f"num_iters must be an int >= 1, got {num_iters!r}")
    if not (isinstance(tol, int | float) and math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite float >= 0, got {tol!r}")
    if not isinstance(measurements, Tensor) or measurements.ndim != 3:
        raise ValueError(f"measurements must be a tensor [B, T, m], got {getattr(measurements, 'shape', type(measurements))}")


def _initial_step(smoothed: SmootherResult, mean: Tensor, learn: set[str]) -> tuple[Tensor | None, Tensor | None]:
    """Pooled ``(m_0, P_0)`` from the smoothed ``x_{-1}`` (``None`` where not estimated)."""
    assert smoothed.initial_mean is not None and smoothed.initial_cov is not None
    sm, sp = smoothed.initial_mean, smoothed.initial_cov
    new_mean = sm.mean(0) if "initial_mean" in learn else None
    if "initial_cov" not in learn:
        return new_mean, None
    centre = new_mean if new_mean is not None else mean.expand_as(sm)
    dev = sm - centre
    cov = (sp + dev[..., :, None] * dev[..., None, :]).mean(0)
    return new_mean, 0.5 * (cov + cov.mT)


@torch.no_grad()
def fit_em(
    filter_or_model: RecursiveFilter | StateSpaceModel,
    measurements: Tensor,
    initial_mean: Tensor,
    initial_cov: Tensor,
    mask: Tensor | None = None,
    controls: Controls = None,
    *,
    num_iters: int = 20,
    learn: Sequence[str] | None = None,
    tol: float = 1e-8,
    time_chunk: int | None = None,
) -> EMResult:
    """Estimate ``Q``, ``R`` (or an IMM's ``transition``/``initial_probs``) by EM and write them
    into the filter (module docstring for the equations).

    Args:
        filter_or_model: a smoothable filter (KalmanFilter, EKF, IteratedEKF, UKF family, IMM of
            such modes), or a model (then a KalmanFilter if linear, else an EKF, is built on it).
        measurements: ``[B, T, m]`` training trajectories (pooled in the M-step).
        initial_mean, initial_cov: belief before the first measurement, ``[n]``/``[B, n]`` and
            ``[n, n]``/``[B, n, n]``.
        mask: ``[B, T]`` or ``[B, T, m]`` bool, False = missing (contributes nothing to ``R``).
        controls: per-step inputs ``[B, T, ...]``.
        num_iters: maximum number of EM iterations (>= 1).
        learn: parameter names as in :func:`~difffilter.selection.match_parameters` (``"Q"``,
            ``"R"``, ``"model.measurement.R"``, ``"transition"``, ``"initial_probs"``) and/or
            ``"initial_mean"``, ``"initial_cov"``; ``None``: every parameter EM can estimate
            (Q and R, or an IMM's transition and initial probabilities).  Parameters not named
            keep their values; a ``"fixed"`` covariance is a buffer and cannot be named.
        tol: stop when the log-likelihood changes by less than ``tol * (1 + |log-likelihood|)``.
        time_chunk: time steps per batched E-step call (memory bound).

    Returns:
        :class:`EMResult`.  Raises ``ValueError`` for a bad ``num_iters``/``tol``/``learn`` and
        ``TypeError`` for a filter or model EM does not support (state-dependent or
        non-additive noise, unsupported filters).
    """
    start = time.process_time()
    _check_args(num_iters, tol, measurements)
    filt = _as_filter(filter_or_model)
    targets, initial = _targets(filt, learn)
    smoother = make_smoother(filt, "rts", time_chunk=time_chunk)
    is_imm = isinstance(filt, IMM)
    if is_imm and initial:
        raise ValueError(f"learn: {sorted(initial)} are not estimated for an IMM (its modes' beliefs are mixed)")
    mean, cov = initial_mean, initial_cov
    # a diffuse start (a prior too wide for plain covariance form) leaves x_{-1}'s smoothed
    # moments undefined: the first transition is then left out of Q's statistics
    diffuse = not is_imm and DIFFUSE_COV in smoother.initial_belief(measurements, mean, cov, None)
    if diffuse and initial:
        raise ValueError(f"learn: {sorted(initial)} cannot be estimated from a diffuse initial_cov (too wide for plain covariance form)")
    obs = observed_components(mask, tuple(measurements.shape), measurements.device)  # type: ignore[arg-type]
    history: list[float] = []
    values: dict[str, Tensor] = {}
    converged = False
    iters = 0
    # an approximate E-step does not guarantee ascent: keep the best iterate (exact state, not values
    # pushed back through the constraints) so a falling log-likelihood never makes the result worse
    best: tuple[int, float, dict[str, Tensor], Tensor, Tensor, dict[str, Tensor]] | None = None
    for it in range(num_iters + 1):
        smoothed = smoother(measurements, mean, cov, mask=mask, controls=controls)
        history.append(float(smoothed.filtered.log_likelihood.sum()))
        if best is None or (math.isfinite(history[-1]) and not history[-1] <= best[1]):
            state = {k: v.detach().clone() for k, v in filt.state_dict().items()}
            best = (it, history[-1], state, mean, cov, dict(values))
        if it > 0 and abs(history[-1] - history[-2]) <= tol * (1.0 + abs(history[-2])):
            converged = True
            break
        if it == num_iters:
            break
        iters += 1
        if is_imm:
            pairs = smoothed.extras["mode_pair_probs"].sum((0, 1))
            pi, mu0 = markov_step(pairs, smoothed.extras["initial_mode_probs"].mean(0), cast(Tensor, filt.transition).detach())
            for t in targets:
                values[t.name] = t.assign(pi if t.kind == "transition" else mu0)
            continue
        kinds = {t.kind for t in targets}
        moments_q = moments_r = None
        if "Q" in kinds:
            moments_q = transition_residual_moments(filt, smoothed, controls, time_chunk=time_chunk)
        if "R" in kinds:
            moments_r = measurement_residual_moments(filt, smoothed, measurements, mask, controls, time_chunk=time_chunk)
        for t in targets:
            current = getattr(t.owner, t.attr).detach()
            base = t.base
            if t.kind == "Q":
                assert moments_q is not None
                used = moments_q[:, 1:] if diffuse else moments_q
                new = process_noise_step(used.sum((0, 1)), used.shape[0] * used.shape[1], t.structure, base)
            else:
                assert moments_r is not None
                new = measurement_noise_step(moments_r, obs, current, t.structure, base)
            values[t.name] = t.assign(new)
        new_mean, new_cov = _initial_step(smoothed, mean, initial)
        if new_mean is not None:
            mean = values["initial_mean"] = new_mean
        if new_cov is not None:
            cov = values["initial_cov"] = new_cov
    assert best is not None
    best_it = best[0]
    if best_it != len(history) - 1:
        filt.load_state_dict(best[2])
        mean, cov, values = best[3], best[4], best[5]
    monotone = all(b >= a - tol * (1.0 + abs(a)) for a, b in zip(history, history[1:], strict=False))
    for t in targets:
        values.setdefault(t.name, getattr(t.owner, t.attr).detach().clone())
    return EMResult(
        log_likelihoods=history,
        values=values,
        initial_mean=mean,
        initial_cov=cov,
        num_iters=iters,
        converged=converged,
        cpu_seconds=time.process_time() - start,
        filter=filt,
        best_iteration=best_it,
        monotone=monotone,
    )
