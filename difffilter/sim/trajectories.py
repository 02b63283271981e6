"""One container for a batch of trajectories: :class:`TrajectorySet`.

Every producer of trajectories hands one over: :func:`~difffilter.sim.sample_trajectories`
(:class:`~difffilter.sim.SampledTrajectories`, a subclass with the drawn initial state and the
sampling model), the papers' simulators (subclasses with their scenario, true parameters and
``make_model``) and :class:`~difffilter.learn.data.TrajectoryDataModule`, whose train/val/test sets
are the normalised form :meth:`TrajectorySet.from_simulation` builds (floats in one dtype, the
initial belief per trajectory, the producer's object kept as ``source``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..models.base import Controls

__all__ = ["TrajectorySet", "cast_controls", "map_controls"]

Batch = dict[str, Any]


def map_controls(controls: Controls, fn: Callable[[Tensor], Tensor]) -> Controls:
    """``fn`` applied to every per-step input (a tensor or a dict of tensors; ``None`` stays ``None``)."""
    if controls is None:
        return None
    if isinstance(controls, Tensor):
        return fn(controls)
    return {k: fn(v) for k, v in controls.items()}


def cast_controls(controls: Controls, dtype: torch.dtype) -> Controls:
    """Floating-point per-step inputs cast to ``dtype`` (others, e.g. integer ids, unchanged)."""
    return map_controls(controls, lambda v: v.to(dtype) if v.is_floating_point() else v)


def _cast(x: Tensor | None, dtype: torch.dtype) -> Tensor | None:
    return x.to(dtype) if x is not None and x.is_floating_point() else x


@dataclass(kw_only=True)
class TrajectorySet:
    """``N`` trajectories of ``T`` steps (batch-first; keyword-only fields).

    Attributes:
        measurements: ``[N, T, m]`` (NaN where ``mask`` is False).
        mask: ``[N, T]`` or ``[N, T, m]`` bool, True = observed; ``None``: all observed.
        controls: per-step inputs ``[N, T, ...]`` (a tensor or a dict of them) or ``None``.
        truth: ``[N, T, n_t]`` true states, or ``None``.
        initial_mean, initial_cov: the belief before the first measurement, ``[N, n]`` (or one
            ``[n]`` for all) and ``[N, n, n]`` (or ``[n, n]``); ``None`` when the producer gives
            none (the learner then uses its own).
        modes: ``[N, T]`` true mode index of every step, when known (drawn over IMM mode
            probabilities in the figures).
        source: in a normalised set (:meth:`from_simulation`), the producer's own object
            (``true_params``, ``make_model()``...).

    Subclasses (a paper's trajectories) add fields, e.g. ``true_params`` and ``make_model()``
    for oracles; :meth:`from_simulation` also accepts any object with these attributes.
    """

    measurements: Tensor
    mask: Tensor | None = None
    controls: Controls = None
    truth: Tensor | None = None
    initial_mean: Tensor | None = None
    initial_cov: Tensor | None = None
    modes: Tensor | None = None
    source: Any = None

    @classmethod
    def from_simulation(cls, data: Any, dtype: torch.dtype | None = None, max_steps: int | None = None) -> TrajectorySet:
        """Normalise a simulator's output (shapes checked, floats cast to ``dtype``, time cut to
        the first ``max_steps`` steps)."""
        z = data.measurements
        if not isinstance(z, Tensor) or z.ndim != 3:
            raise ValueError(f"simulator output must have measurements [B, T, m], got {getattr(z, 'shape', type(z))}")
        dtype = dtype or z.dtype
        n_traj, steps = z.shape[:2]
        cut = slice(0, steps if max_steps is None else min(int(max_steps), steps))
        mean0 = getattr(data, "initial_mean", None)
        cov0 = getattr(data, "initial_cov", None)
        if mean0 is not None and mean0.ndim == 1:
            mean0 = mean0.expand(n_traj, -1)
        if cov0 is not None and cov0.ndim == 2:
            cov0 = cov0.expand(n_traj, -1, -1)
        truth = getattr(data, "truth", None)
        modes = getattr(data, "modes", None)
        return TrajectorySet(
            measurements=z[:, cut].to(dtype),
            mask=None if getattr(data, "mask", None) is None else data.mask[:, cut],
            controls=cast_controls(map_controls(getattr(data, "controls", None), lambda v: v[:, cut]), dtype),
            truth=None if truth is None else truth[:, cut].to(dtype),
            initial_mean=_cast(mean0, dtype),
            initial_cov=_cast(cov0, dtype),
            source=data,
            modes=modes[:, cut] if isinstance(modes, Tensor) else None,
        )

    def __len__(self) -> int:
        return int(self.measurements.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.measurements.shape[1])

    def batch(self, index: Tensor, start: int = 0, stop: int | None = None) -> Batch:
        """Trajectories ``index`` restricted to steps ``[start, stop)`` as a batch dict."""
        t = slice(start, stop)
        pick: Callable[[Tensor], Tensor] = lambda v: v[index][:, t]  # noqa: E731
        return {
            "measurements": pick(self.measurements),
            "mask": None if self.mask is None else pick(self.mask),
            "controls": map_controls(self.controls, pick),
            "truth": None if self.truth is None else pick(self.truth),
            "initial_mean": _per_trajectory(self.initial_mean, 1, len(self), index),
            "initial_cov": _per_trajectory(self.initial_cov, 2, len(self), index),
            "index": index,
            "modes": None if self.modes is None else pick(self.modes),
        }

    def all(self) -> Batch:
        """Every trajectory, whole, as one batch."""
        out = self.batch(torch.arange(len(self)))
        out.update(window_index=0, num_windows=1, start=0)
        return out


def _per_trajectory(x: Tensor | None, event_dims: int, n: int, index: Tensor) -> Tensor | None:
    """Rows ``index`` of ``x [N, ...]``, or of ``x`` shared by all ``n`` trajectories (``event_dims`` dims)."""
    if x is None:
        return None
    return (x.expand(n, *x.shape) if x.ndim == event_dims else x)[index]
