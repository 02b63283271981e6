"""Process CPU time of a KF training step with the shared covariance recursion on and off.

    python experiments/benchmark_kf_shared.py                 # B = 16 64 256 1024 4096, T = 500
    python experiments/benchmark_kf_shared.py --batch 256 --steps 500 --repeats 20

The benchmark's KF (the linear CV model on the p000 GPS positions, float64), through
``FusedFilter(kf, engine="generated", threads=1)`` with ``generated_engine().shared_covariance``
True (the covariance recursion once for the batch, :mod:`difffilter.engines.shared`) and
False (every trajectory's own), one thread. Prints the best process CPU time of ``repeats``
training steps (total log-likelihood and its gradient) per configuration, and the ratio (the
engine's batch threshold for the shared path is lifted here, to measure small batches too).
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from difffilter.engines import FusedFilter  # noqa: E402
from difffilter.engines import shared as shared_module  # noqa: E402
from experiments.benchmarks.cases import builtin_case  # noqa: E402
from experiments.benchmarks.gpsdr import simulate_gpsdr  # noqa: E402
from experiments.benchmarks.runner import BenchSettings  # noqa: E402
from experiments.benchmarks.timing import best_of  # noqa: E402


def cpu_per_training_step(batch: int, steps: int, repeats: int, shared: bool) -> float:
    """Best process CPU seconds of one training step (after one warm-up call)."""
    case = builtin_case("kf", torch.float64, simulate_gpsdr(batch_size=batch, steps=steps, seed=0, dtype=torch.float64), BenchSettings())
    fused = FusedFilter(case.filter, engine="generated", threads=1)
    fused.generated_engine().shared_covariance = shared

    def train() -> None:
        fused(case.measurements, case.initial_mean, case.initial_cov).log_likelihood.sum().backward()

    return best_of(train, repeats, clock=time.process_time)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, nargs="+", default=[16, 64, 256, 1024, 4096])
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--repeats", type=int, default=20)
    a = p.parse_args()
    torch.set_num_threads(1)
    shared_module.MIN_SHARED_BATCH = 1  # measure the shared path at every batch size (the engine uses it from 64)
    print("| B | per trajectory ms | shared ms | per trajectory / shared |\n|---|---|---|---|")
    for b in a.batch:
        own = cpu_per_training_step(b, a.steps, a.repeats, False)
        shared = cpu_per_training_step(b, a.steps, a.repeats, True)
        print(f"| {b} | {own * 1e3:.2f} | {shared * 1e3:.2f} | {own / shared:.2f} |", flush=True)


if __name__ == "__main__":
    main()
