"""Paired comparison of smartLoc runs' learned filters with the hand-tuned one, with block-bootstrap
intervals: is a difference on one held-out segment of one real drive more than noise?

    python experiments/smartloc_paired.py 'run_dirs=[outputs/smartloc_A_v2,outputs/smartloc_B_v2]'

Options in conf/smartloc_paired.yaml; the logic is :func:`experiments.papers.smartloc.paired.compare`
(see its module docstring).
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pathlib import Path  # noqa: E402

import hydra  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.papers.smartloc.paired import MARKDOWN_HEADER, block_bootstrap, compare, markdown_row  # noqa: E402

__all__ = ["block_bootstrap", "compare", "main"]


@hydra.main(version_base="1.3", config_path="../conf", config_name="smartloc_paired")
def main(cfg: DictConfig) -> None:
    """Print one table row per run directory of ``cfg.run_dirs``."""
    torch.set_num_threads(int(cfg.threads))
    print(MARKDOWN_HEADER)
    for run in cfg.run_dirs:
        print(markdown_row(Path(str(run)).name, compare(str(run), block=int(cfg.block), draws=int(cfg.draws))))


if __name__ == "__main__":
    main()
