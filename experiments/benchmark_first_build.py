"""Cold and warm first call of the compiled engine (issue 26: bounded build cost).

For each model a fresh process with an empty kernel cache (``DIFFFILTER_CACHE_DIR`` a new
temporary directory) runs one forward + backward of a UKF on the generated engine (the same as
``DIFFFILTER_ENGINE=compiled`` and a plain call); a second fresh process with that cache then
does the same (warm start); both also run the eager filter for comparison.  CPU is the
process's user + system time including its compiler subprocesses.

* ``n=4``: README's first model (constant velocity in 2-D, range by ``hypot`` and bearing by
  ``atan2``, a wrapped bearing);
* ``n=8``: constant velocity in 4 axes, range and bearing on the first two, the last two
  positions observed directly.

Usage: ``python experiments/benchmark_first_build.py [--batch 32] [--steps 100] [--models 4,8]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from difffilter.engines import FusedFilter  # noqa: E402
from difffilter.filters import UKF  # noqa: E402
from difffilter.models import FunctionalModel  # noqa: E402
from experiments.benchmarks.timing import cpu_with_children  # noqa: E402

D = torch.float64


def _model(n: int):
    axes = n // 2
    blocks = [torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D)] * axes
    transition = torch.block_diag(*blocks)

    def f(x):
        return x @ transition.mT

    def h(x):
        out = [x[..., 0].hypot(x[..., 2]), torch.atan2(x[..., 2], x[..., 0])]
        out += [x[..., 2 * k] for k in range(2, axes)]
        return torch.stack(out, -1)

    m = 2 + max(0, axes - 2)
    r = torch.full((m,), 0.25, dtype=D)
    r[1] = 1e-4
    model = FunctionalModel(f=f, h=h, Q=0.1 * torch.eye(n, dtype=D), R=torch.diag(r), angular_measurements=[1])
    return UKF(model), m


def child(n: int, batch: int, steps: int) -> None:
    ukf, m = _model(n)
    g = torch.Generator().manual_seed(0)
    z = torch.randn(batch, steps, m, dtype=D, generator=g) + 10.0
    m0 = torch.zeros(n, dtype=D)
    m0[0] = 10.0
    p0 = torch.eye(n, dtype=D)
    out = {}
    for name, runner in (("compiled", FusedFilter(ukf, engine="generated")), ("eager", ukf)):
        w0, c0 = time.perf_counter(), cpu_with_children()
        (-runner(z, m0, p0).log_likelihood.mean()).backward()
        out[name] = (time.perf_counter() - w0, cpu_with_children() - c0)
    w0, c0 = time.perf_counter(), cpu_with_children()
    (-FusedFilter(ukf, engine="generated")(z, m0, p0).log_likelihood.mean()).backward()
    out["compiled again"] = (time.perf_counter() - w0, cpu_with_children() - c0)
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--models", default="4,8")
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.batch, args.steps)
        return
    print(f"B={args.batch} T={args.steps} float64, UKF, first forward + backward; {os.cpu_count()} CPUs, torch {torch.__version__}")
    print(f"{'n':>3s} {'cache':6s} {'compiled wall s':>15s} {'compiled cpu s':>14s} {'eager wall s':>12s} {'next compiled call s':>20s}")
    for n in (int(x) for x in args.models.split(",")):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "DIFFFILTER_CACHE_DIR": cache, "DIFFFILTER_ENGINE": "eager"}
            for label in ("cold", "warm"):
                cmd = [sys.executable, __file__, "--child", str(n), "--batch", str(args.batch), "--steps", str(args.steps)]
                res = json.loads(subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1])
                cw, cc = res["compiled"]
                print(f"{n:3d} {label:6s} {cw:15.2f} {cc:14.2f} {res['eager'][0]:12.3f} {res['compiled again'][0]:20.3f}")


if __name__ == "__main__":
    main()
