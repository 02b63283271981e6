"""The one time loop shared by every filter and mixer, and the shared Gaussian update.

Subclasses of :class:`GaussianFilter` implement :meth:`~GaussianFilter.predict` and
:meth:`~GaussianFilter.update` on a *belief*: a ``dict`` of tensors with at least ``"mean"``
``[B, n]`` and ``"cov"`` ``[B, n, n]`` plus whatever the filter carries between steps (square-root
factors, residual statistics, previous measurements, mode probabilities...).  The loop here does
input validation, mask handling, per-step bookkeeping and result assembly, so every filter
shares the same semantics:

* ``(initial_mean, initial_cov)`` is the belief *before* the first measurement; every step
  predicts, then updates.
* ``mask[b, t]`` (or ``mask[b, t, i]``) False means missing.  Missing components are removed
  from the update exactly (their innovation, cross-covariance and innovation-covariance rows are
  zeroed and the diagonal set to one, which is the update on the observed subset); a fully
  missing step is predict-only with log-likelihood 0.  Values under a False mask (NaN allowed)
  are replaced by zeros before any arithmetic, so they reach neither outputs nor gradients.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from ..models.base import Controls, DynamicsModel, MeasurementModel, StateSpaceModel
from ..params import check_covariance
from .diffuse import DIFFUSE_COV, DIFFUSE_SCALE, drop_resolved, measurement_sensitivity, split_prior, total_cov
from .update import (
    Belief,
    StepInfo,
    diffuse_gaussian_update,
    gaussian_update,
    mask_measurement_system,
    square_root_deviations,
    untrusted_steps,
)

__all__ = [
    "Belief",
    "FilterResult",
    "GaussianFilter",
    "StepInfo",
    "diffuse_gaussian_update",
    "gaussian_update",
    "mask_measurement_system",
    "concat_results",
    "slice_controls",
    "slice_steps",
    "square_root_deviations",
    "through_diffuse_phase",
    "detach_belief",
]


@dataclass
class FilterResult:
    """Outputs of a filter run over ``T`` steps (batch-first).

    Attributes:
        mean, cov: posterior after the update at every step, ``[B, T, n]``, ``[B, T, n, n]``.
        prior_mean, prior_cov: prior after the prediction at every step.
        log_likelihood: ``[B, T]`` innovation log-likelihood per step (0 for a missing step).
        nis: ``[B, T]`` normalised innovation squared; ``num_observed [B, T]`` its degrees of
            freedom (observed measurement components).
        final_belief: the full belief after the last step, to continue filtering (TBPTT).
        extras: filter-specific per-step outputs (IMM: ``mode_probs [B, T, M]``...), also
            reachable as attributes (``result.mode_probs``).  Every filter of this package
            adds ``untrusted [B, T]`` (bool): steps whose update could not be vouched for to
            ``1e-2`` relative (a repaired innovation covariance, a variance reduction beyond
            what the update's form resolves in this dtype, a non-finite or negative posterior
            variance).
    """

    mean: Tensor
    cov: Tensor
    prior_mean: Tensor
    prior_cov: Tensor
    log_likelihood: Tensor
    nis: Tensor
    num_observed: Tensor
    final_belief: Belief
    extras: dict[str, Tensor] = field(default_factory=dict)

    def __getattr__(self, name: str) -> Tensor:
        extras = self.__dict__.get("extras", {})
        if name in extras:
            return extras[name]
        raise AttributeError(name)

    @property
    def total_log_likelihood(self) -> Tensor:
        """``[B]`` sum of the per-step log-likelihoods."""
        return self.log_likelihood.sum(-1)


def slice_controls(controls: Controls, t: int) -> Controls:
    """Step ``t`` of per-step inputs ``[B, T, ...]`` (tensor or dict of tensors)."""
    if controls is None:
        return None
    if isinstance(controls, Tensor):
        return controls[:, t]
    return {k: v[:, t] for k, v in controls.items()}


def detach_belief(belief: Belief) -> Belief:
    """Detach every tensor of a belief (truncated back-propagation boundaries)."""
    return {k: v.detach() for k, v in belief.items()}


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
    filt: GaussianFilter,
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


class GaussianFilter(nn.Module):
    """Base class: one time loop, subclasses implement :meth:`predict` and :meth:`update`.

    Filters hold parameters (through their model), never beliefs: :meth:`forward` is a pure
    function of its inputs.
    """

    #: Belief entries that :meth:`step` / ``forward`` record per step besides mean/cov.
    record_keys: tuple[str, ...] = ()
    #: Split an initial covariance that is dangerously wide against the measurement noise into
    #: an exact diffuse part (:mod:`difffilter.filters.diffuse`); set False on an instance to
    #: run every step in plain covariance form.
    diffuse_prior: bool = True

    def __init__(self, model: StateSpaceModel) -> None:
        super().__init__()
        if not isinstance(model, StateSpaceModel):
            raise TypeError(f"model must be a difffilter StateSpaceModel, got {type(model).__name__}")
        self.model = model

    # -- dimensions -------------------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        return self.model.state_dim

    @property
    def measurement_dim(self) -> int:
        return self.model.measurement_dim

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

    # -- validation -------------------------------------------------------------------------
    def _param_dtype(self) -> torch.dtype | None:
        for p in self.parameters():
            if p.is_floating_point():
                return p.dtype
        for b in self.buffers():
            if b.is_floating_point():
                return b.dtype
        return None

    def check_inputs(
        self, measurements: Tensor, initial_mean: Tensor | None, initial_cov: Tensor | None, mask: Tensor | None, controls: Controls
    ) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor | None]:
        """Validate shapes, dtypes and values; return ``(z, mask [B,T,m] or None, mean, cov)``."""
        n, m = self.state_dim, self.measurement_dim
        if not isinstance(measurements, Tensor):
            raise TypeError(f"measurements must be a torch.Tensor [B, T, {m}], got {type(measurements).__name__}")
        if not measurements.is_floating_point():
            raise TypeError(f"measurements must be floating point, got {measurements.dtype}")
        if measurements.ndim != 3 or measurements.shape[-1] != m:
            raise ValueError(f"measurements must have shape [B, T, {m}], got {tuple(measurements.shape)}")
        bsz, steps = measurements.shape[:2]
        if bsz == 0 or steps == 0:
            raise ValueError(
                f"measurements must hold at least one trajectory and one step (B >= 1, T >= 1), got shape {tuple(measurements.shape)}"
            )
        dtype = measurements.dtype
        pdt = self._param_dtype()
        if pdt is not None and pdt != dtype:
            raise TypeError(f"measurements dtype {dtype} differs from the filter's parameter dtype {pdt}; convert one with .to()")
        self.check_parameters()
        if mask is not None:
            if not isinstance(mask, Tensor):
                raise TypeError("mask must be a bool tensor [B, T] or [B, T, m]")
            if mask.shape == (bsz, steps):
                mask = mask[..., None].expand(bsz, steps, m)
            elif mask.shape != (bsz, steps, m):
                raise ValueError(
                    f"mask must have shape [B, T] = [{bsz}, {steps}] or [B, T, m] = [{bsz}, {steps}, {m}], got {tuple(mask.shape)}"
                )
            if mask.dtype != torch.bool:
                if mask.is_complex() or not bool(((mask == 0) | (mask == 1)).all()):
                    raise ValueError("mask must be boolean (True = observed) or hold only 0 and 1")
                mask = mask.to(torch.bool)
        finite = torch.isfinite(measurements)
        bad = ~finite if mask is None else (~finite & mask)
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"measurements contain a non-finite value at [b, t, i] = {list(idx)} that is not masked; "
                "pass mask=False there to mark it missing"
            )
        if mask is not None:
            measurements = torch.where(mask, measurements, torch.zeros((), dtype=dtype, device=measurements.device))
        if initial_mean is not None:
            initial_mean = self._check_mean(initial_mean, bsz, n, dtype)
        if initial_cov is not None:
            initial_cov = self._check_cov(initial_cov, bsz, n, dtype)
        self._check_controls(controls, bsz, steps)
        return measurements, mask, initial_mean, initial_cov

    def check_parameters(self) -> None:
        """Refuse a non-finite raw parameter (e.g. after a diverged optimiser step) before it
        turns a whole batch into NaN; the error names the parameter."""
        for name, p in self.named_parameters():
            if not bool(torch.isfinite(p).all()):
                readable = name.replace("parametrizations.", "").replace(".original", "")
                raise ValueError(
                    f"parameter {readable} ({name}) holds non-finite raw values; set a finite constrained value "
                    f"(e.g. module.{readable.rsplit('.', 1)[-1]} = ...) or restore a checkpoint"
                )

    @staticmethod
    def _check_mean(mean: Tensor, bsz: int, n: int, dtype: torch.dtype) -> Tensor:
        if not isinstance(mean, Tensor):
            raise TypeError(f"initial_mean must be a torch.Tensor [{n}] or [B, {n}]")
        if mean.dtype != dtype:
            raise TypeError(f"initial_mean dtype {mean.dtype} differs from measurements dtype {dtype}")
        if mean.shape == (n,):
            mean = mean.expand(bsz, n)
        elif mean.shape != (bsz, n):
            raise ValueError(f"initial_mean must have shape [{n}] or [B, {n}] = [{bsz}, {n}], got {tuple(mean.shape)}")
        bad = ~torch.isfinite(mean).all(-1)
        if bool(bad.any()):
            raise ValueError(f"initial_mean contains non-finite values (batch elements {bad.nonzero().flatten().tolist()[:10]})")
        return mean

    @staticmethod
    def _check_cov(cov: Tensor, bsz: int, n: int, dtype: torch.dtype) -> Tensor:
        if not isinstance(cov, Tensor):
            raise TypeError(f"initial_cov must be a torch.Tensor [{n}, {n}] or [B, {n}, {n}]")
        if cov.dtype != dtype:
            raise TypeError(f"initial_cov dtype {cov.dtype} differs from measurements dtype {dtype}")
        if cov.shape == (n, n):
            cov = cov.expand(bsz, n, n)
        elif cov.shape != (bsz, n, n):
            raise ValueError(f"initial_cov must have shape [{n}, {n}] or [B, {n}, {n}] = [{bsz}, {n}, {n}], got {tuple(cov.shape)}")
        return check_covariance("initial_cov", cov, n, batch_ok=True)

    def _check_controls(self, controls: Controls, bsz: int, steps: int) -> None:
        if controls is None:
            return
        items = [("controls", controls)] if isinstance(controls, Tensor) else [(f"controls[{k!r}]", v) for k, v in dict(controls).items()]
        for name, v in items:
            if not isinstance(v, Tensor):
                raise TypeError(f"{name} must be a tensor [B, T, ...]")
            if v.ndim < 2 or v.shape[0] != bsz or v.shape[1] != steps:
                raise ValueError(f"{name} must have shape [B, T, ...] = [{bsz}, {steps}, ...], got {tuple(v.shape)}")
        for module in self.modules():
            if isinstance(module, (DynamicsModel, MeasurementModel)):
                module.validate_controls(controls)

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
        z, mk, _, _ = self.check_inputs(z, None, None, mk, u)
        with parametrize.cached():
            prior = self.predict(belief, controls)
            post, info = self.update(prior, z[:, 0], None if mk is None else mk[:, 0], controls)
            return drop_resolved(self.finalize_belief(post)), prior, info

    def initial_belief(
        self, initial_mean: Tensor, initial_cov: Tensor, batch_size: int | None = None, *, controls: Controls = None
    ) -> Belief:
        """Validated starting belief for :meth:`step` (broadcast to ``batch_size``); ``controls``
        (``[B, ...]``, the first step's inputs) for the diffuse-prior check of a model that needs
        them (:meth:`start_belief`)."""
        bsz = batch_size if batch_size is not None else (initial_mean.shape[0] if initial_mean.ndim == 2 else 1)
        mean = self._check_mean(initial_mean, bsz, self.state_dim, initial_mean.dtype)
        cov = self._check_cov(initial_cov, bsz, self.state_dim, initial_cov.dtype)
        return self.start_belief(mean, cov, controls)

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
        """
        z, mask3, mean0, cov0 = self.check_inputs(measurements, initial_mean, initial_cov, mask, controls)
        if belief is None and (mean0 is None or cov0 is None):
            raise ValueError("initial_mean and initial_cov are required unless belief= is given")
        steps = z.shape[1]
        means, covs, pmeans, pcovs, lls, nis, nobs = [], [], [], [], [], [], []
        extras: dict[str, list[Tensor]] = {}
        flags: list[tuple[Tensor | None, Tensor | None, bool]] = []
        with parametrize.cached():
            if belief is None:
                belief = self.start_belief(mean0, cov0, slice_controls(controls, 0))
            for t in range(steps):
                u = slice_controls(controls, t)
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
                flags.append((info.untrusted, info.jitter, DIFFUSE_COV in prior))
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
        result.extras["untrusted"] = _untrusted(result, flags)
        return result


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
