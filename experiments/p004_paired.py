"""Paired Monte-Carlo comparison of a p004_blend run's learned filter with the hand-tuned one.

    python experiments/p004_paired.py run_dir=outputs/p004_full_v2
    python experiments/p004_paired.py run_dir=outputs/p004_full_v2 initial_error=false \
        '+model={sigma_accel_bias_walk: 1e-5, sigma_gyro_bias_walk: 1e-6, sigma_position_step: 0.0288675}'
                                     # the settings before issue 7's fixes (Q_pp = sigma_a^2 T^4/3)

Options in conf/p004_paired.yaml; the logic is :func:`experiments.papers.p004.paired.paired_report`
(see its module docstring).
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import hydra  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.papers.p004.paired import paired_report  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="p004_paired")
def main(cfg: DictConfig) -> None:
    """Print the report of ``cfg.run_dir``."""
    torch.set_num_threads(int(cfg.threads))
    options = {str(k): float(v) for k, v in (cfg.model or {}).items()}
    runs = None if cfg.runs is None else int(cfg.runs)
    print("\n".join(paired_report(str(cfg.run_dir), runs=runs, model_options=options, initial_error=bool(cfg.initial_error))))


if __name__ == "__main__":
    main()
