"""The benchmark's UKF training step (p000 GPS/DR model, ``experiments/benchmark.py``'s ``ukf``
case: value and gradient of the total log-likelihood w.r.t. diag R) on a GPU, against dynamax's
UKF on JAX's device and against the CPU default path, in one run.

    python experiments/benchmark_gpu_ukf.py --batch 4096 --steps 500 --out $OUT/gpu_ukf.md

``experiments/benchmark.py`` (Hydra) times on the CPU only; this script reuses its case builders
(:mod:`experiments.benchmarks.cases`, :mod:`experiments.benchmarks.dynamax_peer`) so that the
model, data and trained parameters are the same.  Rows: difffilter eager on the device (the
default path there: the engine policy compiles CPU calls only), ``FusedFilter(engine="inductor")``
on the device (its first call, the compilation, timed apart), the CPU default path (engine named)
and dynamax; each with its log-likelihood difference to the eager device run.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse  # noqa: E402
import time  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

try:  # the optional peer; dynamax_available() below says why it is skipped when missing
    import jax  # noqa: E402
except ImportError:
    jax = None

from difffilter.engines import FusedFilter  # noqa: E402
from difffilter.engines.policy import chosen_engine, last_engine  # noqa: E402
from experiments.benchmarks.cases import builtin_case  # noqa: E402
from experiments.benchmarks.dynamax_peer import dynamax_available, prepare_dynamax  # noqa: E402
from experiments.benchmarks.gpsdr import BenchData, simulate_gpsdr  # noqa: E402

SETTINGS = SimpleNamespace(ukf_alpha=1.0, ukf_beta=2.0, ukf_kappa=0.0, ekf_analytic_jacobian=True)  # conf/benchmark/full.yaml


def _to(data: BenchData, device: str) -> BenchData:
    return BenchData(*(getattr(data, f).to(device) for f in BenchData.__dataclass_fields__))


def _best(fn, repeats: int, device: str) -> tuple[float, np.ndarray]:  # type: ignore[no-untyped-def]
    out, best = None, float("inf")
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        start = time.perf_counter()
        out = fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return best, out  # type: ignore[return-value]


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-cpu", action="store_true", help="skip the CPU default-path row")
    parser.add_argument("--no-inductor", action="store_true", help="skip FusedFilter(engine='inductor') on the device")
    parser.add_argument("--no-peer", action="store_true", help="skip dynamax even where it is installed")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("--device cuda needs a CUDA build of torch and a GPU")
    dtype = getattr(torch, args.dtype)
    data = simulate_gpsdr(batch_size=args.batch, steps=args.steps, seed=0, dtype=dtype)
    rows: list[tuple[str, str, float | None, float, float]] = []  # what, engine, first call [s], best [s], loglik diff

    def step(case, runner=None):  # type: ignore[no-untyped-def]
        params = [p for p in case.filter.parameters() if p.requires_grad]
        filt = runner if runner is not None else case.filter

        def run() -> np.ndarray:
            for p in params:
                p.grad = None
            ll = case.run(filt).log_likelihood.sum(-1)
            (-ll.sum()).backward()
            return ll.detach().double().cpu().numpy()

        return run

    dev_case = builtin_case("ukf", dtype, _to(data, args.device), SETTINGS)
    dev_case.filter.to(args.device)
    run = step(dev_case)
    start = time.perf_counter()
    ref = run()
    first = time.perf_counter() - start
    best, _ = _best(run, args.repeats, args.device)
    rows.append((f"difffilter UKF on {args.device}", str(last_engine(dev_case.filter)), first, best, 0.0))
    if not args.no_inductor:
        fused = FusedFilter(dev_case.filter, engine="inductor")
        run = step(dev_case, fused)
        start = time.perf_counter()
        run()
        first = time.perf_counter() - start
        best, ll = _best(run, args.repeats, args.device)
        rows.append((f"difffilter FusedFilter on {args.device}", "inductor", first, best, float(np.abs(ll - ref).max())))
    if not args.no_cpu:
        cpu_case = builtin_case("ukf", dtype, data, SETTINGS)
        run = step(cpu_case)
        start = time.perf_counter()
        run()
        first = time.perf_counter() - start
        best, ll = _best(run, args.repeats, "cpu")
        rows.append(
            (
                f"difffilter UKF on cpu ({torch.get_num_threads()} threads)",
                str(last_engine(cpu_case.filter)),
                first,
                best,
                float(np.abs(ll - ref).max()),
            )
        )
    peer = "skipped (--no-peer)" if args.no_peer else dynamax_available()
    if peer is None and jax is not None:
        dx = prepare_dynamax("ukf", data, dtype, "train", ukf_alpha=1.0, ukf_beta=2.0, ukf_kappa=0.0)
        best, _ = _best(dx.run, args.repeats, "cpu")  # run() blocks until done
        rows.append((f"dynamax UKF (jax {jax.default_backend()})", "jit", dx.compile_s, best, float(np.abs(dx.loglik() - ref).max())))
    lines = [
        f"Command: `python experiments/benchmark_gpu_ukf.py {' '.join(argv if argv is not None else sys.argv[1:])}`",
        "",
        f"Device: {torch.cuda.get_device_name() if args.device.startswith('cuda') else args.device}; torch {torch.__version__}; "
        f"{args.dtype}; B = {args.batch}, T = {args.steps}; engine policy: {chosen_engine()}; dynamax: {peer or 'measured'}.  "
        "One training step: forward, total log-likelihood, its gradient w.r.t. diag R.  'first call': includes any "
        "compilation; 'best': best of the repeats after it.",
        "",
        "| run | engine | first call [s] | best [s] | ratio to the device's eager run | max abs loglik diff |",
        "|---|---|---:|---:|---:|---:|",
    ]
    base = rows[0][3]
    for what, engine, first_s, best_s, diff in rows:
        first_txt = "-" if first_s is None else f"{first_s:.3f}"
        lines.append(f"| {what} | {engine} | {first_txt} | {best_s:.4f} | {best_s / base:.3g} | {diff:.1e} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)
    return text


if __name__ == "__main__":
    main()
