"""Paired comparison of smartLoc runs' learned filters with the hand-tuned one, with block-bootstrap
intervals: is a difference on one held-out segment of one real drive more than noise?  (What
``experiments/smartloc_paired.py`` prints.)

For a run directory (an ``experiment=smartloc_real`` run: ``.hydra/config.yaml`` and the best
checkpoint under ``checkpoints/``) :func:`compare` rebuilds the run's test segment and filter,
evaluates the hand-tuned values and the checkpoint's learned values on it, and returns the
horizontal median and RMS error of both, their differences (learned - hand-tuned) and a 95 %
interval for each difference from a paired circular moving-block bootstrap over epochs
(:func:`block_bootstrap`; blocks of 10 s by default: the errors of a filter are strongly
correlated in time, so resampling single epochs would make the interval far too narrow).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from difffilter.evaluate.intervals import block_bootstrap_difference
from difffilter.learn.checkpoints import best_checkpoint
from difffilter.learn.learner import load_filter
from difffilter.selection import assign_parameters

__all__ = ["block_bootstrap", "compare", "markdown_row", "MARKDOWN_HEADER"]

MARKDOWN_HEADER = (
    "| run | epochs | median hand / learned (m) | learned - hand, 95 % CI | RMS hand / learned (m) | learned - hand, 95 % CI |\n"
    "|---|---|---|---|---|---|"
)


def _errors(filt: torch.nn.Module, data: Any) -> torch.Tensor:
    with torch.no_grad():
        res = filt(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask, controls=data.controls)
    return (res.mean[..., :2] - data.truth[..., :2]).norm(dim=-1).reshape(-1)


def block_bootstrap(a: torch.Tensor, b: torch.Tensor, *, block: int, draws: int, seed: int = 0) -> dict[str, tuple[float, float]]:
    """95 % intervals of ``median(a) - median(b)`` and ``rms(a) - rms(b)`` for paired series
    ``a``, ``b`` ``[T]`` by a circular moving-block bootstrap (the same resampled epochs for both:
    :func:`difffilter.evaluate.intervals.block_bootstrap_difference`)."""
    out = {}
    for stat in ("median", "rms"):
        iv = block_bootstrap_difference(a, b, statistic=stat, block=block, draws=draws, seed=seed)
        out[stat] = (iv.lo, iv.hi)
    return out


def compare(run_dir: str | Path, *, block: int = 50, draws: int = 4000) -> dict[str, Any]:
    """Hand-tuned vs learned horizontal errors of one run with bootstrap intervals (module docstring)."""
    run_dir = Path(run_dir)
    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    simulator = instantiate(cfg.scenario)
    data = simulator(batch_size=int(cfg.data.test_size), seed=int(cfg.data.seeds.test), dtype=str(cfg.dtype))
    hand = instantiate(cfg.filter)
    assign_parameters(hand, OmegaConf.to_container(cfg.experiment.hand_tuned, resolve=True))
    learned = copy.deepcopy(hand)
    softness = cfg.learner.get("gate_softness")
    if softness is not None:
        learned.model.measurement.set_gate_softness(float(softness))
    ckpt = best_checkpoint(run_dir)
    learned = load_filter(str(ckpt), filter=learned)
    eh, el = _errors(hand, data), _errors(learned, data)
    ci = block_bootstrap(el, eh, block=block, draws=draws)
    rms = lambda e: float(e.pow(2).mean().sqrt())  # noqa: E731
    return {
        "hand_median": float(eh.median()),
        "learned_median": float(el.median()),
        "d_median": float(el.median() - eh.median()),
        "d_median_lo": ci["median"][0],
        "d_median_hi": ci["median"][1],
        "hand_rms": rms(eh),
        "learned_rms": rms(el),
        "d_rms": rms(el) - rms(eh),
        "d_rms_lo": ci["rms"][0],
        "d_rms_hi": ci["rms"][1],
        "epochs": float(eh.numel()),
        "checkpoint": ckpt.name,
    }


def markdown_row(name: str, r: dict[str, Any]) -> str:
    """One table row (columns of :data:`MARKDOWN_HEADER`) from :func:`compare`'s result."""
    return (
        f"| {name} ({r['checkpoint']}) | {int(r['epochs'])} | {r['hand_median']:.2f} / {r['learned_median']:.2f} | "
        f"{r['d_median']:+.2f} [{r['d_median_lo']:+.2f}, {r['d_median_hi']:+.2f}] | {r['hand_rms']:.2f} / {r['learned_rms']:.2f} | "
        f"{r['d_rms']:+.2f} [{r['d_rms_lo']:+.2f}, {r['d_rms_hi']:+.2f}] |"
    )
