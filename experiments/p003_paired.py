"""Paired comparison of a p003_imm_sins run's learned IMM with the hand-tuned one and the oracle.

    python experiments/p003_paired.py outputs/p003_full_v3

The logic is :func:`difffilter.papers.p003.paired.paired_report` (see its module docstring).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from difffilter.papers.p003.paired import paired_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("\n".join(paired_report(args.run_dir)))


if __name__ == "__main__":
    main()
