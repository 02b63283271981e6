"""Paired comparison of smartLoc runs' learned filters with the hand-tuned one, with block-bootstrap
intervals: is a difference on one held-out segment of one real drive more than noise?

    python experiments/smartloc_paired.py outputs/smartloc_A_v2 outputs/smartloc_B_v2
    python experiments/smartloc_paired.py outputs/smartloc_*        # every run, one line each

The logic is :func:`difffilter.papers.smartloc.paired.compare` (see its module docstring).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from difffilter.papers.smartloc.paired import MARKDOWN_HEADER, block_bootstrap, compare, markdown_row

__all__ = ["block_bootstrap", "compare", "main"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--block", type=int, default=50, help="bootstrap block length in epochs (default 50 = 10 s)")
    parser.add_argument("--draws", type=int, default=4000, help="bootstrap resamples (default 4000)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(MARKDOWN_HEADER)
    for run in args.run_dirs:
        print(markdown_row(run.name, compare(run, block=args.block, draws=args.draws)))


if __name__ == "__main__":
    main()
