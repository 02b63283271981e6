"""The plain settings of a :class:`~difffilter.learn.learner.FilterLearner`: :class:`LearnerOptions`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from torch import Tensor

from ..smoothers import smoother_spec

__all__ = ["LearnerOptions"]

_INDEX_FIELDS = ("position_index", "truth_position_index", "state_index", "truth_index")


@dataclass(frozen=True)
class LearnerOptions:
    """The plain settings of a :class:`FilterLearner` (kept in its checkpoints).

    Attributes:
        initial_mean, initial_cov: ``[n]``, ``[n, n]`` (or the ``[n]`` diagonal) initial belief
            used when the batches carry none.
        max_jitter: largest relative Cholesky jitter allowed while filtering (``None``: default).
        smoother: ``None``, ``"rts"``, ``"fixed_lag"`` or a mapping (see the module docstring);
            the smoother runs on the filter's result (also a fused one).
        position_index, truth_position_index: state/truth components of the position (for
            ``rmse_pos`` and the trajectory figure).
        state_index, truth_index: state/truth components for ``rmse_state`` and NEES.
        scheduler_interval: ``"epoch"`` or ``"step"``: when the LR scheduler steps.
        monitor: metric a plateau scheduler watches.
        max_logged_elements: larger parameters log only their diagonal / norm.
    """

    initial_mean: Tensor | Sequence[float] | None = None
    initial_cov: Tensor | Sequence[Any] | None = None
    max_jitter: float | None = None
    smoother: str | Mapping[str, Any] | None = None
    position_index: Sequence[int] | None = None
    truth_position_index: Sequence[int] | None = None
    state_index: Sequence[int] | None = None
    truth_index: Sequence[int] | None = None
    scheduler_interval: str = "epoch"
    monitor: str = "val/loss"
    max_logged_elements: int = 64

    def __post_init__(self) -> None:
        if self.scheduler_interval not in ("epoch", "step"):
            raise ValueError(f"scheduler_interval must be 'epoch' or 'step', got {self.scheduler_interval!r}")
        for name in _INDEX_FIELDS:
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, [int(i) for i in value])
        smoother_spec(self.smoother)  # a bad kind or setting fails here, naming it

    @classmethod
    def of(cls, value: LearnerOptions | Mapping[str, Any] | None) -> LearnerOptions:
        """``value`` itself, the options of a mapping of their fields (a checkpoint's), or the defaults."""
        if value is None or isinstance(value, LearnerOptions):
            return value or cls()
        if not isinstance(value, Mapping):
            raise TypeError(f"options must be a LearnerOptions or a mapping of its fields, got {type(value).__name__}")
        unknown = set(value) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown learner options {sorted(unknown)}; known: {[f.name for f in dataclasses.fields(cls)]}")
        return cls(**value)

    def as_dict(self) -> dict[str, Any]:
        """The fields as plain values (tensors and plain containers: what a checkpoint keeps)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @property
    def indices(self) -> dict[str, list[int] | None]:
        """The four metric index fields by name (the keywords of :func:`~difffilter.evaluate.metrics.metric_sums`)."""
        return {name: getattr(self, name) for name in _INDEX_FIELDS}
