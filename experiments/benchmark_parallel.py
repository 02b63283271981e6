"""Sequential vs parallel-in-time (associative-scan) Kalman filter and RTS smoother.

    python experiments/benchmark_parallel.py                               # the default grid (~5 min on 2 cores)
    python experiments/benchmark_parallel.py --steps 100 1000 --batches 1 16 --out results/benchmark_parallel.md
    python experiments/benchmark_parallel.py --device cuda                 # on a GPU machine

Prints a markdown table: per ``(T, B)`` the best-of-``repeats`` wall time of the sequential
:class:`~difffilter.filters.KalmanFilter` and of :class:`~difffilter.filters.ParallelKalmanFilter`
(forward; forward + backward of the log-likelihood to Q and R; the RTS smoothers with
``--smoother``), their ratio and their log-likelihood difference.  dynamax's parallel filter is
added when JAX and dynamax are importable (they are optional; nothing is installed here).
Helpers: ``experiments/benchmarks/parallel.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from experiments.benchmarks.parallel import dynamax_available, markdown, run_grid  # noqa: E402


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[100, 1000, 10000, 100000])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 256])
    parser.add_argument("--max-elements", type=int, default=100_000, help="skip (T, B) with B*T above this")
    parser.add_argument("--max-sequential", type=int, default=20_000, help="time the sequential filter only up to this B*T")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument("--no-backward", action="store_true", help="skip the forward+backward rows")
    parser.add_argument("--smoother", action="store_true", help="add the RTS smoother rows")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of small runs (1 beyond B*T = 1e5)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table (with the command) here")
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("--device cuda needs a CUDA build of torch and a GPU")
    torch.manual_seed(0)
    start = time.perf_counter()
    rows = run_grid(
        args.steps,
        args.batches,
        dtype=getattr(torch, args.dtype),
        device=args.device,
        max_elements=args.max_elements,
        max_sequential=args.max_sequential,
        backward=not args.no_backward,
        smoother=args.smoother,
        repeats=lambda elements: args.repeats if elements <= 2_000 else (2 if elements <= 20_000 else 1),
    )
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or platform.machine()
    header = (
        f"Command: `python experiments/benchmark_parallel.py {' '.join(argv if argv is not None else sys.argv[1:])}`\n\n"
        f"Device: {args.device} ({device}), torch {torch.__version__}, {torch.get_num_threads()} threads, {args.dtype}; "
        f"dynamax: {'measured' if dynamax_available() else 'not installed (no peer rows)'}; "
        f"total {time.perf_counter() - start:.0f} s.  Times: best wall-clock seconds of the repeats; "
        "parallel / sequential < 1 means the scan is faster; '-': the sequential filter not timed "
        f"(B*T above --max-sequential {args.max_sequential}).\n\n"
    )
    text = header + markdown(rows) + "\n"
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        command = " ".join(["python", "experiments/benchmark_parallel.py", *(argv if argv is not None else sys.argv[1:])])
        args.out.write_text(f"<!-- generated file: {command} -->\n# Parallel-in-time Kalman filter: benchmark\n\n" + text)
    return text


if __name__ == "__main__":
    main()
