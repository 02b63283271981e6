"""p003: cross-family test on the paper's scripted profile and switching delays of a seed sweep.

    python experiments/train.py -m experiment=p003_imm_sins,p003_modes,p003_physical seed=0,1,2,3,4 \\
        learner.init_perturbation=0.3 hydra/launcher=joblib hydra.sweep.dir=outputs/p003_sweep
    python experiments/p003_paired.py outputs/p003_sweep            # -> outputs/p003_sweep_paper_profile/

For every family (experiment) of the sweep: p003's profile with the family's noise, ``--runs``
flights (one fixed seed), the hand-tuned simplified-UKF IMM, the paper's standard-UKF IMM, the
oracle and every seed's learned IMM on the same flights; writes ``summary_<metric>.md`` (paired
differences, G, per-block ANEES, as the sweep's own summary) and ``switching.md`` (delays with
intervals next to p003's 5/7 and 5/8 steps, per-step cost).  It also writes the sweep's own
summaries for velocity and attitude (``summary_rmse_velocity.md``, ...).  The logic is
:func:`difffilter.papers.p003.paired.paper_profile_report`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from difffilter.papers.p003.paired import paper_profile_report, summarize_metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: <sweep_dir>_paper_profile)")
    parser.add_argument("--runs", type=int, default=24, help="test flights per family on the paper profile")
    parser.add_argument("--seed", type=int, default=3, help="their simulation seed")
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: the config's paper_test.duration)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    summarize_metrics(args.sweep_dir)
    md = paper_profile_report(args.sweep_dir, out_dir=args.out, runs=args.runs, seed=args.seed, duration=args.duration)
    print(md.read_text())


if __name__ == "__main__":
    main()
