"""The RTS backward recursion's two paths side by side: the sequential node and the scan.

    python experiments/benchmark_rts_backward.py

On the benchmark's UKF (GPS/DR model) filtered moments and smoother gains, times one forward +
backward of ``rts_backward(method=...)`` (a loss of the smoothed means and covariances) for
``(B, T)`` in (256, 500), (16, 5000), (1, 5000), float64 and float32, one thread, and prints the
largest differences between the two paths' outputs (results/benchmark_engine.md, session 5).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from difffilter.smoothers import make_smoother  # noqa: E402
from difffilter.smoothers.base import rts_backward  # noqa: E402
from experiments.benchmarks.cases import make_difffilter  # noqa: E402
from experiments.benchmarks.gpsdr import simulate_gpsdr  # noqa: E402
from experiments.benchmarks.runner import BenchSettings  # noqa: E402
from experiments.benchmarks.timing import best_of  # noqa: E402


def compare(batch: int, steps: int, dtype: torch.dtype) -> None:
    """Time both paths on one case and print their largest differences."""
    data = simulate_gpsdr(batch_size=batch, steps=steps, seed=0, dtype=dtype)
    filt = make_difffilter("ukf", dtype, BenchSettings())
    smoother = make_smoother(filt)
    z, m0, p0 = data.measurements, data.initial_mean, data.initial_cov
    truth = data.truth[:, 1:, [0, 3]].to(dtype)
    with torch.no_grad():
        res = filt(z, m0, p0)
        init = smoother.initial_belief(z, m0, p0, None)
        gains, prior_cov = smoother.gains(res, init, None)
    leaves = [x.detach().clone().requires_grad_(True) for x in (res.mean, res.cov, res.prior_mean, prior_cov, gains)]

    def run(method: str) -> tuple[torch.Tensor, ...]:
        return rts_backward(*leaves, init["mean"], init["cov"], smoother.dynamics, method=method)

    outs = {}
    for method in ("sequential", "scan"):

        def train(method: str = method) -> None:
            out = run(method)
            ((out[0][..., [0, 3]] - truth).square().mean() + out[1].sum() * 1e-6).backward()

        with torch.no_grad():
            outs[method] = run(method)
        print(f"B={batch} T={steps} {dtype} {method}: forward + backward {best_of(train, 1):.3f} s", flush=True)
    for name, a, b in zip(("mean", "cov", "cross", "initial mean", "initial cov"), outs["sequential"], outs["scan"], strict=True):
        diff = (a - b).abs().max().item()
        print(f"    {name}: max |diff| {diff:.2e} (relative {diff / a.abs().max().item():.2e})")


def main() -> None:
    torch.set_num_threads(1)
    for batch, steps in ((256, 500), (16, 5000), (1, 5000)):
        for dtype in (torch.float64, torch.float32):
            compare(batch, steps, dtype)


if __name__ == "__main__":
    main()
