"""Evaluate a learner checkpoint exactly like the end of training (Hydra entry point).

    python experiments/eval.py ckpt_path=outputs/train/runs/<run>/checkpoints/epoch_024.ckpt
    python experiments/eval.py ckpt_path=<file> data.test_size=200     # a stored value replaced
    python experiments/eval.py ckpt_path=<file> config_from_checkpoint=false experiment=p004_blend

Rebuilds the training run's test set, hand-tuned filter, oracle and baselines from the config
stored in the checkpoint, loads the learned filter from it, and writes results.md / results.csv
/ per_run.csv and TensorBoard events to outputs/eval/runs/<date>_<time>/: the same table as the
training run's (``train.py train=false ckpt_path=...`` does the same).  The logic lives in
experiments.runner.experiment.run_experiment.
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


@hydra.main(version_base="1.3", config_path="../conf", config_name="eval")
def main(cfg: DictConfig) -> float | None:
    """Evaluate ``cfg.ckpt_path``; the return value is the learned filter's metric."""
    out = run_experiment(cfg)
    if not out:
        return None
    log.info("results written to %s", out["output_dir"])
    return out["metric"]


if __name__ == "__main__":
    main()
