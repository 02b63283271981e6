"""p003's mode-switch statistics: switching delays per test run, their intervals over runs and
training seeds, and the per-step cost of IMM variants (what :mod:`experiments.papers.p003.paired`
tabulates next to the paper's numbers).

A *switch* is a step where the true mode (manoeuvre flag) differs from the previous step; its
*delay* is the number of steps until the matching IMM mode's probability exceeds ``threshold``
(0 = at the first step of the new mode), or undefined when that does not happen before the next
switch (:func:`~difffilter.evaluate.metrics.mode_switch_delay`).  p003 reports the first manoeuvre of
its profile (the 10-20 s acceleration): low -> high dominance after 5 steps (simplified-UKF IMM)
vs 7 (standard-UKF IMM), back to low after 5 vs 8 steps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from difffilter.evaluate.intervals import Interval, crossed_interval
from difffilter.evaluate.metrics import mode_switch_delay
from difffilter.filters.protocol import Filter

__all__ = ["PAPER_SWITCH_STEPS", "SWITCH_KEYS", "switch_delays", "switching_markdown", "switching_rows", "time_per_step"]

#: p003's switching speed (steps): low->high at the 10-20 s acceleration, back to low at 20-60 s.
PAPER_SWITCH_STEPS: dict[str, tuple[float, float]] = {"simplified": (5.0, 5.0), "standard": (7.0, 8.0)}

#: Per-run statistics of :func:`switch_delays`.
SWITCH_KEYS = ("first_up", "first_down", "all_up", "all_down", "detected_up", "detected_down")


def switch_delays(mode_probs: Tensor, modes: Tensor, threshold: float = 0.5) -> dict[str, Tensor]:
    """Per-run switching statistics ``{key: [N]}`` (float64, NaN where undefined) of mode
    probabilities ``[N, T, 2]`` against true modes ``[N, T]`` (0 low, 1 high):

    * ``first_up`` / ``first_down``: delay of the run's first low -> high switch and of the first
      high -> low switch (p003's two numbers);
    * ``all_up`` / ``all_down``: mean delay over the run's detected switches of that direction;
    * ``detected_up`` / ``detected_down``: fraction of the run's switches of that direction detected.
    """
    if mode_probs.ndim != 3 or mode_probs.shape[-1] != 2:
        raise ValueError(f"mode_probs must be [N, T, 2], got {tuple(mode_probs.shape)}")
    d = mode_switch_delay(mode_probs, modes.long(), threshold)
    n = mode_probs.shape[0]
    out = {k: torch.full((n,), math.nan, dtype=torch.float64) for k in SWITCH_KEYS}
    for run in range(n):
        for name, target in (("up", 1), ("down", 0)):
            sel = (d.batch_index == run) & (d.mode == target)
            if not bool(sel.any()):
                continue
            vals, starts = d.delay[sel].to(torch.float64), d.start[sel]
            ok = torch.isfinite(vals)
            out[f"first_{name}"][run] = vals[int(torch.argmin(starts))]
            out[f"detected_{name}"][run] = ok.to(torch.float64).mean()
            if bool(ok.any()):
                out[f"all_{name}"][run] = vals[ok].mean()
    return out


def _cell(iv: Interval, digits: int = 3) -> str:
    if not math.isfinite(iv.estimate):
        return "-"
    if not (math.isfinite(iv.lo) and math.isfinite(iv.hi)):
        return f"{iv.estimate:.{digits}g}"
    return f"{iv.estimate:.{digits}g} [{iv.lo:.{digits}g}, {iv.hi:.{digits}g}]"


def switching_rows(delays: Mapping[str, Mapping[str, Tensor]], prob: float = 0.95) -> list[dict[str, Any]]:
    """One row per filter from ``{filter: {key: [N] or [S, N]}}`` (:func:`switch_delays` per run,
    stacked over training seeds for a learned filter): for each key the mean with its ``prob``
    interval over runs (and seeds: :func:`~difffilter.evaluate.intervals.crossed_interval`; runs where
    a delay is undefined are left out of it) and, for the first switches, how many runs detected it."""
    rows = []
    for name, stats in delays.items():
        row: dict[str, Any] = {"filter": name}
        for key in SWITCH_KEYS:
            m = torch.as_tensor(stats[key], dtype=torch.float64)
            m = m[None] if m.ndim == 1 else m
            row[key] = crossed_interval(m, prob)
            if key.startswith("first_"):
                row[f"{key}_found"] = f"{int(torch.isfinite(m).sum())}/{m.numel()}"
        rows.append(row)
    return rows


def switching_markdown(rows: list[dict[str, Any]], paper: Mapping[str, str] | None = None) -> list[str]:
    """A markdown table of :func:`switching_rows` (``paper``: the published numbers per row name)."""
    head = "| filter | first low->high | found | first high->low | found | all low->high | all high->low | detected up / down | p003 |"
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        det = f"{_cell(r['detected_up'])} / {_cell(r['detected_down'])}"
        cells = [r["filter"], _cell(r["first_up"]), r["first_up_found"], _cell(r["first_down"]), r["first_down_found"]]
        cells += [_cell(r["all_up"]), _cell(r["all_down"]), det, (paper or {}).get(r["filter"], "")]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


@torch.no_grad()
def time_per_step(filters: Mapping[str, Filter], batch: Mapping[str, Any], *, steps: int = 200, repeats: int = 3) -> dict[str, float]:
    """Fastest of ``repeats`` rounds (filters interleaved, after one untimed warm-up round) of the
    wall time per step (ms) of each filter on the first ``steps`` steps of ``batch`` (robust to
    other processes on a shared machine)."""
    steps = min(int(steps), batch["measurements"].shape[1])
    z, mask = batch["measurements"][:, :steps], batch["mask"]
    mask = None if mask is None else mask[:, :steps]
    ctrl = {k: v[:, :steps] for k, v in batch["controls"].items()}
    best = {name: math.inf for name in filters}
    for rnd in range(int(repeats) + 1):
        for name, filt in filters.items():
            tic = time.perf_counter()
            filt(z, batch["initial_mean"], batch["initial_cov"], mask=mask, controls=ctrl)
            if rnd > 0:
                best[name] = min(best[name], 1e3 * (time.perf_counter() - tic) / steps)
    return best
