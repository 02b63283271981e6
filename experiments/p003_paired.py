"""p003: cross-family test on the paper's scripted profile and switching delays of a seed sweep.

    python experiments/train.py experiment=p003_modes -m seed=0,1,2,3,4 learner.init_perturbation=0.3 \\
        hydra.sweep.dir=outputs/p003_final/p003_modes
    python experiments/p003_paired.py sweep_dir=outputs/p003_final/p003_modes   # -> outputs/p003_final/p003_modes_paper_profile/

For every family (experiment) of the sweep: p003's profile with the family's noise, ``runs``
flights (one fixed seed), the hand-tuned simplified-UKF IMM, the paper's standard-UKF IMM, the
oracle and every seed's learned IMM on the same flights; writes ``summary_<metric>.md`` (paired
differences, G, per-block ANEES, as the sweep's own summary) and ``switching.md`` (delays with
intervals next to p003's 5/7 and 5/8 steps, per-step cost).  It also writes the sweep's own
summaries for velocity and attitude (``summary_rmse_velocity.md``, ...).  Options in
conf/p003_paired.yaml; the logic is :func:`experiments.papers.p003.paired.paper_profile_report`.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.papers.p003.paired import paper_profile_report, summarize_metrics  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="p003_paired")
def main(cfg: DictConfig) -> None:
    """Write and print the report of ``cfg.sweep_dir``."""
    torch.set_num_threads(int(cfg.threads))
    summarize_metrics(str(cfg.sweep_dir))
    duration = None if cfg.duration is None else float(cfg.duration)
    md = paper_profile_report(str(cfg.sweep_dir), out_dir=cfg.out, runs=int(cfg.runs), seed=int(cfg.seed), duration=duration)
    print(md.read_text())


if __name__ == "__main__":
    main()
