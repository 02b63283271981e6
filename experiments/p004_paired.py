"""Paired Monte-Carlo comparison of a p004_blend run's learned filter with the hand-tuned one.

    python experiments/p004_paired.py outputs/p004_full_v2
    python experiments/p004_paired.py outputs/p004_full_v2 --no-initial-error \
        --model sigma_accel_bias_walk=1e-5 sigma_gyro_bias_walk=1e-6 sigma_position_step=0.0288675
                                     # the settings before issue 7's fixes (Q_pp = sigma_a^2 T^4/3)

The logic is :func:`difffilter.papers.p004.paired.paired_report` (see its module docstring).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from difffilter.papers.p004.paired import paired_report


def _option(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    try:
        return name, float(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{name}: not a number: {value!r}") from exc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--runs", type=int, default=None, help="test runs (default: the run's data.test_size)")
    parser.add_argument("--model", type=_option, nargs="*", default=[], help="GnssImuModel overrides NAME=VALUE (both filters)")
    parser.add_argument("--no-initial-error", action="store_true", help="initial belief mean = truth (the old simulator)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = paired_report(args.run_dir, runs=args.runs, model_options=dict(args.model), initial_error=not args.no_initial_error)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
