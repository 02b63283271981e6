"""Trajectory data for learning: simulated train/val/test sets and truncated-BPTT windows.

A *simulator* is any callable ``simulator(batch_size=..., seed=..., dtype=...)`` returning a
:class:`~difffilter.sim.TrajectorySet` (or any object with its fields): ``truth [B, T, n_t]``,
``measurements [B, T, m]``, ``mask`` (``[B, T]``,
``[B, T, m]`` or ``None``) and ``controls`` (tensor or dict of ``[B, T, ...]``, or ``None``), and
optionally ``initial_mean [B, n]|[n]`` / ``initial_cov [n, n]|[B, n, n]`` (the belief before the
first measurement), ``true_params`` and ``make_model()`` (for oracles).  Every difffilter
simulator follows this (``difffilter.sim.ModelSimulator``, the papers' simulators).

Batches are plain dicts (which Lightning moves between devices as they are)::

    {"measurements": [B, W, m], "mask": [B, W(, m)] | None, "controls": ... | None,
     "truth": [B, W, n_t] | None, "initial_mean": [B, n] | None, "initial_cov": [B, n, n] | None,
     "index": [B] trajectory ids, "window_index": k, "num_windows": K, "start": k * W,
     "modes": [B, W] true mode indices | None}

Training yields, for each batch of trajectories, its windows in time order (``window_index``
``0..K-1``) so that the learner can carry the belief from one window to the next
(truncated back-propagation through time); validation and test yield whole trajectories.
Under DDP every process draws the same sets (same seeds) and takes its own shard.
"""

from __future__ import annotations

import inspect
import math
import warnings
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import pytorch_lightning as pl
import torch
from torch import Tensor

from .._util import as_dtype
from ..sim.trajectories import TrajectorySet

__all__ = ["EpochOrder", "TrajectoryDataModule", "TrajectorySet", "WindowedTrajectories"]


def __getattr__(name: str) -> Any:
    # SimulatedTrajectories was a second container with TrajectorySet's fields; it is TrajectorySet now
    if name == "SimulatedTrajectories":
        warnings.warn(
            "difffilter.learn.data.SimulatedTrajectories is deprecated: subclass difffilter.sim.TrajectorySet",
            DeprecationWarning,
            stacklevel=2,
        )
        return TrajectorySet
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


Batch = dict[str, Any]


def _accepts(fn: Callable[..., Any], name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


class EpochOrder:
    """The order in which one epoch visits the trajectories: a permutation drawn from
    ``seed + epoch`` when ``shuffle``, else the identity.  Lightning calls :meth:`set_epoch` at the
    start of every training epoch (as for a ``DistributedSampler``); a standalone user calls it too."""

    def __init__(self, *, seed: int = 0, shuffle: bool = False) -> None:
        self.seed, self.shuffle, self.epoch = int(seed), bool(shuffle), 0

    def set_epoch(self, epoch: int) -> None:
        """Use the order of epoch ``epoch`` from the next pass on."""
        self.epoch = int(epoch)

    def order(self, n: int, epoch: int) -> Tensor:
        """Trajectory ids ``[n]`` in the order of epoch ``epoch``."""
        if not self.shuffle:
            return torch.arange(n)
        return torch.randperm(n, generator=torch.Generator().manual_seed(self.seed + epoch))


class WindowedTrajectories:
    """Batches of ``batch_size`` trajectories, each cut into consecutive windows of ``window``
    steps (``None``: whole trajectories), in time order: an iterable with a length, used directly
    as a Lightning data loader (the batches are ready-made, so there is nothing to collate and no
    worker to start).

    The trajectory order of a pass is ``sampler.order`` of the current epoch (``sampler.set_epoch``;
    reshuffled per epoch when ``shuffle``).  ``rank`` and ``world_size`` select this process's
    shard; with ``equal_shards`` every shard has the same number of trajectories (the remainder is
    dropped) so that DDP processes step in lock-step.

    Resumable: :meth:`state_dict` records the seed, the epoch and how many batches of it are done
    (``progress()``, given by the data module from the trainer's loop), and after
    :meth:`load_state_dict` the next pass continues the interrupted epoch where it stopped, so a
    resumed run sees exactly the batches of an uninterrupted one.  Lightning saves and restores
    this state in its checkpoints.
    """

    def __init__(
        self,
        data: TrajectorySet,
        *,
        batch_size: int,
        window: int | None = None,
        shuffle: bool = False,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        equal_shards: bool = False,
        progress: Callable[[], tuple[int, float]] | None = None,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if window is not None and window < 1:
            raise ValueError(f"window must be >= 1 or None, got {window}")
        self.data, self.batch_size, self.window = data, int(batch_size), window
        self.rank, self.world_size = int(rank), int(world_size)
        self.equal_shards = equal_shards
        self.sampler = EpochOrder(seed=seed, shuffle=shuffle)
        # what a DataLoader(batch_size=None) has: Lightning looks for both next to each other
        self.batch_sampler = None
        self.progress = progress
        self._pass_epoch = 0
        self._skip = 0
        if self._shard_size() == 0:
            raise ValueError(f"{len(data)} trajectories cannot be shared by {world_size} processes")

    @property
    def seed(self) -> int:
        return self.sampler.seed

    @property
    def shuffle(self) -> bool:
        return self.sampler.shuffle

    def _shard_size(self) -> int:
        n = len(self.data)
        if self.equal_shards:
            return n // self.world_size
        return len(range(self.rank, n, self.world_size))

    @property
    def num_windows(self) -> int:
        steps = self.data.num_steps
        return 1 if self.window is None else math.ceil(steps / self.window)

    def __len__(self) -> int:
        return math.ceil(self._shard_size() / self.batch_size) * self.num_windows

    def set_epoch(self, epoch: int) -> None:
        """Shorthand for ``sampler.set_epoch``."""
        self.sampler.set_epoch(epoch)

    def state_dict(self) -> dict[str, int]:
        """``{"seed", "epoch", "position"}``: the epoch being iterated and its batches done; an
        epoch whose batches are all done is recorded as the next epoch at position 0."""
        done, total = self.progress() if self.progress is not None else (0, math.inf)
        epoch, done = (self._pass_epoch + 1, 0) if done >= min(total, len(self)) else (self._pass_epoch, int(done))
        return {"seed": self.seed, "epoch": int(epoch), "position": int(done)}

    def load_state_dict(self, state: Mapping[str, int]) -> None:
        """Continue from ``state`` (:meth:`state_dict`) at the next pass."""
        if int(state["seed"]) != self.seed:
            raise ValueError(f"the checkpoint's data order seed is {state['seed']}, this data module's is {self.seed}: the runs differ")
        self.sampler.set_epoch(int(state["epoch"]))
        self._skip = int(state["position"])

    def __iter__(self) -> Iterator[Batch]:
        n = len(self.data)
        self._pass_epoch = epoch = self.sampler.epoch
        order = self.sampler.order(n, epoch)
        skip, self._skip = self._skip, 0
        shard = order[self.rank :: self.world_size][: self._shard_size()]
        steps, k = self.data.num_steps, self.num_windows
        width = steps if self.window is None else self.window
        position = 0
        for first in range(0, len(shard), self.batch_size):
            index = shard[first : first + self.batch_size]
            for w in range(k):
                position += 1
                if position <= skip:
                    continue
                start = w * width
                out = self.data.batch(index, start, min(start + width, steps))
                out.update(window_index=w, num_windows=k, start=start)
                yield out


class TrajectoryDataModule(pl.LightningDataModule):
    """Train/val/test trajectory sets drawn from a simulator with different seeds.

    Args:
        simulator: ``(batch_size=, seed=, dtype=) -> data`` (see the module docstring).
        train_size, val_size, test_size: trajectories per set.
        batch_size: trajectories per training batch; ``eval_batch_size`` for val/test
            (default: the whole shard in one batch).
        window: truncated-BPTT window length ``W`` (``None``: full back-propagation).
        seeds: ``{"train": 0, "val": 1, "test": 2}``; the sets are disjoint draws.
        dtype: dtype of every floating tensor (``"float64"``/``"float32"``).
        shuffle: reshuffle training trajectories every epoch.
        max_steps: keep only the first ``max_steps`` steps (smoke runs of long scenarios); also
            passed to the simulator as ``num_steps`` when it takes that argument.
        test_simulator: optional different simulator for the test set (out-of-distribution).
    """

    def __init__(
        self,
        simulator: Callable[..., Any],
        *,
        train_size: int = 64,
        val_size: int = 32,
        test_size: int = 64,
        batch_size: int = 32,
        eval_batch_size: int | None = None,
        window: int | None = None,
        seeds: Mapping[str, int] | None = None,
        dtype: torch.dtype | str = torch.float64,
        shuffle: bool = True,
        max_steps: int | None = None,
        test_simulator: Callable[..., Any] | None = None,
    ) -> None:
        super().__init__()
        self.simulator = simulator
        self.test_simulator = test_simulator
        self.sizes = {"train": int(train_size), "val": int(val_size), "test": int(test_size)}
        self.batch_size = int(batch_size)
        self.eval_batch_size = eval_batch_size
        self.window = None if window is None else int(window)
        self.seeds = {"train": 0, "val": 1, "test": 2, **{k: int(v) for k, v in dict(seeds or {}).items()}}
        if len(set(self.seeds[k] for k in ("train", "val", "test"))) < 3:
            warnings.warn(f"train/val/test seeds are not distinct ({self.seeds}): the sets overlap", stacklevel=2)
        self.dtype = as_dtype(dtype)
        self.shuffle = shuffle
        self.max_steps = max_steps
        self._sets: dict[str, TrajectorySet] = {}

    def dataset(self, split: str) -> TrajectorySet:
        """The ``"train"``, ``"val"`` or ``"test"`` set (simulated on first use, then cached)."""
        if split not in self.sizes:
            raise ValueError(f"split must be 'train', 'val' or 'test', got {split!r}")
        if split not in self._sets:
            sim = self.test_simulator if split == "test" and self.test_simulator is not None else self.simulator
            self._sets[split] = self.simulate(sim, split)
        return self._sets[split]

    def simulate(self, simulator: Callable[..., Any], split: str = "test") -> TrajectorySet:
        """A set drawn from ``simulator`` with the size, seed, dtype and ``max_steps`` of
        ``split`` (not cached): e.g. a second test family on the test runs' seed."""
        if split not in self.sizes:
            raise ValueError(f"split must be 'train', 'val' or 'test', got {split!r}")
        kwargs: dict[str, Any] = {"batch_size": self.sizes[split], "seed": self.seeds[split], "dtype": self.dtype}
        if self.max_steps is not None and _accepts(simulator, "num_steps"):
            kwargs["num_steps"] = int(self.max_steps)
        return TrajectorySet.from_simulation(simulator(**kwargs), self.dtype, self.max_steps)

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",)}.get(stage or "", ("train", "val", "test"))
        for split in splits:
            self.dataset(split)

    def _rank_world(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0, 1
        return int(trainer.global_rank), int(trainer.world_size)

    def _train_progress(self) -> tuple[int, float]:
        """Training batches done in the current epoch and the epoch's length, as the trainer's
        loop counts them (what a checkpoint taken now resumes from)."""
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0, math.inf
        done = trainer.fit_loop.epoch_loop.batch_progress.current.processed
        return int(done), float(trainer.num_training_batches)

    def _loader(self, split: str) -> WindowedTrajectories:
        rank, world = self._rank_world()
        data = self.dataset(split)
        train = split == "train"
        shard = len(range(rank, len(data), world))
        return WindowedTrajectories(
            data,
            batch_size=self.batch_size if train else (self.eval_batch_size or max(shard, 1)),
            window=self.window if train else None,
            shuffle=train and self.shuffle,
            seed=self.seeds[split],
            rank=rank,
            world_size=world,
            equal_shards=train,
            progress=self._train_progress if train else None,
        )

    def state_dict(self) -> dict[str, Any]:
        """The seeds and sizes of the sets (checked when a run resumes from a checkpoint)."""
        return {"seeds": dict(self.seeds), "sizes": dict(self.sizes), "max_steps": self.max_steps}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Refuse to resume on other data than the checkpoint's."""
        mine = self.state_dict()
        differ = [k for k in mine if k in state_dict and state_dict[k] != mine[k]]
        if differ:
            raise ValueError(
                f"the checkpoint was trained on other data ({', '.join(f'{k}={state_dict[k]}' for k in differ)}; "
                f"this run: {', '.join(f'{k}={mine[k]}' for k in differ)})"
            )

    def train_dataloader(self) -> WindowedTrajectories:
        return self._loader("train")

    def val_dataloader(self) -> WindowedTrajectories:
        return self._loader("val")

    def test_dataloader(self) -> WindowedTrajectories:
        return self._loader("test")
