"""Checkpoints of a :class:`~difffilter.learn.learner.FilterLearner`: what they hold beyond the
weights, and loading them back.

A learner's checkpoint (Lightning's ``.ckpt``) holds, next to the parameters, optimizer,
scheduler and loop states that Lightning writes:

* ``hyper_parameters``: the learner's arguments, among them ``filter_config`` (how to rebuild the
  filter's structure, :func:`~experiments.runner.experiment.rebuild_filter`) and ``loss`` (a
  name or a Hydra config), so that ``FilterLearner.load_from_checkpoint(path)`` works without
  any argument;
* ``difffilter``: the resolved experiment config of the run (``run_config``; what
  ``experiments/eval.py`` evaluates under), the truncated-BPTT belief carried between the
  windows of the batch in progress, the stability counters and the random number generator
  states (torch, numpy, Python) at the time of saving: what a resumed run needs to continue
  bit for bit where the interrupted one stopped.

``FilterLearner.load_from_checkpoint(path)`` or :func:`~difffilter.learn.learner.load_filter`
(the learned filter alone) load a checkpoint back.

Every entry is a tensor or a plain Python container, so checkpoints load with
``torch.load(..., weights_only=True)`` (:func:`read_checkpoint`): loading never executes code
from the file.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "CHECKPOINT_KEY",
    "best_checkpoint",
    "get_rng_state",
    "learner_state",
    "read_checkpoint",
    "restore_learner_state",
    "run_config",
    "set_rng_state",
]

#: Key of the learner's own entries in a checkpoint.
CHECKPOINT_KEY = "difffilter"


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint file's content, loaded on the CPU with ``weights_only=True``."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no checkpoint file {p}")
    return torch.load(p, map_location="cpu", weights_only=True)


def best_checkpoint(run_dir: str | Path) -> Path:
    """The best validation checkpoint of a run directory (``checkpoints/*.ckpt`` other than
    ``last*.ckpt``; with several, the one the newest names as best)."""
    folder = Path(run_dir) / "checkpoints"
    kept = sorted((p for p in folder.glob("*.ckpt") if not p.name.startswith("last")), key=lambda p: p.stat().st_mtime)
    if not kept:
        raise FileNotFoundError(f"no checkpoint other than last.ckpt under {folder}")
    if len(kept) == 1:
        return kept[0]
    for state in read_checkpoint(kept[-1]).get("callbacks", {}).values():
        best = Path(str(state.get("best_model_path") or "")) if isinstance(state, Mapping) else None
        if best is not None and (folder / best.name) in kept:
            return folder / best.name
    return kept[-1]


def run_config(path_or_checkpoint: str | Path | Mapping[str, Any]) -> dict[str, Any] | None:
    """The resolved experiment config stored in a learner checkpoint (``None`` when the learner
    was not built by :func:`~experiments.runner.experiment.run_experiment`)."""
    ckpt = path_or_checkpoint if isinstance(path_or_checkpoint, Mapping) else read_checkpoint(path_or_checkpoint)
    return (ckpt.get(CHECKPOINT_KEY) or {}).get("run_config")


def get_rng_state() -> dict[str, Any]:
    """The global torch, numpy and Python generator states as tensors and plain containers."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": [str(name), torch.from_numpy(np.asarray(keys, dtype=np.int64)), int(pos), int(has_gauss), float(cached)],
        "python": random.getstate(),
    }


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore what :func:`get_rng_state` returned."""
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    keys_np = keys.numpy().astype(np.uint32) if isinstance(keys, Tensor) else np.asarray(keys, dtype=np.uint32)
    np.random.set_state((name, keys_np, pos, has_gauss, cached))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))


def learner_state(learner: Any) -> dict[str, Any]:
    """A learner's entries of a checkpoint (the ``difffilter`` key): run config, the belief carried
    between the windows of the batch in progress, stability counters, generator states."""
    return {
        "run_config": learner.run_config,
        "carry": {"index": learner._carry_index, "beliefs": dict(learner._carries)},
        "counters": {"skipped_steps": learner.skipped_steps, "nonfinite_trajectories": learner.nonfinite_trajectories},
        "rng": get_rng_state(),
    }


def restore_learner_state(learner: Any, stored: Mapping[str, Any] | None) -> None:
    """Put :func:`learner_state`'s entries back; the generator states are applied when training
    starts (``learner._restored_rng``), the carried belief by the next training batch."""
    if not stored:
        return
    learner.run_config = stored.get("run_config")
    carry = stored.get("carry") or {}
    learner._carry_index, learner._carries = carry.get("index"), dict(carry.get("beliefs") or {})
    learner._restored_carry = learner._carry_index is not None
    counters = stored.get("counters") or {}
    learner.skipped_steps = int(counters.get("skipped_steps", 0))
    learner.nonfinite_trajectories = int(counters.get("nonfinite_trajectories", 0))
    learner._restored_rng = stored.get("rng")
