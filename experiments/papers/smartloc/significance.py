"""A learned model replaces the non-learned candidates only when validation says so significantly.

The protocol's selection (:func:`~experiments.papers.smartloc.protocol.select_with_fallbacks`)
adopts the learned (seed, epoch) whose validation score (horizontal median + RMS, m) is strictly
below the hand-tuned filter's and the untrained start's.  On one drive a few metres of validation
gain is inside the block's own noise, and such a choice can lose on test.  With
``selection.significance`` set, the chosen learned model must in addition beat *every* non-learned
candidate by a paired circular block bootstrap of the score on the validation epochs: the upper end
of the ``level`` interval of ``score(learned) - score(candidate)`` below zero.  Otherwise the best
non-learned candidate is used (the hand-tuned filter on a tie), so the protocol never ships a model
that validation cannot tell apart from its start.

The validation windows overlap (100 epochs every 25), so one epoch of the drive enters the score up
to four times.  The bootstrap therefore resamples the *drive's* validation epochs in circular blocks
and weights each window element by how often its epoch was drawn: the interval reflects the
distinct epochs the windows cover, not the window elements (on the smartLoc drive 250 epochs, 700
elements; resampling the elements as independent makes the interval narrower and the gate more
lenient).

Configuration (``conf/realdata/smartloc_v5.yaml``)::

    selection:
      significance: {level: 0.95, block: 50, draws: 4000, seed: 0}
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from difffilter.evaluate.intervals import circular_block_indices
from experiments.holdout import contiguous_blocks

from .protocol import Drive, horizontal_errors

__all__ = [
    "KEYS",
    "epoch_weights",
    "median_plus_rms",
    "significance_gate",
    "significance_options",
    "significantly_better",
    "validation_epochs",
]

#: the keys ``selection.significance`` accepts
KEYS = ("level", "block", "draws", "seed")


def median_plus_rms(x: Tensor, weights: Tensor | None = None) -> Tensor:
    """The selection score of error series: the lower median + RMS, per row of ``weights``.

    Args:
        x: errors ``[N]``.
        weights: ``[draws, N]`` non-negative multiplicities (a bootstrap draw's counts);
            ``None``: one row of ones (the plain score, ``torch.median`` + RMS).

    Returns:
        ``[draws]`` (``[1]`` without weights).
    """
    w = torch.ones(1, x.numel(), dtype=x.dtype) if weights is None else weights.to(x.dtype)
    order = torch.argsort(x)
    cum = torch.cumsum(w[:, order], dim=-1)
    total = cum[:, -1:]
    # the lower median: the smallest value whose cumulative weight reaches half the total (torch.median's choice)
    k = torch.searchsorted(cum, (total / 2).contiguous(), right=False).clamp(max=x.numel() - 1)
    med = x[order][k.squeeze(-1)]
    rms = ((w * x.pow(2)).sum(-1) / total.squeeze(-1)).sqrt()
    return med + rms


def epoch_weights(groups: Tensor, *, block: int, draws: int, seed: int) -> Tensor:
    """``[draws, N]`` multiplicities of ``N`` series elements whose drive epochs are ``groups``
    ``[N]``: the distinct epochs (sorted) are resampled by the circular moving-block bootstrap,
    and each element counts as often as its epoch was drawn."""
    epochs, inverse = torch.unique(groups, sorted=True, return_inverse=True)
    idx = circular_block_indices(
        epochs.numel(), block=min(block, epochs.numel()), draws=draws, generator=torch.Generator().manual_seed(seed)
    )
    counts = torch.zeros(draws, epochs.numel(), dtype=torch.float64).scatter_add_(1, idx, torch.ones_like(idx, dtype=torch.float64))
    return counts[:, inverse]


def significance_options(selection: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """``selection.significance`` checked and completed, or ``None`` when it is absent / null.

    Raises:
        ValueError: an unknown key, a level outside (0, 1), a block or draws below 1.
    """
    raw = dict(selection or {}).get("significance")
    if raw is None:
        return None
    opts = dict(raw)
    unknown = sorted(set(opts) - set(KEYS))
    if unknown:
        raise ValueError(f"selection.significance: unknown key(s) {unknown}; expected some of {list(KEYS)}")
    out = {"level": float(opts.get("level", 0.95)), "block": int(opts.get("block", 50)), "draws": int(opts.get("draws", 4000))}
    out["seed"] = int(opts.get("seed", 0))
    if not 0.0 < out["level"] < 1.0:
        raise ValueError(f"selection.significance.level must be in (0, 1), got {out['level']}")
    for key in ("block", "draws"):
        if out[key] < 1:
            raise ValueError(f"selection.significance.{key} must be a positive integer, got {out[key]}")
    return out


def significantly_better(
    candidate: Tensor, references: Mapping[str, Tensor], options: Mapping[str, Any], groups: Tensor | None = None
) -> tuple[bool, dict[str, tuple[float, float]]]:
    """Whether ``candidate``'s validation score is significantly below every reference's.

    Args:
        candidate: the learned model's horizontal errors on the validation epochs ``[T]``.
        references: name -> the non-learned candidates' errors on the same epochs ``[T]``.
        options: :func:`significance_options`'s result.
        groups: the drive epoch of each error ``[T]`` (:func:`validation_epochs`); ``None``: each
            error its own epoch (a plain circular block bootstrap of the series).

    Returns:
        ``(better, intervals)``: ``intervals[name] = (lo, hi)`` of ``score(candidate) -
        score(reference)``; ``better`` when every ``hi < 0`` (vacuously true without references).
        A non-finite candidate error is never better.
    """
    if not bool(torch.isfinite(candidate).all()):
        return False, {name: (float("nan"), float("nan")) for name in references}
    groups = torch.arange(candidate.numel()) if groups is None else groups
    if groups.shape != candidate.shape:
        raise ValueError(f"groups must give one epoch per error, got {tuple(groups.shape)} for {tuple(candidate.shape)}")
    w = epoch_weights(groups, block=int(options["block"]), draws=int(options["draws"]), seed=int(options["seed"]))
    tail = (1.0 - float(options["level"])) / 2.0
    cand = median_plus_rms(candidate.to(torch.float64), w)
    intervals = {}
    for name, ref in references.items():
        if ref.shape != candidate.shape or not bool(torch.isfinite(ref).all()):
            raise ValueError(f"references[{name!r}] must be finite errors of shape {tuple(candidate.shape)}")
        diff = cand - median_plus_rms(ref.to(torch.float64), w)
        lo, hi = torch.quantile(diff, torch.tensor([tail, 1.0 - tail], dtype=torch.float64))
        intervals[name] = (float(lo), float(hi))
    return all(hi < 0.0 for _, hi in intervals.values()), intervals


def validation_epochs(cfg: Mapping[str, Any], drives: Sequence[Drive], fold: str) -> Tensor:
    """The drive epoch ``[N]`` of each validation error in the order
    :func:`~experiments.papers.smartloc.protocol.horizontal_errors` returns them for
    ``fold_data(cfg, drives, fold)["val"]`` (windows of each drive's validation block, drives in
    order; epochs of drive ``i`` offset by the epochs of the drives before it)."""
    spans = {name: tuple(v) for name, v in dict(cfg["folds"][fold]).items()}
    vwin = dict(cfg.get("val_windows") or {"length": None, "stride": None})
    out, offset = [], 0
    for d in drives:
        first, stop = contiguous_blocks(d.data.num_epochs, spans)["val"]
        size = stop - first if vwin["length"] is None else int(vwin["length"])
        step = size if vwin["stride"] is None else int(vwin["stride"])
        out += [offset + s0 + torch.arange(size) for s0 in range(first, stop - size + 1, step)]
        offset += d.data.num_epochs
    return torch.cat(out)


def significance_gate(
    learned: Any,
    hand: Mapping[str, tuple[Any, float]],
    start: tuple[str, Any, float],
    val_sets: Any,
    options: Mapping[str, Any],
    groups: Tensor | None = None,
) -> tuple[str, dict[str, Any]]:
    """``("learned", intervals)`` when the learned filter's validation score is significantly below
    the hand-tuned filter's (if a candidate) and the untrained start's
    (:func:`significantly_better`), else the better of
    those two by score (the hand-tuned filter on a tie) with the intervals that failed."""
    # a candidate whose validation run is not finite is not a candidate (as in select_with_fallbacks)
    refs = {k: v for k, v in ({**hand, start[0]: (start[1], start[2])}).items() if math.isfinite(float(v[1]))}
    errors = {name: horizontal_errors(filt, val_sets) for name, (filt, _) in refs.items()}
    better, intervals = significantly_better(horizontal_errors(learned, val_sets), errors, options, groups)
    record = {"options": dict(options), "intervals": {k: list(v) for k, v in intervals.items()}, "passed": better}
    if better or not refs:
        return "learned", record
    low = min(score for _, score in refs.values())
    return next(name for name, (_, score) in refs.items() if score == low), record
