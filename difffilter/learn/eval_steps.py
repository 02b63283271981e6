"""Validation and test steps of :class:`~difffilter.learn.learner.FilterLearner` (a mixin):
metric sums per batch, one reduction over DDP processes per epoch, the ``val/...``/``test/...``
metrics (and ``smoothed_*`` with a smoother).  Each step returns the filter's result of its batch
(what callbacks such as :class:`~difffilter.learn.plots.DiagnosticFigures` receive as
``outputs``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from ..evaluate.metrics import finalize_metrics, metric_sums
from ..filters.protocol import FilterResult
from ..smoothers import SmootherResult

__all__ = ["EvaluationSteps"]

_SMOOTHED_METRICS = ("rmse_pos", "rmse_state", "anees")


class EvaluationSteps:
    """Validation/test hooks of a learner; the learner provides ``__call__``, ``loss_fn``,
    ``_reduce_loss``, ``smooth``, ``_smoother`` and ``indices``, and the state ``_sums``."""

    _sums: dict[str, torch.Tensor]

    def _eval_step(self: Any, batch: Mapping[str, Any], stage: str) -> FilterResult:
        result = self(batch)
        loss, bad = self._reduce_loss(self.loss_fn(result, batch), stage)
        n = int(batch["measurements"].shape[0])
        f64 = torch.float64
        filtered = result.filtered if isinstance(result, SmootherResult) else result
        sums = metric_sums(filtered, batch.get("truth"), **self.indices)
        if self._smoother is not None and batch.get("truth") is not None:
            smoothed = result if isinstance(result, SmootherResult) else self.smooth(result, batch)
            sums.update({f"smoothed/{k}": v for k, v in metric_sums(smoothed, batch["truth"], **self.indices).items()})
        sums["loss_sum"] = (loss.detach() if loss is not None else torch.zeros((), device=self.device)).to(f64) * (n - bad)
        sums["loss_count"] = torch.tensor(float(n - bad), dtype=f64, device=self.device)
        for k, v in sums.items():
            self._sums[k] = self._sums.get(k, torch.zeros((), dtype=f64, device=self.device)) + v.to(f64)
        return filtered

    def _eval_epoch_end(self: Any, stage: str) -> None:
        keys = sorted(self._sums)
        if not keys:
            return
        packed = torch.stack([self._sums[k] for k in keys])
        if self.trainer.world_size > 1:
            packed = self.trainer.strategy.reduce(packed, reduce_op="sum")
        sums = dict(zip(keys, packed, strict=True))
        self._sums = {}
        metrics = finalize_metrics({k: v for k, v in sums.items() if not k.startswith("smoothed/")})
        smoothed = finalize_metrics({k.removeprefix("smoothed/"): v for k, v in sums.items() if k.startswith("smoothed/")})
        metrics.update({f"smoothed_{k}": smoothed[k] for k in _SMOOTHED_METRICS if k in smoothed})
        count = float(sums["loss_count"])
        metrics["loss"] = float(sums["loss_sum"]) / count if count > 0 else float("nan")
        # Already summed over processes above; sync_dist only averages identical values.
        self.log_dict({f"{stage}/{k}": v for k, v in metrics.items()}, on_step=False, on_epoch=True, batch_size=1, sync_dist=True)

    def on_validation_epoch_start(self) -> None:
        self._sums = {}

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> FilterResult:
        return self._eval_step(batch, "val")

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val")

    def on_test_epoch_start(self) -> None:
        self._sums = {}

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> FilterResult:
        return self._eval_step(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test")
