"""Sequential measurement updates: one sensor (group of components) after the other."""

from __future__ import annotations

import torch
from torch import Tensor

from ..models.base import Controls, StateSpaceModel
from .base import Belief, RecursiveFilter, StepInfo

__all__ = ["SequentialUpdate"]


class SequentialUpdate(RecursiveFilter):
    """Wraps a filter so that each step's update processes the measurement groups in turn.

    The prediction is the wrapped filter's; the update runs the wrapped filter's own update once
    per group, each time with the step's mask restricted to that group (the filters' masked
    update is exactly the update with those components alone), starting from the previous
    group's posterior.  Groups without an observed component in the whole batch are skipped.
    The step's log-likelihood is the sum over groups (``log p(z_1) + log p(z_2 | z_1) + ...``),
    which equals the joint update's for linear-Gaussian models; nonlinear filters relinearise (or
    redraw sigma points) after each group.  Filters whose update carries memory (RCUKF's
    residual statistics) apply it per group.

    Args:
        filter: the filter whose predict/update run (any :class:`RecursiveFilter`, IMM included).
        groups: measurement component indices per group, in update order; default: the sensors
            of a :class:`~difffilter.models.sensors.MultiSensorMeasurement` (``component_groups``),
            else one group per component.

    Learnable: the wrapped filter's parameters (same names under ``filter.``).
    """

    def __init__(self, filter: RecursiveFilter, *, groups: list[list[int]] | None = None) -> None:  # noqa: A002
        super().__init__()
        if not isinstance(filter, RecursiveFilter):
            raise TypeError(f"filter must be a difffilter RecursiveFilter, got {type(filter).__name__}")
        m = filter.measurement_dim
        if groups is None:
            meas = getattr(getattr(filter, "model", None), "measurement", None)
            groups = meas.component_groups() if hasattr(meas, "component_groups") else [[i] for i in range(m)]
        flat = [int(i) for g in groups for i in g]
        if not groups or any(len(g) == 0 for g in groups) or sorted(flat) != list(range(m)):
            raise ValueError(f"groups must partition the {m} measurement components into non-empty groups, got {groups}")
        self.filter = filter
        self.groups = [[int(i) for i in g] for g in groups]
        self.record_keys = filter.record_keys
        self.memory_keys = getattr(filter, "memory_keys", ())

    @property
    def model(self) -> StateSpaceModel:  # type: ignore[override]
        return self.filter.model

    @property
    def state_dim(self) -> int:
        return self.filter.state_dim

    @property
    def measurement_dim(self) -> int:
        return self.filter.measurement_dim

    def init_belief(self, mean: Tensor, cov: Tensor) -> Belief:
        return self.filter.init_belief(mean, cov)

    def attach_diffuse(self, belief: Belief, diffuse_cov: Tensor, scale: Tensor) -> Belief:
        return self.filter.attach_diffuse(belief, diffuse_cov, scale)

    def sensitivity(self, mean: Tensor, u: Controls) -> Tensor | None:
        return self.filter.sensitivity(mean, u)

    def predict(self, belief: Belief, u: Controls) -> Belief:
        return self.filter.predict(belief, u)

    def record(self, belief: Belief) -> dict[str, Tensor]:
        return self.filter.record(belief)

    def finalize_belief(self, belief: Belief) -> Belief:
        return self.filter.finalize_belief(belief)

    def update(self, belief: Belief, z: Tensor, mask: Tensor | None, u: Controls) -> tuple[Belief, StepInfo]:
        observed = torch.ones_like(z, dtype=torch.bool) if mask is None else mask
        zero = z.new_zeros(z.shape[:-1])
        ll, nis, nobs = zero, zero, zero
        untrusted, jitter = torch.zeros_like(z[..., 0], dtype=torch.bool), zero
        for group in self.groups:
            sel = torch.zeros(z.shape[-1], dtype=torch.bool, device=z.device)
            sel[group] = True
            gmask = observed & sel
            if not bool(gmask.any()):
                continue
            belief, info = self.filter.update(belief, z, gmask, u)
            ll, nis, nobs = ll + info.log_likelihood, nis + info.nis, nobs + info.num_observed
            flag = info.flags()
            if flag is not None:
                untrusted = untrusted | flag
            if info.jitter is not None:
                jitter = jitter + info.jitter
        return belief, StepInfo(ll, nis, nobs, untrusted=untrusted, jitter=jitter)
