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

``GaussianFilter`` is the former name of :class:`RecursiveFilter`, kept as an alias.  The shared
vocabulary (:class:`~difffilter.filters.protocol.FilterResult`, ``Belief``, :class:`StepInfo`,
:func:`gaussian_update`...) is re-exported here for the filters built on the loop.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.nn.utils import parametrize

from ..models.base import Controls
from ._common import StepInfo, detach_belief, gaussian_update, mask_measurement_system, slice_controls
from .protocol import Belief, Filter, FilterResult

__all__ = [
    "Belief",
    "FilterResult",
    "GaussianFilter",
    "RecursiveFilter",
    "StepInfo",
    "detach_belief",
    "gaussian_update",
    "mask_measurement_system",
    "slice_controls",
]


class RecursiveFilter(Filter):
    """One time loop; subclasses implement :meth:`predict` and :meth:`update` (and, when their
    belief carries more than ``mean``/``cov``, :meth:`init_belief`).

    Constructed like every :class:`~difffilter.filters.protocol.Filter`: on a state-space
    ``model``, or on none for filters that combine others (the IMM).  Filters hold parameters
    (through their model), never beliefs: :meth:`forward` is a pure function of its inputs.
    """

    #: Belief entries that :meth:`step` / ``forward`` record per step besides mean/cov.
    record_keys: tuple[str, ...] = ()

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
            return self.finalize_belief(post), prior, info

    def initial_belief(self, initial_mean: Tensor, initial_cov: Tensor, batch_size: int | None = None) -> Belief:
        """Validated starting belief for :meth:`step` (broadcast to ``batch_size``)."""
        bsz = batch_size if batch_size is not None else (initial_mean.shape[0] if initial_mean.ndim == 2 else 1)
        mean = self._check_mean(initial_mean, bsz, self.state_dim, initial_mean.dtype)
        cov = self._check_cov(initial_cov, bsz, self.state_dim, initial_cov.dtype)
        return self.init_belief(mean, cov)

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
        if belief is None:
            if mean0 is None or cov0 is None:
                raise ValueError("initial_mean and initial_cov are required unless belief= is given")
            belief = self.init_belief(mean0, cov0)
        steps = z.shape[1]
        means, covs, pmeans, pcovs, lls, nis, nobs = [], [], [], [], [], [], []
        extras: dict[str, list[Tensor]] = {}
        with parametrize.cached():
            for t in range(steps):
                u = slice_controls(controls, t)
                prior = self.predict(belief, u)
                post, info = self.update(prior, z[:, t], None if mask3 is None else mask3[:, t], u)
                belief = self.finalize_belief(post)
                means.append(belief["mean"])
                covs.append(belief["cov"])
                pmeans.append(prior["mean"])
                pcovs.append(prior["cov"])
                lls.append(info.log_likelihood)
                nis.append(info.nis)
                nobs.append(info.num_observed)
                for k, v in self.record(belief).items():
                    extras.setdefault(k, []).append(v)
        stack: Any = lambda xs: torch.stack(xs, 1)  # noqa: E731
        return FilterResult(
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


#: The former name of :class:`RecursiveFilter` (kept for existing code and configs).
GaussianFilter = RecursiveFilter
