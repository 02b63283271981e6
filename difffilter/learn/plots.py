"""Diagnostic figures (matplotlib, object-oriented API: no global pyplot state), and the
:class:`DiagnosticFigures` callback that logs them during training.

Each function draws one trajectory and returns a ``matplotlib.figure.Figure`` ready for
``SummaryWriter.add_figure`` or ``fig.savefig``.  Axes carry the state components' names and
units when the model has a :class:`~difffilter.models.layout.StateLayout` (``labels``, from
:func:`state_labels`), else ``state[i]``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
import torch
from matplotlib.figure import Figure
from torch import Tensor

from ..models.layout import StateLayout, model_defaults

__all__ = ["DiagnosticFigures", "diagnostic_figures", "plot_errors", "plot_mode_probs", "plot_trajectory", "state_labels"]


def state_labels(index: Sequence[int], layout: StateLayout | None = None) -> list[str]:
    """Axis labels of state components ``index``: ``"x [m]"`` from ``layout``, else ``"state[i]"``."""
    out = []
    for i in index:
        if layout is not None and 0 <= i < layout.dim:
            unit = layout.units[i]
            out.append(f"{layout.names[i]} [{unit}]" if unit else layout.names[i])
        else:
            out.append(f"state[{i}]")
    return out


def _np(x: Tensor) -> object:
    return x.detach().to("cpu", torch.float64).numpy()


def plot_trajectory(
    truth: Tensor | None,
    estimate: Tensor,
    *,
    position_index: Sequence[int],
    truth_position_index: Sequence[int] | None = None,
    measurements: Tensor | None = None,
    measurement_index: Sequence[int] | None = None,
    title: str = "trajectory",
    labels: Sequence[str] | None = None,
) -> Figure:
    """Truth vs estimate of one trajectory: the plane of the first two position components
    (``estimate [T, n]``, ``truth [T, n_t]``), or position against time for one component;
    ``labels`` name the position components (default ``state[i]``)."""
    fig = Figure(figsize=(6, 5))
    ax = fig.add_subplot()
    pi = list(position_index)
    ti = list(truth_position_index) if truth_position_index is not None else pi
    est = _np(estimate[:, pi])
    names = list(labels) if labels is not None else state_labels(pi)
    if len(pi) >= 2:
        if measurements is not None and measurement_index is not None:
            z = _np(measurements[:, list(measurement_index)])
            ax.plot(z[:, 0], z[:, 1], ".", ms=2, color="0.6", label="measurements")  # type: ignore[index]
        if truth is not None:
            tr = _np(truth[:, ti])
            ax.plot(tr[:, 0], tr[:, 1], "k-", lw=1.5, label="truth")  # type: ignore[index]
        ax.plot(est[:, 0], est[:, 1], "C1--", lw=1.2, label="estimate")  # type: ignore[index]
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal", adjustable="datalim")
    else:
        if truth is not None:
            ax.plot(_np(truth[:, ti[0]]), "k-", label="truth")
        ax.plot(est[:, 0], "C1--", label="estimate")  # type: ignore[index]
        ax.set_xlabel("step")
        ax.set_ylabel(names[0])
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def plot_errors(
    truth: Tensor,
    mean: Tensor,
    cov: Tensor,
    *,
    index: Sequence[int] | None = None,
    truth_index: Sequence[int] | None = None,
    title: str = "error and 3-sigma envelope",
    labels: Sequence[str] | None = None,
) -> Figure:
    """Estimation error of each selected component with the filter's ``±3 sigma`` envelope
    (``mean [T, n]``, ``cov [T, n, n]``, ``truth [T, n_t]``); ``labels`` name the components."""
    idx = list(index) if index is not None else list(range(mean.shape[-1]))
    tidx = list(truth_index) if truth_index is not None else idx
    names = list(labels) if labels is not None else state_labels(idx)
    err = _np(mean[:, idx] - truth[:, tidx])
    sd = _np(3.0 * torch.diagonal(cov, dim1=-2, dim2=-1)[:, idx].clamp_min(0).sqrt())
    fig = Figure(figsize=(7, 1.8 * len(idx) + 0.6))
    axes = fig.subplots(len(idx), 1, sharex=True, squeeze=False)[:, 0]
    for k, ax in enumerate(axes):
        ax.plot(err[:, k], "C0-", lw=1, label="error")  # type: ignore[index]
        ax.plot(sd[:, k], "C3--", lw=0.8, label="±3σ")  # type: ignore[index]
        ax.plot(-sd[:, k], "C3--", lw=0.8)  # type: ignore[index, operator]
        ax.set_ylabel(names[k])
    axes[0].set_title(title)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("step")
    fig.tight_layout()
    return fig


def plot_mode_probs(mode_probs: Tensor, *, true_modes: Tensor | None = None, names: Sequence[str] | None = None) -> Figure:
    """IMM mode probabilities ``[T, M]`` over time, with the true mode sequence ``[T]`` (mode
    indices) drawn over them when known: a step line at the height of the true mode's index
    scaled to ``[0, 1]`` (for two modes, the probability the true mode should have)."""
    mp = _np(mode_probs)
    fig = Figure(figsize=(7, 3))
    ax = fig.add_subplot()
    for j in range(mode_probs.shape[-1]):
        ax.plot(mp[:, j], lw=1.2, label=names[j] if names else f"mode {j}")  # type: ignore[index]
    if true_modes is not None:
        m = mode_probs.shape[-1]
        ax.step(range(true_modes.shape[0]), _np(true_modes.to(torch.float64) / max(m - 1, 1)), "k:", lw=1, where="post", label="true mode")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("step")
    ax.set_ylabel("probability")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def diagnostic_figures(
    data: Mapping[str, Any],
    *,
    position_index: Sequence[int] | None = None,
    truth_position_index: Sequence[int] | None = None,
    layout: StateLayout | None = None,
) -> dict[str, Figure]:
    """The figures of one trajectory: ``data`` holds ``mean [T, n]``, ``cov [T, n, n]`` and
    optionally ``truth [T, n_t]``, ``mode_probs [T, M]``, ``modes [T]`` (true mode indices).
    Returns ``{"trajectory", "error" (with a truth), "mode_probs" (with mode probabilities)}``."""
    mean = data["mean"]
    pos = list(position_index) if position_index is not None else list(range(min(2, mean.shape[-1])))
    tpos = list(truth_position_index) if truth_position_index is not None and position_index is not None else None
    labels = state_labels(pos, layout)
    figures = {"trajectory": plot_trajectory(data.get("truth"), mean, position_index=pos, truth_position_index=tpos, labels=labels)}
    if data.get("truth") is not None:
        figures["error"] = plot_errors(data["truth"], mean, data["cov"], index=pos, truth_index=tpos, labels=labels)
    if data.get("mode_probs") is not None:
        figures["mode_probs"] = plot_mode_probs(data["mode_probs"], true_modes=data.get("modes"))
    return figures


class DiagnosticFigures(pl.Callback):
    """Log :func:`diagnostic_figures` of the first trajectory of the first validation batch
    every ``every_n_epochs`` epochs (0: never), and of the test set, to every logger that takes
    figures (``add_figure``, e.g. TensorBoard): truth vs estimate, errors with their ±3 sigma
    envelope, and IMM mode probabilities when the result has ``mode_probs`` (with the true mode
    drawn over them when the data have ``modes``), axes named after the model's
    :class:`~difffilter.models.layout.StateLayout`.

    Works with a :class:`~difffilter.learn.learner.FilterLearner`, whose validation and test
    steps return the filter's result of the batch.
    """

    def __init__(self, *, every_n_epochs: int = 1) -> None:
        self.every_n_epochs = int(every_n_epochs)
        self._data: dict[str, Any] | None = None

    def _keep(self, outputs: Any, batch: Mapping[str, Any], batch_idx: int, dataloader_idx: int) -> None:
        if batch_idx != 0 or dataloader_idx != 0 or outputs is None:
            return
        first = lambda v: None if v is None else v[0].detach()  # noqa: E731
        self._data = {
            "truth": first(batch.get("truth")),
            "mean": first(outputs.mean),
            "cov": first(outputs.cov),
            "mode_probs": first(outputs.extras.get("mode_probs")),
            "modes": first(batch.get("modes")),
        }

    def on_validation_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:  # noqa: E501
        self._keep(outputs, batch, batch_idx, dataloader_idx)

    def on_test_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:  # noqa: E501
        self._keep(outputs, batch, batch_idx, dataloader_idx)

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        every = self.every_n_epochs
        if every > 0 and trainer.current_epoch % every == 0 and not trainer.sanity_checking:
            self._log(trainer, pl_module, "val")
        self._data = None

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._log(trainer, pl_module, "test")
        self._data = None

    def _log(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        writers = [lg.experiment for lg in trainer.loggers if hasattr(lg.experiment, "add_figure")]
        if self._data is None or not trainer.is_global_zero or not writers:
            return
        indices = getattr(pl_module, "indices", {})
        defaults = model_defaults(getattr(pl_module, "filter", None))
        figures = diagnostic_figures(
            self._data,
            position_index=indices.get("position_index"),
            truth_position_index=indices.get("truth_position_index"),
            layout=None if defaults is None else defaults.layout,
        )
        for writer in writers:
            for name, fig in figures.items():
                writer.add_figure(f"{stage}/{name}", fig, global_step=trainer.global_step, close=False)
