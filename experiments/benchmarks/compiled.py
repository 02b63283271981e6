"""What FusedFilter's first call costs: a cold start (empty kernel caches) and a warm process
start (a new process that finds the kernels built by an earlier one).

Each measurement runs in a fresh Python process, so nothing of the benchmark's own process
(loaded libraries, traced programs) is reused: the first call is a forward (no gradient), the
second a training step (log-likelihood and gradient), each on ``steps`` steps.  The generated
engine keeps its kernels in ``DIFFFILTER_CACHE_DIR``, the inductor engine in
``TORCHINDUCTOR_CACHE_DIR``; both point into one temporary directory per cold/warm pair.

Run one measurement as a script (prints one JSON line)::

    python -m experiments.benchmarks.compiled --kind ukf --engine generated --dtype float64 --batch 256
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
from typing import Any

import torch

from .cases import builtin_case, torch_runner
from .gpsdr import simulate_gpsdr
from .runner import DTYPES, BenchSettings
from .timing import cpu_with_children

__all__ = ["compile_costs", "first_calls"]


def first_calls(*, kind: str, engine: str, dtype: str, batch: int, steps: int, threads: int = 1, seed: int = 0) -> dict[str, Any]:
    """Seconds of the first forward call and of the first training step after it, in this process
    (wall clock), and the CPU seconds of both together, the compiler's included (``total_cpu_s``)."""
    torch.set_num_threads(threads)
    dt = DTYPES[dtype]
    case = builtin_case(kind, dt, simulate_gpsdr(batch_size=batch, steps=steps, seed=seed, dtype=dt), BenchSettings())
    c0, t0 = cpu_with_children(), time.perf_counter()
    forward = torch_runner(case, "forward", fused=True, threads=threads, engine=engine)
    forward()
    t1 = time.perf_counter()
    torch_runner(case, "train", runner=forward.runner)()  # the same wrapper, as a training script uses it
    t2, c2 = time.perf_counter(), cpu_with_children()
    return {"first_forward_s": t1 - t0, "first_train_s": t2 - t1, "total_s": t2 - t0, "total_cpu_s": c2 - c0}


def _in_subprocess(cache: Path, timeout_s: float | None, **config: Any) -> dict[str, Any]:
    args = [sys.executable, "-m", "experiments.benchmarks.compiled"]
    for k, v in config.items():
        args += [f"--{k.replace('_', '-')}", str(v)]
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["DIFFFILTER_CACHE_DIR"] = str(cache / "difffilter")
    env["TORCHINDUCTOR_CACHE_DIR"] = str(cache / "inductor")
    t0 = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, env=env, cwd=root)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"compile-cost subprocess failed ({proc.returncode}): {proc.stderr[-2000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["process_s"] = wall
    return out


def compile_costs(
    kind: str, *, engine: str, dtype: str = "float64", batch: int = 256, steps: int = 20, threads: int = 1, timeout_s: float | None = 3600.0
) -> list[dict[str, Any]]:
    """Two rows: the cold start and the warm process start of ``FusedFilter(engine=engine)``."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="difffilter-compile-") as tmp:
        for start in ("cold", "warm process"):
            res = _in_subprocess(Path(tmp), timeout_s, kind=kind, engine=engine, dtype=dtype, batch=batch, steps=steps, threads=threads)
            rows.append({"filter": kind, "engine": engine, "dtype": dtype, "B": batch, "start": start, **res})
    return rows


def _main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", default="ukf", choices=["kf", "ekf", "ukf", "imm"])
    p.add_argument("--engine", default="generated")
    p.add_argument("--dtype", default="float64", choices=list(DTYPES))
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    print(json.dumps(first_calls(kind=a.kind, engine=a.engine, dtype=a.dtype, batch=a.batch, steps=a.steps, threads=a.threads)))


if __name__ == "__main__":
    _main()
