"""The one time loop shared by every recursive filter and mixer.

Subclasses of :class:`RecursiveFilter` implement :meth:`~RecursiveFilter.predict` and
:meth:`~RecursiveFilter.update` on a *belief*: a ``dict`` of tensors with at least ``"mean"``
``[B, n]`` and ``"cov"`` ``[B, n, n]`` plus whatever the filter carries between steps (square-root
factors, residual statistics, previous measurements, mode probabilities...).  The loop here does
input validation (:meth:`~difffilter.filters.protocol.Filter.check_inputs`), mask handling,
per-step bookkeeping and result assembly, so every filter shares the same semantics:

* ``(initial_mean, initial_cov)`` is the belief *before* the first measurement; every step
  predicts, then updates.
* ``mask[b, t]`` (or ``mask[b, t, i]``) False means missing.  Missing components are removed
  from the update exactly (their innovation, cross-covariance and innovation-covariance rows are
  zeroed and the diagonal set to one, which is the update on the observed subset); a fully
  missing step is predict-only with log-likelihood 0.  Values under a False mask (NaN allowed)
  are replaced by zeros before any arithmetic, so they reach neither outputs nor gradients.

A dangerously wide initial covariance starts in the exact two-part form of
:mod:`difffilter.filters.diffuse` (:meth:`RecursiveFilter.start_belief`); every result carries
``extras["untrusted"] [B, T]`` (:func:`~difffilter.filters.update.untrusted_steps`).

``GaussianFilter`` is the former name of :class:`RecursiveFilter`, kept as an alias.  The shared
vocabulary (:class:`~difffilter.filters.protocol.FilterResult`, ``Belief``, :class:`StepInfo`,
:func:`gaussian_update`...) is re-exported here for the filters built on the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from ..linalg import inside_vmap
from ..models.base import Controls
from ..threads import scoped_forward
from ._common import StepInfo, cast_controls, detach_belief, mask_measurement_system, slice_controls
from .diffuse import DIFFUSE_COV, DIFFUSE_SCALE, drop_resolved, measurement_sensitivity, split_prior, total_cov
from .isolation import isolated_run
from .protocol import Belief, Filter, FilterResult
from .update import diffuse_gaussian_update, gaussian_update, rounding_flags, square_root_deviations, untrusted_steps

__all__ = [
    "PRECOMPUTE_BLOCK",
    "ROUNDING_BLOCK",
    "Belief",
    "FilterResult",
    "GaussianFilter",
    "RecursiveFilter",
    "StepInfo",
    "concat_results",
    "detach_belief",
    "diffuse_gaussian_update",
    "gaussian_update",
    "mask_measurement_system",
    "slice_controls",
    "slice_steps",
    "square_root_deviations",
    "through_diffuse_phase",
]


#: Trajectory-steps per block whose derived inputs (:meth:`~difffilter.filters.protocol.Filter.precompute_controls`)
#: ``forward`` builds in one call: ``T`` steps at once up to ``B T = 8192`` (a ``[B, T, 20, 20]``
#: float64 transition is then 26 MB), blocks of ``8192 // B`` steps beyond.
PRECOMPUTE_BLOCK = 8192
#: Steps whose pending rounding checks (:attr:`StepInfo.rounding`) the time loop makes at once.
ROUNDING_BLOCK = 64
#: ``hook(filter, measurements, initial_mean, initial_cov, mask, controls, belief)`` asked first by
#: every :meth:`RecursiveFilter.forward`: a result to return, or None to run the filter's own
#: loop.  Set by :mod:`difffilter.engines` to its engine policy (``DIFFFILTER_ENGINE``).
ENGINE_HOOK: list[Callable[..., FilterResult | None] | None] = [None]


class RecursiveFilter(Filter):
    """One time loop; subclasses implement :meth:`predict` and :meth:`update` (and, when their
    belief carries more than ``mean``/``cov``, :meth:`init_belief`).

    Constructed like every :class:`~difffilter.filters.protocol.Filter`: on a state-space
    ``model``, or on none for filters that combine others (the IMM).  Filters hold parameters
    (through their model), never beliefs: :meth:`forward` is a pure function of its inputs.
    """

    #: Belief entries that :meth:`step` / ``forward`` record per step besides mean/cov.
    record_keys: tuple[str, ...] = ()
    #: Split an initial covariance that is dangerously wide against the measurement noise into
    #: an exact diffuse part (:mod:`difffilter.filters.diffuse`); set False on an instance to
    #: run every step in plain covariance form.
    diffuse_prior: bool = True
    #: Whether a plain call asks :data:`ENGINE_HOOK` (the engine policy) first.  False where the
    #: class's own ``forward`` is the point (the parallel scan): its few sequential steps never
    #: pay for a compiled kernel.
    uses_engine_policy: bool = True

    # -- to implement -----------------------------------------------------------------------
    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        """Belief from a validated ``mean [B, n]``, ``cov [B, n, n]``."""
        return {"mean": mean, "cov": cov}

    def predict(self, belief: Belief, u: Controls) -> Belief:  # pragma: no cover - abstract
        raise NotImplementedError

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:  # pragma: no cover
        raise NotImplementedError

    def record(self, belief: Belief) -> dict[str, Tensor]:
        """Per-step outputs beyond mean/cov (stacked into ``FilterResult.extras``)."""
        return {k: belief[k] for k in self.record_keys}

    def finalize_belief(self, belief: Belief) -> Belief:
        """Hook after each update (e.g. to drop predict-only entries)."""
        return belief

    # -- diffuse priors -----------------------------------------------------------------------
    def sensitivity(self, mean: Tensor, u: Controls) -> Tensor:
        """Rows ``g [B, k, n]`` that tell which prior directions the measurements resolve, and
        how sharply (:func:`~difffilter.filters.diffuse.measurement_sensitivity`)."""
        return measurement_sensitivity(self.model, mean, u)

    def attach_diffuse(self, belief: Belief, diffuse_cov: Tensor, scale: Tensor) -> Belief:
        """Add a diffuse part ``scale * diffuse_cov`` to a belief built by :meth:`init_belief`."""
        return {**belief, DIFFUSE_COV: diffuse_cov, DIFFUSE_SCALE: scale}

    def start_belief(self, mean: Tensor, cov: Tensor, u: Controls = None) -> Belief:
        """The belief before the first step: :meth:`init_belief`, with the dangerously wide
        directions of ``cov`` moved to an exact diffuse part when :attr:`diffuse_prior` is set.

        ``u`` are the first step's inputs, with which the model is evaluated at ``mean``; a
        model that cannot be evaluated without them keeps ``cov`` whole when ``u`` is None.
        """
        if self.diffuse_prior:
            try:
                rows = self.sensitivity(mean, u)
            except (KeyError, TypeError):
                if u is not None:
                    raise
                rows = None
            split = None if rows is None else split_prior(cov, rows)
            if split is not None:
                p_fin, p_inf, kappa = split
                return self.attach_diffuse(self.init_belief(mean, p_fin), p_inf, kappa)
        return self.init_belief(mean, cov)

    # -- running ----------------------------------------------------------------------------
    def step(
        self, belief: Belief, measurement: Tensor, mask: Tensor | None = None, controls: Controls = None
    ) -> tuple[Belief, Belief, StepInfo]:
        """One online step: predict with ``controls``, update with ``measurement [B, m]``.

        ``mask [B]`` or ``[B, m]``.  Returns ``(posterior, prior, info)``; start from
        :meth:`initial_belief`.
        """
        z = measurement[:, None]
        mk = None if mask is None else (mask[:, None] if mask.ndim == 1 else mask[:, None, :])
        u = (
            None
            if controls is None
            else (controls[:, None] if isinstance(controls, Tensor) else {k: v[:, None] for k, v in controls.items()})
        )
        u = cast_controls(u, z)
        z, mk, _, _ = self.check_inputs(z, None, None, mk, u)
        if u is not None:
            # the models' derived inputs, once for every mode of a mixer (precompute_controls)
            controls = slice_controls(self.precompute_controls(u), 0)
        with parametrize.cached():
            prior = self.predict(belief, controls)
            post, info = self.update(prior, z[:, 0], None if mk is None else mk[:, 0], controls)
            info = replace(info, untrusted=info.flags(), rounding=None)  # the pending check, made now
            return drop_resolved(self.finalize_belief(post)), prior, info

    def initial_belief(
        self, initial_mean: Tensor, initial_cov: Tensor, batch_size: int | None = None, *, controls: Controls = None
    ) -> Belief:
        """Validated starting belief for :meth:`step` (broadcast to ``batch_size``); ``controls``
        (``[B, ...]``, the first step's inputs) for the diffuse-prior check of a model that needs
        them (:meth:`start_belief`)."""
        bsz = batch_size if batch_size is not None else (initial_mean.shape[0] if initial_mean.ndim == 2 else 1)
        values = not inside_vmap()  # per-sample values cannot be read inside vmap
        mean = self._check_mean(initial_mean, bsz, self.state_dim, initial_mean.dtype, values=values)
        cov = self._check_cov(initial_cov, bsz, self.state_dim, initial_cov.dtype, values=values)
        return self.start_belief(mean, cov, controls)

    @scoped_forward
    def forward(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None = None,
        initial_cov: Tensor | None = None,
        mask: Tensor | None = None,
        controls: Controls = None,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        """Filter ``measurements [B, T, m]`` from the belief ``(initial_mean, initial_cov)``.

        Args:
            measurements: ``[B, T, m]``.
            initial_mean: ``[n]`` or ``[B, n]`` mean before the first measurement.
            initial_cov: ``[n, n]`` or ``[B, n, n]``, symmetric positive definite.
            mask: ``[B, T]`` or ``[B, T, m]`` bool, True = observed.
            controls: per-step inputs ``[B, T, ...]`` (tensor or dict of tensors) passed to the
                model's ``f`` and ``h`` at each step.
            belief: a full belief to continue from (e.g. ``result.final_belief`` of the previous
                window in truncated back-propagation); replaces ``initial_mean``/``initial_cov``.

        A trajectory whose result is non-finite passes no gradient to the others
        (:func:`~difffilter.filters.isolation.isolated_run`).
        """
        return isolated_run(self._run, measurements, initial_mean, initial_cov, mask, controls, belief)

    def _run(
        self,
        measurements: Tensor,
        initial_mean: Tensor | None,
        initial_cov: Tensor | None,
        mask: Tensor | None,
        controls: Controls,
        *,
        belief: Belief | None = None,
    ) -> FilterResult:
        hook = ENGINE_HOOK[0]
        if hook is not None and self.uses_engine_policy:
            out = hook(self, measurements, initial_mean, initial_cov, mask, controls, belief)
            if out is not None:
                return out
        controls = cast_controls(controls, measurements)
        z, mask3, mean0, cov0 = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if belief is None and (mean0 is None or cov0 is None):
            raise ValueError("initial_mean and initial_cov are required unless belief= is given")
        steps = z.shape[1]
        # the models' derived inputs, built for a block of steps at a time (bounded memory)
        block = max(1, PRECOMPUTE_BLOCK // z.shape[0])
        derived = self.precompute_controls(slice_steps(controls, 0, block))
        means, covs, pmeans, pcovs, lls, nis, nobs = [], [], [], [], [], [], []
        extras: dict[str, list[Tensor]] = {}
        flags: list[tuple[Tensor | int | None, Tensor | None, bool]] = []
        pending = _PendingRounding()
        with parametrize.cached():
            if belief is None:
                belief = self.start_belief(mean0, cov0, slice_controls(derived, 0))
            for t in range(steps):
                if t and t % block == 0:
                    derived = self.precompute_controls(slice_steps(controls, t, t + block))
                u = slice_controls(derived, t % block)
                prior = self.predict(belief, u)
                post, info = self.update(prior, z[:, t], None if mask3 is None else mask3[:, t], u)
                belief = self.finalize_belief(post)
                means.append(belief["mean"])
                covs.append(total_cov(belief))
                pmeans.append(prior["mean"])
                pcovs.append(total_cov(prior))
                lls.append(info.log_likelihood)
                nis.append(info.nis)
                nobs.append(info.num_observed)
                for k, v in self.record(belief).items():
                    extras.setdefault(k, []).append(v)
                flags.append((pending.add(info), info.jitter, DIFFUSE_COV in prior))
                belief = drop_resolved(belief)
        stack: Any = lambda xs: torch.stack(xs, 1)  # noqa: E731
        result = FilterResult(
            mean=stack(means),
            cov=stack(covs),
            prior_mean=stack(pmeans),
            prior_cov=stack(pcovs),
            log_likelihood=stack(lls),
            nis=stack(nis),
            num_observed=stack(nobs),
            final_belief=belief,
            extras={k: stack(v) for k, v in extras.items()},
        )
        pending.flush()
        result.extras["untrusted"] = _untrusted(result, [(pending.resolve(f), j, d) for f, j, d in flags])
        return result


#: The former name of :class:`RecursiveFilter` (kept for existing code and configs).
GaussianFilter = RecursiveFilter


class _PendingRounding:
    """The steps' pending rounding checks (:attr:`StepInfo.rounding`), made for
    :data:`ROUNDING_BLOCK` steps at a time: a few operations per block instead of per step, and
    memory for a block's inputs only.  :meth:`add` returns a step's flag or a placeholder that
    :meth:`resolve` turns into the flag once its block was checked."""

    def __init__(self) -> None:
        self.waiting: list[tuple[int, StepInfo]] = []
        self.done: dict[int, Tensor] = {}
        self.count = 0

    def add(self, info: StepInfo) -> Tensor | int | None:
        if info.rounding is None:
            return info.untrusted
        key = self.count
        self.count += 1
        self.waiting.append((key, info))
        if len(self.waiting) >= ROUNDING_BLOCK:
            self.flush()
        return key

    def flush(self) -> None:
        waiting, self.waiting = self.waiting, []
        if not waiting:
            return
        terms = [info.rounding for _, info in waiting]
        like = terms[0]
        same = all(
            all((a is None) == (b is None) and (a is None or a.shape == b.shape) for a, b in zip(t, like, strict=True))  # type: ignore[union-attr]
            for t in terms
        )
        if same and len(terms) > 1:
            stacked = [None if like[i] is None else torch.stack([t[i] for t in terms], 0) for i in range(len(like))]
            flags = list(rounding_flags(*stacked).unbind(0))  # type: ignore[arg-type]
        else:
            flags = [rounding_flags(*t) for t in terms]  # type: ignore[misc]
        for (key, info), flag in zip(waiting, flags, strict=True):
            self.done[key] = flag if info.untrusted is None else info.untrusted | flag

    def resolve(self, flag: Tensor | int | None) -> Tensor | None:
        return self.done.pop(flag) if isinstance(flag, int) else flag


def _untrusted(result: FilterResult, flags: list[tuple[Tensor | None, Tensor | None, bool]]) -> Tensor:
    """``[B, T]``: the run-wide check of :func:`~difffilter.filters.update.untrusted_steps` and
    the steps' own flags (an innovation covariance that needed jitter, a flagged update)."""
    exact = torch.tensor([d for _, _, d in flags], dtype=torch.bool, device=result.mean.device)
    out = untrusted_steps(result.mean, result.cov, result.prior_cov, result.log_likelihood, exact)
    for i in (0, 1):
        own = [f[i] for f in flags]
        if any(v is not None for v in own):
            like = next(v for v in own if v is not None)
            zero = torch.zeros_like(like)
            out = out | (torch.stack([zero if v is None else v for v in own], 1) != 0)
    return out


def slice_steps(controls: Controls, start: int, stop: int) -> Controls:
    """Steps ``start:stop`` of per-step inputs ``[B, T, ...]`` (tensor or dict of tensors)."""
    if controls is None:
        return None
    if isinstance(controls, Tensor):
        return controls[:, start:stop]
    return {k: v[:, start:stop] for k, v in controls.items()}


def concat_results(parts: list[FilterResult]) -> FilterResult:
    """One :class:`FilterResult` from consecutive runs (along time); an extra missing from a
    part is filled with zeros of its shape."""
    if len(parts) == 1:
        return parts[0]
    cat = lambda name: torch.cat([getattr(r, name) for r in parts], 1)  # noqa: E731
    keys = dict.fromkeys(k for r in parts for k in r.extras)
    extras = {}
    for k in keys:
        like = next(r.extras[k] for r in parts if k in r.extras)
        extras[k] = torch.cat(
            [r.extras[k] if k in r.extras else like.new_zeros(like.shape[0], r.mean.shape[1], *like.shape[2:]) for r in parts], 1
        )
    fields = ("mean", "cov", "prior_mean", "prior_cov", "log_likelihood", "nis", "num_observed")
    return FilterResult(**{f: cat(f) for f in fields}, final_belief=parts[-1].final_belief, extras=extras)


def through_diffuse_phase(
    filt: RecursiveFilter,
    rest: Callable[..., FilterResult],
    measurements: Tensor,
    mask: Tensor | None,
    controls: Controls,
    belief: Belief,
) -> FilterResult:
    """Run ``filt`` step by step while ``belief`` has a diffuse part, then ``rest(measurements,
    mask=..., controls=..., belief=...)`` (e.g. a compiled twin of ``filt``) on the remaining
    steps; the results concatenated.  For engines that run the ordinary recursion only."""
    parts = []
    steps = measurements.shape[1]
    t = 0
    while t < steps and DIFFUSE_COV in belief:
        part = filt(
            measurements[:, t : t + 1],
            mask=None if mask is None else mask[:, t : t + 1],
            controls=slice_steps(controls, t, t + 1),
            belief=belief,
        )
        parts.append(part)
        belief = part.final_belief
        t += 1
    if t < steps:
        parts.append(
            rest(measurements[:, t:], mask=None if mask is None else mask[:, t:], controls=slice_steps(controls, t, steps), belief=belief)
        )
    return concat_results(parts)
