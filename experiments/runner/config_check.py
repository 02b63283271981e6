"""Check the numbers of a training config before anything is built from it.

A value of the wrong type typed on the command line used to surface deep inside Lightning or
torch: ``trainer.max_epochs=two`` as a bare ``AssertionError``, ``optimizer.lr=abc`` as a
``TypeError`` naming no key.  :func:`check_config` reads the keys below and raises a
``ValueError`` naming the key, the value given and the value expected.
"""

from __future__ import annotations

import math
from typing import Any

from omegaconf import DictConfig, OmegaConf

__all__ = ["CHECKS", "check_config"]


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


#: ``{dotted key: (test, what is expected)}``; an absent or null key is not checked.
CHECKS: dict[str, tuple[Any, str]] = {
    "trainer.max_epochs": (lambda v: _int(v) and v >= -1, "an integer >= -1 (-1: no limit)"),
    "trainer.min_epochs": (lambda v: _int(v) and v >= 0, "an integer >= 0"),
    "trainer.max_steps": (lambda v: _int(v) and v >= -1, "an integer >= -1 (-1: no limit)"),
    "trainer.log_every_n_steps": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "trainer.check_val_every_n_epoch": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "trainer.accumulate_grad_batches": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "trainer.num_sanity_val_steps": (lambda v: _int(v) and v >= -1, "an integer >= -1"),
    "trainer.gradient_clip_val": (lambda v: _number(v) and v >= 0, "a number >= 0"),
    "trainer.limit_train_batches": (lambda v: _number(v) and v >= 0, "a number >= 0 (a fraction or a count)"),
    "trainer.limit_val_batches": (lambda v: _number(v) and v >= 0, "a number >= 0 (a fraction or a count)"),
    "trainer.limit_test_batches": (lambda v: _number(v) and v >= 0, "a number >= 0 (a fraction or a count)"),
    "optimizer.lr": (lambda v: _number(v) and v > 0, "a positive number"),
    "optimizer.weight_decay": (lambda v: _number(v) and v >= 0, "a number >= 0"),
    "optimizer.momentum": (lambda v: _number(v) and v >= 0, "a number >= 0"),
    "optimizer.eps": (lambda v: _number(v) and v > 0, "a positive number"),
    "data.batch_size": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "data.train_size": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "data.val_size": (lambda v: _int(v) and v >= 0, "an integer >= 0"),
    "data.test_size": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "data.window": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "data.max_steps": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "seed": (lambda v: _int(v), "an integer"),
    "threads": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
    "divergence.max_scale_ratio": (lambda v: _number(v) and v > 1, "a number > 1"),
    "divergence.max_loss_ratio": (lambda v: _number(v) and v > 1, "a number > 1"),
    "divergence.max_skipped_steps": (lambda v: _int(v) and v >= 1, "an integer >= 1"),
}


def check_config(cfg: DictConfig) -> None:
    """Raise ``ValueError`` naming the first key of :data:`CHECKS` whose value in ``cfg`` is of
    the wrong type or out of range (e.g. ``trainer.max_epochs='two'``)."""
    for key, (ok, expected) in CHECKS.items():
        try:
            value = OmegaConf.select(cfg, key, throw_on_missing=False)
        except Exception:  # noqa: BLE001 - an interpolation that cannot resolve is reported where it is used
            continue
        if value is None:
            continue
        if not ok(value):
            raise ValueError(f"config key {key} must be {expected}, got {value!r} ({type(value).__name__})")
