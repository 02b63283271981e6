"""Cross-family test and switching delays of a p003 seed sweep (``experiments/p003_paired.py``).

A sweep ``python experiments/train.py -m experiment=p003_imm_sins,p003_modes,p003_physical
seed=0,1,2,3,4`` trains every family's learned IMM on random flights and tests it on held-out
random flights of the same family (the sweep's ``summary.md``).  :func:`paper_profile_report`
then, for every family (group of jobs), rebuilds the family on **p003's scripted flight profile**
(``paper_test`` of the job's config: a different flight family from training, with the family's
sensor noise), draws ``runs`` test flights with one fixed seed, and runs on the same flights

* ``hand-tuned`` - p003's IMM of simplified UKFs with the paper's values (the job's
  ``experiment.hand_tuned``),
* ``IMM standard UKF`` - the paper's baseline, the same IMM of standard (additive-noise) UKFs,
* ``oracle`` - the family's true parameters (``experiment.oracle``, with the scripted profile's
  transition matrix), where the family has one,
* ``learned`` - every job's best checkpoint (:func:`~experiments.papers.p003.experiment.learned_from_state`).

Outputs under ``out_dir``: one directory per job with ``per_run.csv`` / ``results.csv`` (those
four filters, paired on the same runs) and the job's overrides, so
:func:`~experiments.runner.sweep.summarize_sweep` pools them as it pools the sweep; its summaries
for each metric (``summary_<metric>.md``); ``switching.md`` / ``switching.csv``: the switching
delays (:mod:`experiments.papers.p003.report`) of every filter with intervals over runs (and seeds),
next to p003's published delays, and the per-step cost of the simplified and standard IMMs.
"""

from __future__ import annotations

import csv
import math
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from difffilter.evaluate.evaluation import PER_RUN_FILE, Evaluation, evaluate_runs, write_per_run
from difffilter.filters.protocol import Filter
from difffilter.learn.checkpoints import best_checkpoint, read_checkpoint
from difffilter.learn.data import TrajectorySet

from ...runner.experiment import build_filter, write_results
from ...runner.sweep import SUMMARY_CSV, SUMMARY_MD, Job, load_jobs, summarize_sweep
from .experiment import learned_from_state
from .report import PAPER_SWITCH_STEPS, SWITCH_KEYS, switch_delays, switching_markdown, switching_rows, time_per_step

__all__ = ["METRICS", "paper_profile_report", "summarize_metrics"]

#: Per-run metrics summarised (position, velocity and attitude error; ``rmse_<block>`` needs the
#: experiment's ``state_blocks``).
METRICS = ("rmse_pos", "rmse_velocity", "rmse_attitude")

_PAPER = {
    "hand-tuned": f"simplified-UKF IMM: {PAPER_SWITCH_STEPS['simplified'][0]:g} / {PAPER_SWITCH_STEPS['simplified'][1]:g} steps",
    "IMM standard UKF": f"standard-UKF IMM: {PAPER_SWITCH_STEPS['standard'][0]:g} / {PAPER_SWITCH_STEPS['standard'][1]:g} steps",
}


class _Recorder(nn.Module):
    """Runs ``filt`` and keeps every result's mode probabilities (one pass yields the metrics of
    :func:`~difffilter.evaluate.evaluation.evaluate_runs` and the switching delays)."""

    def __init__(self, filt: Filter) -> None:
        super().__init__()
        self.filt = filt
        self.mode_probs: list[Tensor] = []

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        res = self.filt(*args, **kwargs)
        mode_probs = res.extras.get("mode_probs")  # only IMMs have them (the single-UKF oracle has none)
        if mode_probs is not None:
            self.mode_probs.append(mode_probs.detach())
        return res


def _plain(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def _evaluate(filt: Filter, data: TrajectorySet, exp: DictConfig) -> tuple[Evaluation, Tensor | None]:
    rec = _Recorder(filt.to(torch.float64).eval())
    blocks = {str(k): [int(i) for i in v] for k, v in (_plain(exp.get("state_blocks")) or {}).items()} or None
    pos = exp.get("position_index")
    ev = evaluate_runs(rec, data, position_index=None if pos is None else [int(i) for i in pos], blocks=blocks)
    return ev, (torch.cat(rec.mode_probs) if rec.mode_probs else None)


def _groups(jobs: Sequence[Job]) -> dict[str, list[Job]]:
    out: dict[str, list[Job]] = {}
    for j in jobs:
        out.setdefault(j.group, []).append(j)
    return out


def summarize_metrics(directory: str | Path, metrics: Sequence[str] = METRICS, *, draws: int = 4000) -> list[Path]:
    """:func:`~experiments.runner.sweep.summarize_sweep` of ``directory`` for each metric, kept as
    ``summary_<metric>.md``/``.csv`` (``summary.md`` ends as the first metric's)."""
    root, paths = Path(directory), []
    for metric in [*metrics[1:], metrics[0]]:
        md, table = summarize_sweep(root, metric=metric, draws=draws)
        paths.append(root / f"summary_{metric}.md")
        shutil.copyfile(md, paths[-1])
        shutil.copyfile(table, root / f"summary_{metric}.csv")
    return paths


def paper_profile_report(
    sweep_dir: str | Path,
    *,
    out_dir: str | Path | None = None,
    runs: int = 24,
    seed: int = 3,
    duration: float | None = None,
    threshold: float = 0.5,
    prob: float = 0.95,
    draws: int = 4000,
) -> Path:
    """Evaluate the sweep below ``sweep_dir`` on p003's scripted profile (module docstring) and
    return the path of ``switching.md``.

    Args:
        out_dir: where to write (default: ``<sweep_dir>_paper_profile`` beside the sweep).
        runs: test flights per family (one batch; >= 20 for the switching-delay intervals).
        seed: their simulation seed (the same for every family and filter: paired runs).
        duration: flight length in seconds (default: the config's ``paper_test.duration``).
        threshold: mode probability that counts as a switch.
        prob: coverage of the intervals; draws: bootstrap resamples of ``G``.
    """
    sweep = Path(sweep_dir)
    jobs = load_jobs(sweep)
    if not jobs:
        raise FileNotFoundError(f"no finished job (per_run.csv) below {sweep}")
    out = Path(out_dir) if out_dir is not None else sweep.parent / f"{sweep.name}_paper_profile"
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# p003: switching delays on p003's scripted profile", ""]
    table_rows: list[dict[str, Any]] = []
    timed = False
    for group, gjobs in _groups(jobs).items():
        cfg = OmegaConf.load(gjobs[0].directory / ".hydra" / "config.yaml")
        exp = cfg.experiment
        sim = instantiate(cfg.paper_test, _convert_="all")
        kwargs = {} if duration is None else {"duration": float(duration)}
        scen = sim(batch_size=int(runs), seed=int(seed), dtype=torch.float64, **kwargs)
        data = TrajectorySet.from_simulation(scen, torch.float64)
        hand_params = _plain(exp.hand_tuned)
        fixed: dict[str, Filter] = {
            "hand-tuned": build_filter(cfg.filter, dtype=torch.float64, params=hand_params),
            "IMM standard UKF": build_filter(cfg.filter, dtype=torch.float64, params=hand_params, filter="standard"),
        }
        if exp.get("oracle") is not None and exp.oracle.get("filter") is not None:
            fixed["oracle"] = build_filter(exp.oracle.filter, dtype=torch.float64, profile="paper", duration=float(data.num_steps))
        evals = {name: _evaluate(f, data, exp) for name, f in fixed.items()}
        modes = scen.manoeuvre[:, : data.num_steps]
        delays = {name: switch_delays(mp, modes, threshold) for name, (_, mp) in evals.items() if mp is not None}
        learned_delays: list[dict[str, Tensor]] = []
        for job in gjobs:
            ckpt = best_checkpoint(job.directory)  # the best validation checkpoint
            state = read_checkpoint(ckpt)["state_dict"]
            learned = learned_from_state(fixed["hand-tuned"], state, cfg.learner.get("q_groups"), cfg.learner.get("r_groups"))
            ev, mp = _evaluate(learned, data, exp)
            if mp is not None:
                learned_delays.append(switch_delays(mp, modes, threshold))
            job_out = out / (group.replace(" ", "_").replace("=", "-") or "all") / job.directory.name
            (job_out / ".hydra").mkdir(parents=True, exist_ok=True)
            if (job.directory / ".hydra" / "overrides.yaml").exists():
                shutil.copyfile(job.directory / ".hydra" / "overrides.yaml", job_out / ".hydra" / "overrides.yaml")
            every = {**{n: e for n, (e, _) in evals.items()}, "learned": ev}
            write_per_run({n: e.per_run for n, e in every.items()}, job_out / PER_RUN_FILE)
            note = f"{group}: {len(data)} flights x {data.num_steps} s of p003's profile (seed {seed}), checkpoint {ckpt.name}"
            write_results([{"filter": n, **e.summary} for n, e in every.items()], job_out, title=f"paper profile: {group}", note=note)
        if learned_delays:
            delays["learned"] = {k: torch.stack([d[k] for d in learned_delays]) for k in SWITCH_KEYS}
        rows = switching_rows(delays, prob)
        for r in rows:
            table_rows.append({"group": group, "filter": r["filter"], **{k: r[k].estimate for k in SWITCH_KEYS}})
            table_rows[-1].update({f"{k}_lo": r[k].lo for k in SWITCH_KEYS} | {f"{k}_hi": r[k].hi for k in SWITCH_KEYS})
        lines += [f"## {group or 'all jobs'}: {len(data)} flights x {data.num_steps} s, seed {seed}, {len(gjobs)} training seeds", ""]
        lines += switching_markdown(rows, _PAPER) + [""]
        if not timed:
            batch = data.batch(torch.arange(min(2, len(data))))
            imms = {"simplified": fixed["hand-tuned"], "standard": fixed["IMM standard UKF"]}
            imms["augmented"] = build_filter(cfg.filter, dtype=torch.float64, params=hand_params, filter="augmented")
            ms = time_per_step(imms, batch)
            lines += ["Per-step cost of the hand-tuned IMMs (fastest of 3 interleaved rounds, 200 steps, 2 flights, ms/step): "]
            lines += [", ".join(f"{k} {v:.2f}" for k, v in ms.items()) + ".", ""]
            timed = True
    intro = [
        f"Delay = steps from a true mode change (manoeuvre flag) until the matching mode's probability exceeds {threshold}; "
        f"first = the profile's first manoeuvre (10-20 s acceleration, up; its end, down); all = mean over the run's detected "
        f"switches; found = runs (x seeds) where the first switch was detected; mean [{100 * prob:g} % interval over runs, "
        "crossed with training seeds for the learned row; runs with an undetected switch left out].",
        "",
    ]
    md = out / "switching.md"
    md.write_text("\n".join(lines[:2] + intro + lines[2:]) + "\n")
    with (out / "switching.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(table_rows[0]) if table_rows else ["group"])
        writer.writeheader()
        writer.writerows({k: (v if not isinstance(v, float) or math.isfinite(v) else "") for k, v in r.items()} for r in table_rows)
    summarize_metrics(out, draws=draws)
    for name in (SUMMARY_MD, SUMMARY_CSV):
        if not (out / name).exists():
            raise FileNotFoundError(f"summary {name} was not written under {out}")
    return md
