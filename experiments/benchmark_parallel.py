"""Sequential vs parallel-in-time (associative-scan) Kalman filter and RTS smoother, and
dynamax's parallel filter and smoother as the peer.

    python experiments/benchmark_parallel.py --smoother                    # the default grid (~20 min on a loaded 2-core CPU)
    python experiments/benchmark_parallel.py --steps 100 1000 --batches 1 16 --out results/benchmark_parallel.md
    python experiments/benchmark_parallel.py --device cuda --steps 10000 --batches 1 64   # on a GPU machine

Prints a markdown table: per ``(T, B)`` the best-of-``repeats`` wall time of the sequential
:class:`~difffilter.filters.KalmanFilter` on the default path (the engine policy in force; the
engine that ran is named) and forced eager, of :class:`~difffilter.filters.ParallelKalmanFilter`
and of dynamax's ``parallel_inference`` (forward; forward + backward of the log-likelihood to Q
and R; the RTS smoothers with ``--smoother``), the parallel filter's ratios to each and the
log-likelihood differences.  The dynamax columns need JAX and dynamax (optional; ``--no-peer``
skips them); dynamax runs after the torch rows in a process of its own
(JAX deadlocked beside torch in one process), with XLA's own thread pool unless ``XLA_FLAGS`` says otherwise.
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

from difffilter.engines.policy import chosen_engine  # noqa: E402
from experiments.benchmarks.parallel import markdown, run_grid  # noqa: E402


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[100, 1000, 10000, 100000])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 256])
    parser.add_argument("--max-elements", type=int, default=100_000, help="skip (T, B) with B*T above this")
    parser.add_argument("--max-sequential", type=int, default=100_000, help="time the sequential filter's default path only up to this B*T")
    parser.add_argument("--max-eager", type=int, default=20_000, help="time the sequential filter forced eager only up to this B*T (CPU)")
    parser.add_argument("--no-peer", action="store_true", help="skip dynamax even where it is installed")
    parser.add_argument("--peer-timeout-s", type=float, default=1800.0, help="bound on the dynamax process (finished cells are kept)")
    parser.add_argument("--peer-all", action="store_true", help="dynamax also on the fwd+bwd and smoother rows (a JIT build each)")
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
    rows, peer = run_grid(
        args.steps,
        args.batches,
        dtype=getattr(torch, args.dtype),
        device=args.device,
        max_elements=args.max_elements,
        max_sequential=args.max_sequential,
        max_eager=args.max_eager,
        peer=not args.no_peer,
        peer_timeout_s=args.peer_timeout_s,
        peer_rows=("filter", "filter fwd+bwd", "smoother") if args.peer_all else ("filter",),
        backward=not args.no_backward,
        smoother=args.smoother,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
        repeats=lambda elements: args.repeats if elements <= 2_000 else (2 if elements <= 20_000 else 1),
    )
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or platform.machine()
    header = (
        f"Command: `python experiments/benchmark_parallel.py {' '.join(argv if argv is not None else sys.argv[1:])}`\n\n"
        f"Device: {args.device} ({device}), torch {torch.__version__}, {torch.get_num_threads()} threads, {args.dtype}; "
        f"engine policy (default path): {chosen_engine()}; peer: {peer}; total {time.perf_counter() - start:.0f} s.  "
        "Times: best wall-clock seconds of the repeats (model: 2-D constant velocity, n = 4, m = 2). "
        "'its engine': what ran the default path's best repeat ('generated': the compiled C++ engine; "
        "'*': the auto policy switched during the repeats). A ratio < 1 means the parallel filter is faster; "
        f"'-': not timed (default path above --max-sequential {args.max_sequential}, eager above "
        f"--max-eager {args.max_eager} or off the CPU, dynamax absent or on a row without --peer-all; "
        "fwd+bwd and smoother rows repeat the filter row's differences).\n\n"
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
