"""Validation and test steps of :class:`~difffilter.learn.learner.FilterLearner` (a mixin):
metric sums per batch, one reduction over DDP processes per epoch, the ``val/...``/``test/...``
metrics (and ``smoothed_*`` with a smoother) and the diagnostic figures."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from ..evaluate.metrics import finalize_metrics, metric_sums
from ..models.layout import model_defaults
from ..smoothers import SmootherResult
from .plots import diagnostic_figures

__all__ = ["EvaluationSteps"]

_SMOOTHED_METRICS = ("rmse_pos", "rmse_state", "anees")


class EvaluationSteps:
    """Validation/test hooks of a learner; the learner provides ``__call__``, ``loss_fn``,
    ``_reduce_loss``, ``smooth``, ``_smoother``, ``indices``, ``filter`` and
    ``figure_every_n_epochs``, and the state ``_sums``, ``_figure_data``."""

    _sums: dict[str, torch.Tensor]
    _figure_data: dict[str, Any] | None

    def _eval_step(self: Any, batch: Mapping[str, Any], batch_idx: int, stage: str) -> None:
        result = self(batch)
        loss, bad = self._reduce_loss(self.loss_fn(result, batch), stage)
        n = int(batch["measurements"].shape[0])
        f64 = torch.float64
        filtered = result.filtered if isinstance(result, SmootherResult) else result
        sums = metric_sums(filtered, batch.get("truth"), **self.indices)
        if self._smoother is not None and batch.get("truth") is not None:
            smoothed = result if isinstance(result, SmootherResult) else self.smooth(result, batch)
            sums.update({f"smoothed/{k}": v for k, v in metric_sums(smoothed, batch["truth"], **self.indices).items()})
        result = filtered
        sums["loss_sum"] = (loss.detach() if loss is not None else torch.zeros((), device=self.device)).to(f64) * (n - bad)
        sums["loss_count"] = torch.tensor(float(n - bad), dtype=f64, device=self.device)
        for k, v in sums.items():
            self._sums[k] = self._sums.get(k, torch.zeros((), dtype=f64, device=self.device)) + v.to(f64)
        if batch_idx == 0:
            self._figure_data = {
                "truth": None if batch.get("truth") is None else batch["truth"][0].detach(),
                "mean": result.mean[0].detach(),
                "cov": result.cov[0].detach(),
                "mode_probs": result.extras["mode_probs"][0].detach() if "mode_probs" in result.extras else None,
                "modes": None if batch.get("modes") is None else batch["modes"][0].detach(),
            }

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
        every = self.figure_every_n_epochs
        if stage == "test" or (every > 0 and self.current_epoch % every == 0 and not self.trainer.sanity_checking):
            self._log_figures(stage)

    def _log_figures(self: Any, stage: str) -> None:
        data = self._figure_data
        if data is None or not self.trainer.is_global_zero:
            return
        writers = [lg.experiment for lg in self.loggers if hasattr(lg.experiment, "add_figure")]
        if not writers:
            return
        defaults = model_defaults(self.filter)
        figures = diagnostic_figures(
            data,
            position_index=self.indices["position_index"],
            truth_position_index=self.indices["truth_position_index"],
            layout=None if defaults is None else defaults.layout,
        )
        for writer in writers:
            for name, fig in figures.items():
                writer.add_figure(f"{stage}/{name}", fig, global_step=self.global_step, close=False)

    def on_validation_epoch_start(self) -> None:
        self._sums, self._figure_data = {}, None

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        self._eval_step(batch, batch_idx, "val")

    def on_validation_epoch_end(self) -> None:
        self._eval_epoch_end("val")

    def on_test_epoch_start(self) -> None:
        self._sums, self._figure_data = {}, None

    def test_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        self._eval_step(batch, batch_idx, "test")

    def on_test_epoch_end(self) -> None:
        self._eval_epoch_end("test")
