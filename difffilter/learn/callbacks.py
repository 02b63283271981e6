"""Lightning callbacks of a training run: per-epoch summary lines, a checkpoint on SIGTERM/SIGINT,
and checkpoints that travel with a resumed run.

* :class:`EpochSummary` - one log line per epoch (``epoch 3/25: train/loss 7.91, val/loss
  7.86, val/rmse_pos 10.8 (1.2 s)``), into the run's log file and the console;
* :class:`GracefulInterrupt` - SIGTERM (a scheduler's stop, ``scancel``), SIGUSR2 (the warning
  the submitit launcher asks SLURM to send before a time limit) or SIGINT (Ctrl+C) during
  training lets the current batch finish, writes ``last.ckpt`` and stops the run with
  :class:`TrainingInterrupted` (exit status 128 + the signal number, so a scheduler does not
  record success); a second Ctrl+C stops at once;
* :class:`RunCheckpoint` - Lightning's ``ModelCheckpoint``; a run resumed from another run's
  checkpoint copies that run's kept checkpoints into its own directory and keeps their scores,
  so "best" means the same as in an uninterrupted run.
"""

from __future__ import annotations

import logging
import shutil
import signal
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import Callback, ModelCheckpoint
from pytorch_lightning.utilities.exceptions import SIGTERMException
from pytorch_lightning.utilities.rank_zero import rank_zero_only

__all__ = ["EpochSummary", "GracefulInterrupt", "RunCheckpoint", "TrainingInterrupted"]

log = logging.getLogger(__name__)

# Signals this module's handler takes over during training (SIGTERM goes through Lightning's own
# handler, trainer.received_sigterm).  SIGUSR2 is what submitit asks SLURM to send signal_delay_s
# before a time limit or at preemption; left to submitit's handler it would end the job without
# a checkpoint (it raises or requeues from inside the training step).
_HANDLED = tuple(getattr(signal, name) for name in ("SIGINT", "SIGUSR2") if hasattr(signal, name))


class TrainingInterrupted(SystemExit):
    """Training stopped by signal ``signum`` after writing ``checkpoint``; the process exits with
    status ``128 + signum`` (130 for SIGINT, 143 for SIGTERM), as a shell reports a signal."""

    def __init__(self, signum: int, checkpoint: str | None = None) -> None:
        super().__init__(128 + int(signum))
        self.signum, self.checkpoint = int(signum), checkpoint

    def __str__(self) -> str:
        name = signal.Signals(self.signum).name
        return f"training interrupted by {name}" + (f"; checkpoint {self.checkpoint}" if self.checkpoint else "")


class EpochSummary(Callback):
    """Log one line per training epoch with the epoch's metrics and its wall time.

    Args:
        keys: metrics shown when logged (``trainer.callback_metrics``), in this order.
    """

    def __init__(self, *, keys: tuple[str, ...] = ("train/loss_epoch", "val/loss", "val/rmse_pos", "val/anees", "val/nis")) -> None:
        self.keys = tuple(keys)
        self._start = 0.0

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._start = time.perf_counter()  # a run resumed mid-epoch starts no epoch

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._start = time.perf_counter()

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        metrics = trainer.callback_metrics
        parts = [f"{k.removesuffix('_epoch')} {float(metrics[k]):.4g}" for k in self.keys if k in metrics]
        total = trainer.max_epochs if trainer.max_epochs is not None and trainer.max_epochs >= 0 else "?"
        log.info("epoch %d/%s: %s (%.1f s)", trainer.current_epoch + 1, total, ", ".join(parts), time.perf_counter() - self._start)


class GracefulInterrupt(Callback):
    """On SIGTERM, SIGUSR2 or SIGINT during training: finish the batch, write a checkpoint, stop
    non-zero (``128 + signal``: 143, 140, 130).

    The checkpoint is written at a batch boundary (``on_train_batch_end``), the point from which
    Lightning, the data loader (:class:`~difffilter.learn.data.WindowedTrajectories`) and the
    learner resume exactly; under DDP the processes agree on the signal first.  A SIGTERM that
    Lightning turns into its own stop (at the end of an epoch or during validation) is
    checkpointed in :meth:`on_exception`.

    Args:
        dirpath: folder of the checkpoint (default: the ``ModelCheckpoint``'s, else
            ``<default_root_dir>/checkpoints``).
        filename: its name (``last.ckpt``: what ``resume=true`` continues from).
    """

    def __init__(self, *, dirpath: str | None = None, filename: str = "last.ckpt") -> None:
        self.dirpath, self.filename = dirpath, filename
        self.received: int | None = None
        self.saved: str | None = None
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:  # asked twice: stop now
            raise KeyboardInterrupt
        self.received = signum
        log.warning("received %s: finishing the batch, then writing a checkpoint (again to stop at once)", signal.Signals(signum).name)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.received, self.saved = None, None
        if threading.current_thread() is threading.main_thread():
            self._previous = {int(s): signal.signal(s, self._handler) for s in _HANDLED}

    def _restore(self) -> None:
        if self._previous and threading.current_thread() is threading.main_thread():
            for signum, previous in self._previous.items():
                signal.signal(signum, previous)
            self._previous = {}

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._restore()

    def _pending(self, trainer: pl.Trainer) -> int | None:
        signum = self.received or (int(signal.SIGTERM) if trainer.received_sigterm else 0)
        if trainer.world_size > 1:
            flag = torch.tensor(float(signum), device=trainer.strategy.root_device)
            signum = int(trainer.strategy.reduce(flag, reduce_op="max"))
        return signum or None

    def _save(self, trainer: pl.Trainer) -> str:
        folder = (
            self.dirpath or getattr(trainer.checkpoint_callback, "dirpath", None) or str(Path(trainer.default_root_dir) / "checkpoints")
        )
        path = str(Path(folder) / self.filename)
        trainer.save_checkpoint(path)
        self.saved = path
        log.warning("checkpoint written to %s", path)
        return path

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        signum = self._pending(trainer)
        if signum is not None:
            path = self._save(trainer)
            self._restore()
            raise TrainingInterrupted(signum, path)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        self._restore()
        if isinstance(exception, SIGTERMException) and self.saved is None:
            self._save(trainer)


class RunCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` whose state follows a run resumed into another directory: the
    checkpoints the interrupted run kept (best k, last) are copied into this run's ``dirpath``
    with their scores, instead of Lightning's default of forgetting the scores."""

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        old = state_dict.get("dirpath")
        if old is None or self.dirpath is None or Path(old).resolve() == Path(self.dirpath).resolve():
            super().load_state_dict(state_dict)
            return
        new = Path(self.dirpath)

        def moved(path: Any) -> Any:
            if not path or Path(path).parent.resolve() != Path(old).resolve():
                return path
            target = new / Path(path).name
            if rank_zero_only.rank == 0 and Path(path).is_file() and not target.exists():
                new.mkdir(parents=True, exist_ok=True)
                shutil.copy2(path, target)
            return str(target)

        state = dict(state_dict)
        state["dirpath"] = self.dirpath
        state["best_k_models"] = {moved(k): v for k, v in (state_dict.get("best_k_models") or {}).items()}
        for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
            state[key] = moved(state_dict.get(key))
        super().load_state_dict(state)
