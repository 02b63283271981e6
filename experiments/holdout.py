"""Learning on real recordings with a held-out validation block: contiguous blocks, bounded
parameters that decay towards their starting values, checkpoint selection on validation across
seeds and epochs, and paired block-bootstrap comparisons on a test block.

Real data usually means a few long recordings, not many independent runs.  The protocol these
helpers implement (``experiments.papers.smartloc.protocol`` is its user):

* each recording is cut into **contiguous blocks** (:func:`contiguous_blocks`), e.g. train
  ``[0, 0.4)``, validation ``[0.4, 0.6)``, test ``[0.6, 1)`` of its epochs; train and test never
  share an epoch and the validation block is neither;
* the learned parameters are **bounded** around their starting (hand-tuned) values on a log scale
  (:func:`bound_parameters`) and pulled back towards them by a prior (:class:`LogDistancePrior`,
  "weight decay towards the hand-tuned values");
* every training replicate (seed) records a **validation score** and a snapshot of the learned
  parameters before training and after every epoch (:class:`EpochSnapshots`); the model used on
  the test block is the (seed, epoch) with the best validation score (:func:`select_candidate`),
  optionally within a horizon of epochs, so that training longer can only change the choice when
  the validation block prefers the later model;
* the test block's per-epoch errors of two filters are compared with a paired circular
  moving-block bootstrap (:func:`paired_error_table`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
import torch
from torch import Tensor, nn

from difffilter.evaluate.intervals import block_bootstrap_difference
from difffilter.params import Interval, register_constrained
from difffilter.selection import match_parameters, parameter_owners

__all__ = [
    "EpochSnapshots",
    "clone_with_snapshot",
    "LogDistancePrior",
    "bound_parameters",
    "contiguous_blocks",
    "error_statistics",
    "paired_error_table",
    "restore_snapshot",
    "select_candidate",
]


def contiguous_blocks(num_steps: int, spans: Mapping[str, tuple[float, float]]) -> dict[str, tuple[int, int]]:
    """Step ranges ``{name: (first, stop)}`` of contiguous blocks given as fractions ``[a, b)`` of a
    recording of ``num_steps`` steps (rounded to the nearest step); blocks must not overlap.

    Raises:
        ValueError: a span outside ``[0, 1]``, empty after rounding, or overlapping another.
    """
    out: dict[str, tuple[int, int]] = {}
    for name, span in spans.items():
        a, b = (float(v) for v in span)
        if not 0.0 <= a < b <= 1.0:
            raise ValueError(f"block {name!r} must be a span 0 <= a < b <= 1 of the recording, got {list(span)}")
        first, stop = int(round(a * num_steps)), int(round(b * num_steps))
        if stop <= first:
            raise ValueError(f"block {name!r} {list(span)} holds no step of a {num_steps}-step recording")
        out[name] = (first, stop)
    spans_sorted = sorted(out.items(), key=lambda kv: kv[1])
    for (n1, (_, s1)), (n2, (f2, _)) in zip(spans_sorted, spans_sorted[1:], strict=False):
        if f2 < s1:
            raise ValueError(f"blocks {n1!r} and {n2!r} overlap: {out[n1]} and {out[n2]}")
    return out


class LogDistancePrior:
    """``log p(v) = -sum ((log v - log v_ref) / scale)^2 / 2``: a Gaussian pull of a positive
    parameter towards ``reference`` on a log scale (no Jacobian term, so the maximum is exactly
    at the reference).  For :class:`~difffilter.learn.learner.FilterLearner`'s ``prior`` (:class:`~difffilter.learn.losses.LogPrior`)."""

    def __init__(self, *, reference: Tensor | float, scale: float = 1.0) -> None:
        if not float(scale) > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        ref = torch.as_tensor(reference, dtype=torch.float64).detach().clone()
        if not bool((ref > 0).all()):
            raise ValueError(f"reference must be positive, got {ref.tolist()}")
        self.reference, self.scale = ref, float(scale)

    def log_prob(self, value: Tensor) -> Tensor:
        ref = self.reference.to(value.dtype)
        return -0.5 * (((torch.log(value) - torch.log(ref)) / self.scale) ** 2).sum()


def bound_parameters(module: nn.Module, names: Sequence[str], *, ratio: float) -> dict[str, tuple[float, float]]:
    """Re-register the positive parameters ``names`` of ``module`` as log-scale
    :class:`~difffilter.params.Interval` s ``[v_min / ratio, v_max * ratio]`` around their current
    values ``v`` (same values, now bounded; Adam's steps on the raw value are then relative
    changes).  Parameters already bounded by an ``Interval`` and non-positive ones are skipped.

    Returns ``{dotted name: (lower, upper)}`` of the parameters re-registered.
    """
    if not float(ratio) > 1.0:
        raise ValueError(f"ratio must exceed 1, got {ratio}")
    owners = parameter_owners(module)
    out: dict[str, tuple[float, float]] = {}
    for hits in match_parameters(module, names).values():
        for name in hits:
            mod, attr, _ = owners[name]
            chain = getattr(getattr(mod, "parametrizations", None), attr, None)
            if chain is not None and any(isinstance(c, Interval) for c in chain):
                continue
            value = getattr(mod, attr).detach().clone()
            if not bool((value > 0).all()) or value.ndim > 1:
                continue
            lo, hi = float(value.min()) / float(ratio), float(value.max()) * float(ratio)
            register_constrained(mod, attr, value, Interval(lo, hi))
            out[name] = (lo, hi)
    return out


def _snapshot(module: nn.Module, names: Sequence[str]) -> dict[str, Tensor]:
    owners = parameter_owners(module)
    return {n: torch.cat([r.detach().reshape(-1) for r in owners[n][2]]).clone() for n in names}


def restore_snapshot(module: nn.Module, snapshot: Mapping[str, Tensor]) -> None:
    """Write a snapshot of :class:`EpochSnapshots` (raw values by dotted name) back into ``module``."""
    owners = parameter_owners(module)
    with torch.no_grad():
        for name, flat in snapshot.items():
            raws = owners[name][2]
            offset = 0
            for raw in raws:
                raw.copy_(flat[offset : offset + raw.numel()].reshape(raw.shape).to(raw.dtype))
                offset += raw.numel()


class EpochSnapshots(pl.Callback):
    """Record ``score(filter)`` (lower is better; e.g. the validation block's error) and a
    snapshot of the learned raw parameters before training (epoch 0) and after every training
    epoch ``e`` (epoch ``e``).

    Attributes:
        scores: ``[E + 1]`` validation scores, one per epoch.
        snapshots: the matching raw parameters ``{dotted name: flat tensor}``.
        extras: whatever ``score`` returned besides the score (a dict per epoch, e.g. median, RMS).
    """

    def __init__(self, score: Callable[[nn.Module], float | tuple[float, Mapping[str, float]]], names: Sequence[str]) -> None:
        super().__init__()
        self.score_fn, self.names = score, list(names)
        self.scores: list[float] = []
        self.snapshots: list[dict[str, Tensor]] = []
        self.extras: list[dict[str, float]] = []

    def record(self, filt: nn.Module) -> dict[str, float]:
        """Score ``filt`` (in eval mode, without gradients) and store score and snapshot."""
        was = filt.training
        filt.eval()
        with torch.no_grad():
            out = self.score_fn(filt)
        filt.train(was)
        score, extra = (out, {}) if not isinstance(out, tuple) else (out[0], dict(out[1]))
        score = float(score) if math.isfinite(float(score)) else math.inf
        self.scores.append(score)
        self.extras.append({k: float(v) for k, v in extra.items()})
        self.snapshots.append(_snapshot(filt, self.names))
        return {"score": score, **self.extras[-1]}

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self.scores:
            self.record(pl_module.filter)  # type: ignore[attr-defined]

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        logged = self.record(pl_module.filter)  # type: ignore[attr-defined]
        pl_module.log_dict({f"val/{k}": v for k, v in logged.items()}, on_step=False, on_epoch=True, batch_size=1)


def select_candidate(scores: Sequence[Sequence[float]], horizon: int | None = None) -> tuple[int, int]:
    """``(replicate, epoch)`` with the lowest score among epochs ``<= horizon`` (all: ``None``) of
    every replicate's score list; ties go to the earlier epoch, then the earlier replicate, so a
    model that validation cannot tell from its start is not replaced."""
    best: tuple[float, int, int] | None = None
    for r, row in enumerate(scores):
        stop = len(row) if horizon is None else min(len(row), int(horizon) + 1)
        for e in range(stop):
            key = (float(row[e]), e, r)
            if math.isfinite(key[0]) and (best is None or key < best):
                best = key
    if best is None:
        raise ValueError("no finite validation score to select from")
    return best[2], best[1]


def error_statistics(errors: Tensor) -> dict[str, float]:
    """Median, RMS and 95th percentile of per-step errors ``[T]``."""
    e = errors.detach().to(torch.float64).reshape(-1)
    return {"median": float(e.median()), "rms": float(e.pow(2).mean().sqrt()), "p95": float(torch.quantile(e, 0.95))}


def paired_error_table(
    errors: Mapping[str, Tensor], reference: str, *, block: int, draws: int = 4000, seed: int = 0, prob: float = 0.95
) -> list[dict[str, Any]]:
    """One row per filter: median / RMS / p95 of its per-step errors ``[T]`` and, for every filter
    but ``reference``, the differences filter - reference of the median and the RMS with paired
    circular moving-block bootstrap intervals (:func:`~difffilter.evaluate.intervals.block_bootstrap_difference`,
    blocks of ``block`` steps, the same resamples for every filter)."""
    if reference not in errors:
        raise ValueError(f"reference {reference!r} is not among the filters {list(errors)}")
    ref = errors[reference].detach().to(torch.float64).reshape(-1)
    rows = []
    for name, err in errors.items():
        e = err.detach().to(torch.float64).reshape(-1)
        row: dict[str, Any] = {"filter": name, **error_statistics(e)}
        if name != reference:
            for stat in ("median", "rms"):
                iv = block_bootstrap_difference(e, ref, statistic=stat, block=block, draws=draws, seed=seed, prob=prob)
                row[f"d_{stat}"], row[f"d_{stat}_lo"], row[f"d_{stat}_hi"] = iv.estimate, iv.lo, iv.hi
        rows.append(row)
    return rows


def clone_with_snapshot(module: nn.Module, snapshot: Mapping[str, Tensor]) -> nn.Module:
    """A deep copy of ``module`` with a snapshot's raw values written in."""
    twin = copy.deepcopy(module)
    restore_snapshot(twin, snapshot)
    return twin
