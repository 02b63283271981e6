"""Paired Monte-Carlo comparison of a ``p004_blend`` run's learned filter with the hand-tuned one
(what ``experiments/p004_paired.py`` prints).

Rebuilds p004's test set (the fixed 400 s drive, ``data.test_size`` runs, the data module's test
seed) and the blend filter with the hand-tuned values and with the learned values of the run's
checkpoint, and reports per filter: RMSE of the position, the paired difference of the per-run
mean squared position error (learned - hand-tuned) with its Monte-Carlo standard error, ANEES
over all 8 states with a 95 % interval over runs (per-run means are independent; the steps of
one run are not, which the chi-square band of results.md assumes), and NEES per state block.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from difffilter.learn.checkpoints import best_checkpoint
from difffilter.learn.learner import load_filter
from difffilter.selection import assign_parameters
from experiments.papers.p004.model import GnssImuModel

from .experiment import blend_filter, p004_simulator

__all__ = ["BLOCKS", "paired_report", "per_run_errors"]

#: State blocks of the planar GNSS/IMU model reported separately.
BLOCKS = {"position": [0, 1], "velocity": [2, 3], "heading": [4], "accel_bias": [5, 6], "gyro_bias": [7]}


def _blend(delta: float, options: Mapping[str, float], sigma_points: Any = None) -> torch.nn.Module:
    model = GnssImuModel(planar=True, dtype=torch.float64, **options)
    return blend_filter(model=model, delta=delta, sigma_points=sigma_points).to(torch.float64)


def per_run_errors(filt: torch.nn.Module, data: Any) -> dict[str, torch.Tensor]:
    """Per-run mean squared position error ``mse_pos [R]`` and NEES per block ``nees_<block> [R]``
    (and over all 8 states, ``nees_all``) of ``filt`` on ``data``."""
    with torch.no_grad():
        res = filt(data.measurements, data.initial_mean, data.initial_cov, mask=data.mask, controls=data.controls)
    err = res.mean - data.truth
    out = {"mse_pos": err[..., :2].pow(2).sum(-1).mean(-1)}
    for name, idx in {**BLOCKS, "all": list(range(8))}.items():
        e = err[..., idx]
        cov = res.cov[..., idx, :][..., :, idx]
        out[f"nees_{name}"] = (e[..., None, :] @ torch.linalg.solve(cov, e[..., None]))[..., 0, 0].mean(-1)
    return out


def paired_report(
    run_dir: str | Path, *, runs: int | None = None, model_options: Mapping[str, float] | None = None, initial_error: bool = True
) -> list[str]:
    """The report lines for the run directory ``run_dir``.

    Args:
        runs: test runs (default: the run's ``data.test_size``).
        model_options: :class:`GnssImuModel` overrides for both filters (values overridden here
            are not taken from the checkpoint).
        initial_error: ``False``: the initial belief's mean is the truth (the old simulator).
    """
    run_dir = Path(run_dir)
    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    ckpt = best_checkpoint(run_dir)
    runs = int(runs or cfg.data.test_size)
    if runs < 2:
        raise ValueError(f"runs must be at least 2, got {runs}")
    test = cfg.data.test_simulator
    data = p004_simulator(
        batch_size=runs,
        seed=int(cfg.data.seeds.test),
        dtype=torch.float64,
        randomize=bool(test.randomize),
        planar=bool(test.planar),
        gnss_outages=[tuple(w) for w in (test.gnss_outages or [])],
        initial_heading_std_deg=test.initial_heading_std_deg,
        initial_error=initial_error,
    )
    options = dict(model_options or {})
    points = cfg.filter.get("sigma_points")  # the run's own set (p004: Julier, lambda = 3 - n)

    def blend() -> torch.nn.Module:
        return _blend(float(cfg.filter.delta), options, None if points is None else instantiate(points))

    hand = blend()
    assign_parameters(hand, OmegaConf.to_container(cfg.experiment.hand_tuned, resolve=True))
    learned = blend()
    learned_state = load_filter(str(ckpt), filter=blend()).state_dict()
    # values overridden by model_options stay as given (they are not learned in p004_blend)
    keep = [n.removeprefix("sigma_") for n in options]
    learned_state = {k: v for k, v in learned_state.items() if not any(n in k for n in keep)}
    learned.load_state_dict({**learned.state_dict(), **learned_state})
    lines = [f"{run_dir}: {runs} runs, checkpoint {ckpt.name}"]
    rows = {"hand-tuned": per_run_errors(hand, data), "learned": per_run_errors(learned, data)}
    for name, r in rows.items():
        nees = r["nees_all"]
        ci = 1.96 * float(nees.std()) / math.sqrt(runs)
        blocks = " ".join(f"{b} {float(r[f'nees_{b}'].mean()):.3f}/{len(i)}" for b, i in BLOCKS.items())
        rmse = math.sqrt(float(r["mse_pos"].mean()))
        lines.append(f"{name:10s} rmse_pos {rmse:.5f} m  ANEES {float(nees.mean()):.3f} +- {ci:.3f} (95 % over runs)  {blocks}")
    d = rows["learned"]["mse_pos"] - rows["hand-tuned"]["mse_pos"]
    base = float(rows["hand-tuned"]["mse_pos"].mean())
    rel, se = 50.0 * float(d.mean()) / base, 50.0 * float(d.std()) / math.sqrt(runs) / base
    lines.append(f"paired: learned - hand-tuned RMSE {rel:+.4f} % +- {se:.4f} % (1 s.e.; {int((d < 0).sum())}/{runs} runs better)")
    return lines
