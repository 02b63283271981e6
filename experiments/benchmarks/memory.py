"""Peak memory of a truncated-BPTT training step, measured in a fresh process per configuration.

One training step filters ``T`` steps of ``B`` trajectories in windows of ``W`` steps; each
window's loss (negative mean log-likelihood) is back-propagated and an optimiser step taken,
then the belief is detached and carried into the next window
(``forward(..., belief=detach_belief(res.final_belief))``).  The autograd graph then never
holds more than one window, so the peak should not grow with ``T``.

Run one configuration as a script (prints one JSON line)::

    python -m experiments.benchmarks.memory --filter ukf --dtype float64 --steps 5000 --batch 1024 --window 100

or call :func:`measure_training_memory`, which launches that in a subprocess so the peak
resident set (``VmHWM``) belongs to this configuration alone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

from difffilter.engines import FusedFilter
from difffilter.filters.base import detach_belief

from .cases import builtin_case
from .gpsdr import simulate_gpsdr
from .runner import DTYPES, BenchSettings
from .timing import MemoryProbe, read_status_mb

__all__ = ["measure_training_memory", "training_step_memory"]


def training_step_memory(
    *,
    kind: str,
    dtype: str,
    steps: int,
    batch: int,
    window: int,
    threads: int = 2,
    max_windows: int | None = None,
    seed: int = 0,
    engine: str = "reference",
) -> dict[str, Any]:
    """Run one TBPTT training step in this process; return timings and memory (MiB).

    ``engine``: ``"reference"`` (the filter itself) or a :class:`FusedFilter` engine name."""
    torch.set_num_threads(threads)
    dt = DTYPES[dtype]
    case = builtin_case(kind, dt, simulate_gpsdr(batch_size=batch, steps=steps, seed=seed, dtype=dt), BenchSettings())
    filt = case.filter if engine == "reference" else FusedFilter(case.filter, engine=engine, threads=threads)
    z, m0, p0 = case.measurements, case.initial_mean, case.initial_cov
    opt = torch.optim.Adam([p for p in case.filter.parameters() if p.requires_grad], lr=1e-3)
    n_win = (steps + window - 1) // window
    if max_windows is not None:
        n_win = min(n_win, max_windows)
    rss_after: list[float] = []
    belief = None
    probe = MemoryProbe().__enter__()  # resets the high-water mark after setup (data, imports)
    baseline = probe.baseline_mb
    t0 = time.perf_counter()
    for w in range(n_win):
        zw = z[:, w * window : (w + 1) * window]
        res = filt(zw, m0, p0) if belief is None else filt(zw, belief=belief)
        loss = -res.log_likelihood.mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        belief = detach_belief(res.final_belief)
        del res, loss
        rss_after.append(read_status_mb("VmRSS"))
    elapsed = time.perf_counter() - t0
    probe.__exit__(None, None, None)
    done = min(n_win * window, steps)
    return {
        "filter": kind,
        "engine": engine,
        "dtype": dtype,
        "T": steps,
        "B": batch,
        "W": window,
        "windows_run": n_win,
        "seconds": elapsed,
        "seconds_full_T": elapsed * steps / done,
        "steps_per_s": batch * done / elapsed,
        "baseline_mb": baseline,
        "peak_rss_mb": probe.peak_mb,
        "peak_above_baseline_mb": probe.extra_mb,
        "rss_after_first_window_mb": rss_after[0],
        "rss_after_last_window_mb": rss_after[-1],
    }


def measure_training_memory(*, timeout_s: float | None = None, **config: Any) -> dict[str, Any]:
    """:func:`training_step_memory` in a fresh Python process (keywords as there)."""
    args = [sys.executable, "-m", "experiments.benchmarks.memory"]
    for k, v in config.items():
        if v is not None:
            args += [f"--{k.replace('_', '-')}", str(v)]
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, env=env, cwd=root)
    if proc.returncode != 0:
        raise RuntimeError(f"memory subprocess failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", default="ukf", choices=["kf", "ekf", "ukf", "imm"])
    p.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--window", type=int, default=100)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--max-windows", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--engine", default="reference")
    a = p.parse_args()
    out = training_step_memory(
        kind=a.kind, dtype=a.dtype, steps=a.steps, batch=a.batch, window=a.window, threads=a.threads, max_windows=a.max_windows,
        seed=a.seed, engine=a.engine,
    )  # fmt: skip
    print(json.dumps(out))


if __name__ == "__main__":
    _main()
