"""Paired comparison of a p003_imm_sins run's learned IMM with the hand-tuned one and the oracle.

    python experiments/p003_paired.py run_dir=outputs/p003_full_v3

Options in conf/p003_paired.yaml; the logic is :func:`difffilter.papers.p003.paired.paired_report`
(see its module docstring).
"""

from __future__ import annotations

import hydra
import torch
from omegaconf import DictConfig

from difffilter.papers.p003.paired import paired_report


@hydra.main(version_base="1.3", config_path="../conf", config_name="p003_paired")
def main(cfg: DictConfig) -> None:
    """Print the report of ``cfg.run_dir``."""
    torch.set_num_threads(int(cfg.threads))
    print("\n".join(paired_report(str(cfg.run_dir))))


if __name__ == "__main__":
    main()
