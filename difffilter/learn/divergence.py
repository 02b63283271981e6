"""Stop a training run that diverges instead of reporting it as a success.

The learner's stability kit (:mod:`difffilter.learn.learner`) skips a step whose loss or
gradient is not finite and leaves non-finite trajectories out of the batch mean, which is the
right answer to one bad window.  A run whose parameters run away is another matter: with
``optimizer.lr=1e6`` a noise variance reached 1.5e-154 and the learned filter's ANEES 1.1e154,
and the run still ended ``completed``.  :class:`DivergenceGuard` watches every training step and
raises :class:`TrainingDivergedError` (status ``diverged`` in ``status.json``, non-zero exit, the
reason in the message) when the run has diverged, meaning any of:

* **a non-finite learnable parameter** (raw or constrained value);
* **a scale parameter out of range**: every entry of a learnable *scale* parameter (a variance
  or other positive quantity: the diagonal of a ``PositiveDefinite``, ``FactorCovariance``,
  ``ScaledMatrix`` or ``GroupScaledCovariance`` value, every entry of a ``Positive`` one) must
  stay within a factor ``max_scale_ratio`` (default 1e12) of its value when training started,
  i.e. in ``[start / 1e12, start * 1e12]``.  Twelve orders of magnitude is far beyond any
  change of units or of a legitimate tuning (a variance learned from 1 to 1e-6 moves six), yet
  well inside float64's range, so a trip means the optimiser is walking off to a degenerate
  filter (a variance that no longer changes any result), not learning.  Entries that start at
  zero (a semi-definite base) are not checked;
* **an absurd loss**: the training loss of a step differs from the first finite step's loss
  ``L0`` by more than ``max_loss_ratio * max(|L0|, 1)`` (default 1e6).  The ``max(., 1)``
  keeps a loss that starts near zero (an NLL crossing zero) from tripping on an ordinary change;
  a negative log-likelihood that moves by a million times its start means a covariance has
  collapsed or exploded;
* **no finite step for a while**: ``max_skipped_steps`` (default 20) consecutive steps skipped
  for a non-finite loss or gradient: the parameters no longer produce a usable filter.

The limits are the ``divergence`` node of the training config (``conf/common.yaml``);
``divergence.enabled=false`` turns the guard off.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Callback
from torch import Tensor, nn
from torch.nn.utils import parametrize

from ..constraints import FactorCovariance, Positive, PositiveDefinite
from ..params import GroupScaledCovariance, ScaledMatrix

__all__ = ["DivergenceGuard", "TrainingDivergedError", "scale_parameters"]

log = logging.getLogger(__name__)

_MATRIX_SCALES = (PositiveDefinite, FactorCovariance, ScaledMatrix, GroupScaledCovariance)


class TrainingDivergedError(RuntimeError):
    """Training stopped because the run diverged; ``reason`` says which check tripped."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"training diverged: {reason}")
        self.reason = reason


def scale_parameters(module: nn.Module) -> dict[str, Tensor]:
    """The learnable scale quantities below ``module``: ``{dotted.name: positive entries}`` (the
    diagonal of a covariance-type value, every entry of a ``Positive`` one), detached."""
    out: dict[str, Tensor] = {}
    for mod_name, mod in module.named_modules():
        if not parametrize.is_parametrized(mod):
            continue
        for pname, plist in mod.parametrizations.items():
            if not plist.original.requires_grad:
                continue
            constraint = plist[0]
            if isinstance(constraint, _MATRIX_SCALES):
                value = getattr(mod, pname).detach()
                entries = value.diagonal(dim1=-2, dim2=-1) if value.dim() >= 2 and value.shape[-1] == value.shape[-2] else value
            elif isinstance(constraint, Positive):
                entries = getattr(mod, pname).detach()
            else:
                continue
            out[f"{mod_name}.{pname}" if mod_name else pname] = entries.reshape(-1).clone()
    return out


class DivergenceGuard(Callback):
    """Raise :class:`TrainingDivergedError` when a training run diverges (module docstring).

    Args:
        max_scale_ratio: a learnable scale entry may move by at most this factor (either way)
            from its value when training started.
        max_loss_ratio: the training loss may differ from the first step's ``L0`` by at most
            ``max_loss_ratio * max(|L0|, 1)``.
        max_skipped_steps: consecutive steps skipped for a non-finite loss or gradient allowed.
        enabled: False turns every check off.
    """

    def __init__(
        self, *, max_scale_ratio: float = 1e12, max_loss_ratio: float = 1e6, max_skipped_steps: int = 20, enabled: bool = True
    ) -> None:
        for name, v in (("max_scale_ratio", max_scale_ratio), ("max_loss_ratio", max_loss_ratio)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 1:
                raise ValueError(f"divergence.{name} must be a finite number > 1, got {v!r}")
        if isinstance(max_skipped_steps, bool) or not isinstance(max_skipped_steps, int) or max_skipped_steps < 1:
            raise ValueError(f"divergence.max_skipped_steps must be an integer >= 1, got {max_skipped_steps!r}")
        self.max_scale_ratio = float(max_scale_ratio)
        self.max_loss_ratio = float(max_loss_ratio)
        self.max_skipped_steps = max_skipped_steps
        self.enabled = bool(enabled)
        self.start: dict[str, Tensor] = {}
        self.first_loss: float | None = None
        self._skipped_seen = 0
        self._skipped_run = 0

    def state_dict(self) -> dict[str, Any]:
        return {"start": {k: v.tolist() for k, v in self.start.items()}, "first_loss": self.first_loss}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.start = {k: torch.tensor(v, dtype=torch.float64) for k, v in state_dict.get("start", {}).items()}
        self.first_loss = state_dict.get("first_loss")

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self.start:  # a resumed run keeps the start of the run it continues
            self.start = {k: v.to(torch.float64) for k, v in scale_parameters(pl_module).items()}
        self._skipped_seen = int(getattr(pl_module, "skipped_steps", 0))
        self._skipped_run = 0

    def check(self, module: nn.Module, loss: float | None) -> None:
        """Raise :class:`TrainingDivergedError` if ``module``'s parameters or the step's ``loss``
        (None: the step had no finite loss) show divergence."""
        for name, p in module.named_parameters():
            if p.requires_grad and not bool(torch.isfinite(p.detach()).all()):
                raise TrainingDivergedError(f"learnable parameter {name} is not finite")
        lo, hi = 1.0 / self.max_scale_ratio, self.max_scale_ratio
        for name, now in scale_parameters(module).items():
            now = now.to(torch.float64)
            if not bool(torch.isfinite(now).all()):
                raise TrainingDivergedError(f"{name} is not finite ({now.tolist()})")
            start = self.start.get(name)
            if start is None or start.shape != now.shape:
                continue
            ok = start > 0
            ratio = now[ok] / start[ok]
            bad = (ratio < lo) | (ratio > hi)
            if bool(bad.any()):
                i = int(bad.nonzero()[0])
                raise TrainingDivergedError(
                    f"{name} moved from {float(start[ok][i]):.3g} to {float(now[ok][i]):.3g}, beyond the factor "
                    f"divergence.max_scale_ratio={self.max_scale_ratio:g} of its start"
                )
        if loss is None:
            return
        if not math.isfinite(loss):
            return  # counted as a skipped step by the learner
        if self.first_loss is None:
            self.first_loss = loss
            return
        limit = self.max_loss_ratio * max(abs(self.first_loss), 1.0)
        if abs(loss - self.first_loss) > limit:
            raise TrainingDivergedError(
                f"training loss {loss:.3g} is beyond divergence.max_loss_ratio={self.max_loss_ratio:g} times the first step's "
                f"({self.first_loss:.3g})"
            )

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if not self.enabled:
            return
        skipped = int(getattr(pl_module, "skipped_steps", 0))
        was_skipped = skipped > self._skipped_seen  # its loss is the learner's zero stand-in
        self._skipped_run = self._skipped_run + 1 if was_skipped else 0
        self._skipped_seen = skipped
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        value = float(loss.detach()) if isinstance(loss, Tensor) and not was_skipped else None
        if self._skipped_run >= self.max_skipped_steps:
            raise TrainingDivergedError(
                f"{self._skipped_run} consecutive steps had a non-finite loss or gradient "
                f"(divergence.max_skipped_steps={self.max_skipped_steps})"
            )
        self.check(pl_module, value)
