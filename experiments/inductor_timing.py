"""Wall-clock of FusedFilter's inductor engine: first call (compilation included), forward, training step.

Usage (from the repository root)::

    PYTHONPATH=$PWD nice -n 10 python experiments/inductor_timing.py [kind] [batch] [steps] [repeats]

``kind`` is a built-in benchmark case (``ukf`` default, ``ekf``, ``kf``...) on the GPS/DR data of
:mod:`experiments.benchmarks.gpsdr`, float64, one thread (``torch.set_num_threads(1)`` and inductor's
``cpp.threads=1``).  Prints one line per measurement: the first forward call (builds the forward
graph), the median of ``repeats`` forward calls, the first training step (builds the backward
graph), the median of ``repeats`` training steps; wall-clock and process CPU seconds.  For a
cold first compilation, point ``TORCHINDUCTOR_CACHE_DIR`` at an empty directory.  Only public API is used, so the script runs
unchanged on older checkouts for before/after comparisons.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from difffilter.engines import FusedFilter  # noqa: E402
from experiments.benchmarks.cases import builtin_case, torch_runner  # noqa: E402
from experiments.benchmarks.gpsdr import simulate_gpsdr  # noqa: E402
from experiments.benchmarks.runner import BenchSettings  # noqa: E402


def _timed(fn: object) -> tuple[float, float]:
    """``(wall, process CPU)`` seconds of ``fn()``: on a shared machine the CPU time is the steadier one."""
    wall, cpu = time.perf_counter(), time.process_time()
    fn()  # type: ignore[operator]
    return time.perf_counter() - wall, time.process_time() - cpu


def _median(fn: object, repeats: int) -> str:
    runs = [_timed(fn) for _ in range(repeats)]
    return f"{statistics.median(w for w, _ in runs):.3f} s wall, {statistics.median(c for _, c in runs):.3f} s CPU"


def main(kind: str = "ukf", batch: int = 256, steps: int = 500, repeats: int = 3) -> None:
    """Print the four timings for case ``kind`` at ``batch`` x ``steps``."""
    torch.set_num_threads(1)
    case = builtin_case(kind, torch.float64, simulate_gpsdr(batch_size=batch, steps=steps, seed=0), BenchSettings())
    fused = FusedFilter(case.filter, engine="inductor", threads=1)
    forward = torch_runner(case, "forward", runner=fused)
    train = torch_runner(case, "train", runner=fused)
    print(f"case={kind} B={batch} T={steps} float64 threads=1 torch={torch.__version__}", flush=True)
    print("first forward (compile + run): {:.1f} s wall, {:.1f} s CPU".format(*_timed(forward)), flush=True)
    print(f"forward median of {repeats}: {_median(forward, repeats)}", flush=True)
    print("first training step (compile + run): {:.1f} s wall, {:.1f} s CPU".format(*_timed(train)), flush=True)
    print(f"training step median of {repeats}: {_median(train, repeats)}", flush=True)
    print(f"engine: {fused.last_engine}, compile failed: {fused._compile_failed}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    main(args[0] if args else "ukf", *(int(a) for a in args[1:4]))
