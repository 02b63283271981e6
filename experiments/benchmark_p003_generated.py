"""p003's IMM bank on FusedFilter's generated engine: size of the traced step, first-call (trace and
C++ build) time, speed and agreement with the reference filter (results/benchmark_engine.md, session 4).

    python experiments/benchmark_p003_generated.py                      # size of the step only (seconds)
    python experiments/benchmark_p003_generated.py --max-nodes 400000   # also build and time the forward kernel
    python experiments/benchmark_p003_generated.py --max-nodes 400000 --train   # and the reverse kernel

The build of the forward kernel took 12 min and 6.2 GB (compiler) on the 2-core development machine;
use a fresh ``DIFFFILTER_CACHE_DIR`` to time a cold build.
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
from difffilter.engines import trace as fused_trace  # noqa: E402
from difffilter.engines.graph import UnsupportedOp  # noqa: E402
from experiments.papers.p003.experiment import group_scale_q, p003_imm, simulate  # noqa: E402

#: experiments/papers/p003/conf/filter/p003_imm_simplified.yaml and the learner of
#: experiments/papers/p003/conf/experiment/p003_imm_sins.yaml
MODEL = {"num_satellites": 8, "linearized": False, "position_in_metres": True, "discretization": "expm"}
TRANSITION = [[0.9952238805970149, 0.004776119402985075], [0.056, 0.944]]


def main() -> None:
    """Trace (and optionally build and time) the generated step of p003's learned IMM."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--max-nodes", type=int, default=None, help="raise the engine's step-size limit to this")
    parser.add_argument("--train", action="store_true", help="also build and time the reverse kernel (training step)")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.max_nodes is not None:
        fused_trace.MAX_NODES = args.max_nodes
    sc = simulate(args.batch, 0, torch.float64, duration=float(args.steps), profile="random", num_satellites=8, feedback="imm")
    imm = group_scale_q(p003_imm(model=MODEL, transition=TRANSITION), "imu_white", "range_rate")
    data = (sc.measurements, sc.initial_mean, sc.initial_cov)
    kw = {"mask": sc.mask, "controls": sc.controls}
    fused = FusedFilter(imm, engine="generated")

    def timed(label: str, fn):  # noqa: ANN001, ANN202
        start = time.perf_counter()
        out = fn()
        print(f"{label}: {time.perf_counter() - start:.3f} s", flush=True)
        return out

    with torch.no_grad():
        ref = timed("reference forward", lambda: imm(*data, **kw))
        try:
            out = timed("generated forward, first call (trace + build)", lambda: fused(*data, **kw))
        except UnsupportedOp as exc:
            print(f"generated engine: {exc}")
            return
        timed("generated forward, second call", lambda: fused(*data, **kw))
    print(f"max |mean difference| {float((out.mean - ref.mean).abs().max()):.3g}")
    print(f"max |log-likelihood difference| {float((out.log_likelihood - ref.log_likelihood).abs().max()):.3g}")
    if not args.train:
        return
    params = [p for p in imm.parameters() if p.requires_grad]

    def grads(filt):  # noqa: ANN001, ANN202
        return torch.autograd.grad(filt(*data, **kw).log_likelihood.sum(), params)

    g_ref = timed("reference training step", lambda: grads(imm))
    timed("generated training step, first call (reverse build)", lambda: grads(fused))
    g_gen = timed("generated training step, second call", lambda: grads(fused))
    rel = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-300)) for a, b in zip(g_gen, g_ref, strict=True))
    print(f"max relative gradient difference {rel:.3g}")


if __name__ == "__main__":
    main()
