"""Glue between the real smartLoc drive and the learning stack (``experiment=smartloc_real``).

The drive is one real trajectory (1,372 epochs, 283 s; :mod:`experiments.papers.smartloc.data`), so the
"simulator" of the data module is an adapter that cuts it into segments:
:func:`smartloc_simulator` returns, for the split that the data module asks for (recognised by
its seed, ``split_seeds``), the windows of that split's segment, e.g. training windows of 200
epochs every 50 epochs inside the first 60 % of the drive, and the last 40 % as one continuous
test trajectory.  Each window starts from :func:`~experiments.papers.smartloc.model.smartloc_initial_belief`
(snapshot fix of the epoch before it), so train and test never share an epoch when their
segments do not overlap.

Also here (the filters of the experiment are in :mod:`experiments.papers.smartloc.filters`):

* :func:`smartloc_synthetic_simulator` - synthetic drives on the geometry of one segment
  (:mod:`experiments.papers.smartloc.synthetic`, error model calibrated on that segment) for the
  training splits, the real held-out segment for the test split;
* :func:`smartloc_model` - :func:`~experiments.papers.smartloc.model.make_smartloc_model` for configs;
* :func:`smartloc_learner` - the learner, optionally with a smooth reject gate on the learned
  filter only (the hand-tuned row keeps the model's gate).

Data: CC BY-SA 4.0, TU Chemnitz smartLoc (Reisdorf et al., VEHICULAR 2016), see the data README.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from difffilter._util import as_dtype, generator
from difffilter.filters.protocol import Filter
from difffilter.learn.learner import FilterLearner
from difffilter.selection import assign_parameters
from difffilter.sim import TrajectorySet

from .data import SmartLocData, load_smartloc
from .model import make_smartloc_model, smartloc_initial_belief
from .synthetic import PseudorangeErrorModel, calibrate_error_model, simulate_smartloc_drives
from .wls import WlsSolution, single_epoch_wls

__all__ = ["SmartLocTrajectories", "smartloc_learner", "smartloc_model", "smartloc_simulator", "smartloc_synthetic_simulator"]


@functools.lru_cache(maxsize=4)
def _drive(path: str | None, slots: str) -> SmartLocData:
    return load_smartloc(path, slots=slots)


@functools.lru_cache(maxsize=2)
def _snapshot(path: str | None) -> WlsSolution:
    # The initial beliefs use the loader's robust snapshot fixes (Cauchy, c = 1.5: 23.4 m median).
    return single_epoch_wls(_drive(path, "epoch"), robust="cauchy", threshold=1.5)


def smartloc_model(*, path: str | None = None, slots: str = "satellite", dtype: torch.dtype | str = "float64", **options: Any) -> nn.Module:
    """:func:`~experiments.papers.smartloc.model.make_smartloc_model` on the (cached) drive; ``options``
    are its keywords (``robust``, ``gate``, ``gate_floor``, ``gate_gradient``, ``gate_softness``,
    ``noise_from_data``, dynamics PSDs)."""
    return make_smartloc_model(_drive(path, slots), dtype=as_dtype(dtype), **options)


def smartloc_learner(
    filter: Filter,  # noqa: A002 - the field's word
    loss: Any,
    *,
    gate_softness: float | None = None,
    start_params: Mapping[str, Any] | None = None,
    **learner_kwargs: Any,
) -> FilterLearner:
    """A :class:`~difffilter.learn.learner.FilterLearner` on ``filter`` (``run_experiment`` hands
    it a copy of the hand-tuned filter) with the pseudorange reject gate of the copy set to
    ``gate_softness`` and ``start_params`` (constrained values by name) applied.

    ``gate_softness=None`` keeps the model's gate (the learner is then exactly
    ``FilterLearner(filter, loss, ...)``); ``0``: the hard gate; ``t > 0``: the smooth gate
    ``R_jj x 1e6 ** sigmoid((n_j - gate) / t)`` in training, validation and the final evaluation
    of the learned filter, with ``t`` a parameter that ``learn: [..., gate_softness]`` may train.
    The hand-tuned row (and every baseline) keeps the model config's gate.
    """
    if gate_softness is not None:
        meas = getattr(getattr(filter, "model", None), "measurement", None)
        if meas is None or not hasattr(meas, "set_gate_softness"):
            raise TypeError(f"gate_softness needs a filter whose model.measurement has a reject gate, got {type(filter).__name__}")
        meas.set_gate_softness(gate_softness)
    if start_params:
        assign_parameters(filter, dict(start_params))
    return FilterLearner(filter, loss, **learner_kwargs)


@dataclass(kw_only=True)
class SmartLocTrajectories(TrajectorySet):
    """Windows of the real drive in the data module's layout.

    Attributes:
        truth: ``[B, T, 3]`` ENU reference (first reference point = origin).
        measurements: ``[B, T, K]`` reduced pseudoranges; ``mask [B, T, K]``.
        controls: ``sat_pos``, ``glonass``, ``pr_var``, ``pr_obs``, ``speed``, ``yaw_rate``, ``dt``.
        initial_mean, initial_cov: ``[B, 7]``, ``[B, 7, 7]`` (snapshot fix + reference yaw/height).
        start: ``[B]`` first epoch of each window.
        data: the loaded drive.
    """

    start: Tensor
    data: SmartLocData
    model_options: Mapping[str, Any] | None = None

    def make_model(self) -> nn.Module:
        """The loader's odometry + pseudorange model for this drive."""
        return make_smartloc_model(self.data, dtype=self.measurements.dtype, **dict(self.model_options or {}))


def _epoch(value: float, total: int) -> int:
    """A segment bound: a fraction of the drive (``0 <= value <= 1``) or an epoch index."""
    v = float(value)
    return int(round(v * total)) if 0.0 <= v <= 1.0 else int(v)


def _split_of(seed: int, split_seeds: Mapping[str, int] | None) -> str | None:
    """The split whose seed (``split_seeds``, default ``{train: 0, val: 1, test: 2}``) is ``seed``."""
    return {int(v): k for k, v in dict(split_seeds or {"train": 0, "val": 1, "test": 2}).items()}.get(int(seed))


def _segment(segments: Mapping[str, Mapping[str, Any]], name: str, total: int) -> tuple[int, int, int, dict[str, Any]]:
    """``(first, stop, length, spec)`` of segment ``name`` (bounds checked; ``length`` defaults to
    the whole segment)."""
    spec = dict(segments[name])
    first, stop = _epoch(spec.get("start", 0.0), total), _epoch(spec.get("stop", 1.0), total)
    if not 0 <= first < stop <= total:
        raise ValueError(f"segment {name!r} must satisfy 0 <= start < stop <= {total} epochs, got [{first}, {stop})")
    length = stop - first if spec.get("length") is None else int(spec["length"])
    return first, stop, length, spec


def smartloc_simulator(
    *,
    batch_size: int,
    seed: int,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    segments: Mapping[str, Mapping[str, Any]],
    split_seeds: Mapping[str, int] | None = None,
    elevation_mask_deg: float = 15.0,
    slots: str = "satellite",
    path: str | None = None,
) -> SmartLocTrajectories:
    """Windows of the real drive for the split whose seed is ``seed``.

    Args:
        batch_size: the largest number of windows to return (the first ones in time).
        seed: the data module's seed of the split; ``split_seeds`` (``${data.seeds}``, default
            ``{train: 0, val: 1, test: 2}``) names the split.
        num_steps: cut every window to its first ``num_steps`` epochs (smoke runs).
        segments: ``{split: {start, stop, length, stride}}``; ``start``/``stop`` bound the
            segment (fractions of the drive in ``[0, 1]`` or epoch indices), ``length`` and
            ``stride`` (epochs) cut it into windows (``length: null``: the whole segment as one
            trajectory).
        elevation_mask_deg: satellites below are masked out (the loader's 15 deg).
        slots: ``"satellite"`` (one slot per satellite: what coloured-noise models need) or
            ``"epoch"``.
        path: data folder (default: the loader's).
    """
    split = _split_of(seed, split_seeds)
    if split is None:
        raise ValueError(f"seed {seed} names no split of split_seeds {dict(split_seeds or {})}")
    if split not in segments:
        raise ValueError(f"no segment for split {split!r}; segments has {sorted(segments)}")
    data = _drive(path, slots)
    first, stop, length, spec = _segment(segments, split, data.num_epochs)
    stride = length if spec.get("stride") is None else int(spec["stride"])
    starts = list(range(first, stop - length + 1, stride))[: int(batch_size)]
    if not starts:
        raise ValueError(f"segment {split!r} [{first}, {stop}) holds no window of {length} epochs")
    steps = length if num_steps is None else min(length, int(num_steps))
    dt = as_dtype(dtype)
    full = data.batch(dt, elevation_mask_deg=elevation_mask_deg)

    def cut(t: Tensor) -> Tensor:
        return torch.cat([t[:, s : s + steps] for s in starts], 0)

    start = torch.tensor(starts, dtype=torch.long)
    mean0, cov0 = smartloc_initial_belief(data, start, wls=_snapshot(path), dtype=dt)
    return SmartLocTrajectories(
        truth=cut(full.truth),
        measurements=cut(full.measurements),
        mask=cut(full.mask),
        controls={k: cut(v) for k, v in full.controls.items()},
        initial_mean=mean0,
        initial_cov=cov0,
        start=start,
        data=data,
    )


@functools.lru_cache(maxsize=8)
def _calibrated(path: str | None, slots: str, first: int, stop: int, elevation_mask_deg: float) -> PseudorangeErrorModel:
    return calibrate_error_model(_drive(path, slots), first, stop, elevation_mask_deg=elevation_mask_deg)


def smartloc_synthetic_simulator(
    *,
    batch_size: int,
    seed: int,
    dtype: torch.dtype | str = torch.float64,
    num_steps: int | None = None,
    segments: Mapping[str, Mapping[str, Any]],
    synthetic: Sequence[str] = ("train", "val"),
    calibration: str = "train",
    error_model: Mapping[str, Any] | None = None,
    split_seeds: Mapping[str, int] | None = None,
    elevation_mask_deg: float = 15.0,
    slots: str = "satellite",
    path: str | None = None,
) -> SmartLocTrajectories:
    """Synthetic drives for the splits in ``synthetic``, the real drive for the others.

    A synthetic split's segment ``{start, stop, length}`` bounds the real epochs whose geometry
    (reference track, satellites, visibility, receiver variances, C/N0, odometry) is used:
    ``batch_size`` windows of ``length`` epochs start at epochs drawn uniformly in the segment
    (seeded by the split's seed), and their pseudoranges and clock are drawn from a
    :class:`~experiments.papers.smartloc.synthetic.PseudorangeErrorModel`.  That model is estimated
    by :func:`~experiments.papers.smartloc.synthetic.calibrate_error_model` on the real epochs of the
    segment named ``calibration`` (with the reference track), then overridden field by field by
    ``error_model``.  Initial beliefs: centred on a draw from ``N(truth, P0)`` with the real
    windows' ``P0``.  Other splits are :func:`smartloc_simulator`'s real windows.  The remaining
    arguments are :func:`smartloc_simulator`'s.
    """
    split = _split_of(seed, split_seeds)
    bad = sorted(set(synthetic) - set(segments))
    if bad:
        raise ValueError(f"synthetic names splits without a segment: {bad}; segments has {sorted(segments)}")
    if calibration not in segments:
        raise ValueError(f"calibration must name a segment, got {calibration!r}; segments has {sorted(segments)}")
    if split not in synthetic:
        return smartloc_simulator(
            batch_size=batch_size,
            seed=seed,
            dtype=dtype,
            num_steps=num_steps,
            segments=segments,
            split_seeds=split_seeds,
            elevation_mask_deg=elevation_mask_deg,
            slots=slots,
            path=path,
        )
    data = _drive(path, slots)
    total = data.num_epochs
    c0, c1, _, _ = _segment(segments, calibration, total)
    model = _calibrated(path, slots, c0, c1, float(elevation_mask_deg))
    if error_model:
        unknown = sorted(set(error_model) - set(PseudorangeErrorModel.__dataclass_fields__))
        if unknown:
            raise ValueError(f"error_model has unknown fields {unknown}; known: {sorted(PseudorangeErrorModel.__dataclass_fields__)}")
        model = dataclasses.replace(model, **dict(error_model))
    first, stop, length, _ = _segment(segments, split, total)
    if length < 2 or first + length > stop:
        raise ValueError(f"segment {split!r} [{first}, {stop}) holds no window of {length} >= 2 epochs")
    gen = generator(int(seed))
    starts = torch.randint(first, stop - length + 1, (int(batch_size),), generator=gen).tolist()
    steps = length if num_steps is None else min(length, int(num_steps))
    batch, mean0, cov0, _ = simulate_smartloc_drives(
        data, starts, steps, model, seed=int(seed) + 1, dtype=as_dtype(dtype), elevation_mask_deg=elevation_mask_deg
    )
    return SmartLocTrajectories(
        truth=batch.truth,
        measurements=batch.measurements,
        mask=batch.mask,
        controls=batch.controls,
        initial_mean=mean0,
        initial_cov=cov0,
        start=batch.start,
        data=data,
    )
