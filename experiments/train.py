"""Learn filter parameters from simulated trajectories (Hydra entry point).

    python experiments/train.py                        # default: 2-D Singer target, in-family
    python experiments/train.py debug=smoke            # < 1 minute end-to-end
    python experiments/train.py experiment=cv2d loss=mse_nees
    python experiments/train.py trainer=ddp_sim        # 2 CPU processes (DDP, gloo)
    python experiments/train.py -m optimizer.lr=0.02,0.05,0.1 hydra/launcher=joblib hydra.launcher.n_jobs=2
    python experiments/train.py hydra.run.dir=<interrupted run> resume=true   # continue from its last.ckpt
    python experiments/train.py train=false ckpt_path=<file>  # evaluate only (= experiments/eval.py)

Builds everything from conf/train.yaml, fits, tests, then evaluates the hand-tuned, learned and
oracle filters on held-out test trajectories; writes results.md / results.csv and TensorBoard
events to the run directory, prints the table and returns the experiment's metric (what a
Hydra sweeper such as Optuna minimises).  SIGTERM/SIGINT (and SIGUSR2, submitit's warning before
a SLURM time limit) write checkpoints/last.ckpt and exit with status 128 + the signal number
(143/130/140); status.json in the run directory says completed, interrupted or failed.
The logic lives in experiments.runner.experiment.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# difffilter before torch, so that OpenMP's idle workers sleep instead of spinning (difffilter/_openmp.py)
importlib.import_module("difffilter")

import logging  # noqa: E402

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.runner.experiment import run_experiment  # noqa: E402

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    """Train and evaluate; the return value is the metric a sweeper optimises (optimized_metric)."""
    out = run_experiment(cfg)
    if not out:  # non-zero DDP ranks evaluate nothing
        return None
    log.info("results written to %s", out["output_dir"])
    return out["optimized"]


if __name__ == "__main__":
    main()
