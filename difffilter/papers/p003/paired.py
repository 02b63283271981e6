"""Paired comparison of a ``p003_imm_sins`` run's learned IMM with the hand-tuned one and the oracle
(what ``experiments/p003_paired.py`` prints).

Rebuilds the run's test set (its data module, test seed) and the hand-tuned, learned (best
checkpoint, in the learner's layout: ``learner.q_groups``) and oracle IMMs, runs them on every
test run, and reports per filter the position RMSE of each run and of all runs, the NLL per step,
and for each pair the mean relative difference of the per-run RMSE with its standard error (the
runs are independent; the steps of one run are not) and how many runs are lower.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ...learn.checkpoints import best_checkpoint
from ...learn.experiment import build_filter
from .report import ModeSwitchReport

__all__ = ["paired_report"]


def paired_report(run_dir: str | Path) -> list[str]:
    """The report lines for the run directory ``run_dir`` (``.hydra/config.yaml`` and ``checkpoints/``)."""
    run_dir = Path(run_dir)
    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    ckpt = best_checkpoint(run_dir)
    test = instantiate(cfg.data, _convert_="all").dataset("test")
    batch = test.batch(torch.arange(len(test)))
    plain = lambda node: OmegaConf.to_container(node, resolve=True) if node is not None else None  # noqa: E731
    exp = cfg.experiment
    hand = build_filter(cfg.filter, dtype=torch.float64, params=plain(exp.hand_tuned))
    filters = {"hand-tuned": hand, "learned": ModeSwitchReport._learned(hand, run_dir, cfg.learner.get("q_groups"))}
    if exp.get("oracle") is not None and exp.oracle.get("filter") is not None:
        filters["oracle"] = build_filter(exp.oracle.filter, dtype=torch.float64, params=plain(exp.oracle.get("params")))
    idx = [int(i) for i in exp.position_index]
    tidx = idx if exp.get("truth_position_index") is None else [int(i) for i in exp.truth_position_index]
    rmse: dict[str, torch.Tensor] = {}
    lines = [f"{run_dir}: {len(test)} test runs, checkpoint {ckpt.name}"]
    for name, filt in filters.items():
        with torch.no_grad():
            res = filt(batch["measurements"], batch["initial_mean"], batch["initial_cov"], mask=batch["mask"], controls=batch["controls"])
        err = res.mean[..., idx] - batch["truth"][..., tidx]
        rmse[name] = err.pow(2).sum(-1).mean(-1).sqrt()
        total = math.sqrt(float(rmse[name].pow(2).mean()))
        runs = " ".join(f"{v:.4f}" for v in rmse[name].tolist())
        lines.append(f"{name:10s} rmse_pos {total:.4f} m  NLL {float(-res.log_likelihood.mean()):.4f}/step  per run: {runs}")
    for a, b in (("learned", "hand-tuned"), ("learned", "oracle"), ("hand-tuned", "oracle")):
        if a in rmse and b in rmse:
            d = (rmse[a] / rmse[b] - 1.0) * 100.0
            se = float(d.std()) / math.sqrt(d.numel())
            lines.append(f"{a} - {b}: rmse_pos {float(d.mean()):+.3f} % (s.e. {se:.3f} %), lower in {int((d < 0).sum())}/{d.numel()} runs")
    return lines
