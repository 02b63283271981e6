"""Thread-count sensitivity of a user's training step (issue 24 item 5, issue 26 item 4).

A 5-state coordinated-turn model with range and bearing (``FunctionalModel``), a UKF, Adam, as a
user writes it; each configuration is timed in the same process, alternating, and reported as
wall and CPU (user + system of this process) per step:

* ``torch threads``: torch's intra-op count the caller set (``torch.set_num_threads``);
* ``filter threads``: :func:`difffilter.threads.set_filter_threads` (``1``: the library's default,
  the filter's forward and backward passes run single-threaded; ``torch``: the library leaves
  torch's setting alone, as before the setting existed);
* ``runner``: ``eager`` (the UKF itself) or ``compiled`` (``FusedFilter``; its kernels are built or
  loaded before timing).

Usage: ``python experiments/benchmark_threads.py [--batch 64] [--steps 200] [--repeats 3]
[--runners eager,compiled] [--modes train,forward]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

import torch

from difffilter.engines import FusedFilter
from difffilter.filters import UKF
from difffilter.models import FunctionalModel
from difffilter.threads import set_filter_threads

D = torch.float64
DT = 0.1


def coordinated_turn(x: torch.Tensor) -> torch.Tensor:
    px, py, v, heading, rate = x.unbind(-1)
    return torch.stack([px + DT * v * torch.cos(heading), py + DT * v * torch.sin(heading), v, heading + DT * rate, rate], -1)


def range_bearing(x: torch.Tensor) -> torch.Tensor:
    return torch.stack([torch.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2), torch.atan2(x[..., 1], x[..., 0])], -1)


def make(batch: int, steps: int):
    model = FunctionalModel(
        f=coordinated_turn,
        h=range_bearing,
        Q=0.01 * torch.eye(5, dtype=D),
        R=torch.diag(torch.tensor([0.25, 1e-3], dtype=D)),
        angular_measurements=[1],
        Q_structure="diagonal",
        R_structure="diagonal",
    )
    g = torch.Generator().manual_seed(0)
    z = torch.randn(batch, steps, 2, dtype=D, generator=g) * 0.1 + torch.tensor([10.0, 0.5], dtype=D)
    return model, z, torch.tensor([10.0, 5.0, 1.0, 0.3, 0.05], dtype=D), torch.eye(5, dtype=D)


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--runners", default="eager,compiled")
    ap.add_argument("--modes", default="train,forward")
    args = ap.parse_args()
    default_threads = torch.get_num_threads()
    model, z, m0, p0 = make(args.batch, args.steps)
    ukf = UKF(model)
    runners = {"eager": ukf, "compiled": FusedFilter(ukf)}
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)

    def step(runner: torch.nn.Module, mode: str) -> None:
        if mode == "forward":
            with torch.no_grad():
                runner(z, m0, p0)
            return
        opt.zero_grad()
        (-runner(z, m0, p0).log_likelihood.mean()).backward()
        opt.step()

    configs = [
        (r, m, tt, ft)
        for r in args.runners.split(",")
        for m in args.modes.split(",")
        for tt in sorted({1, default_threads})
        for ft in (1, None)
        if not (tt == 1 and ft is None)  # one thread either way
    ]
    for r, m, *_ in configs:  # build or load kernels, fill caches
        step(runners[r], m)
    times: dict[tuple, list[tuple[float, float]]] = {c: [] for c in configs}
    for _ in range(args.repeats):
        for c in configs:
            r, m, tt, ft = c
            torch.set_num_threads(tt)
            set_filter_threads(ft)
            w0, c0 = time.perf_counter(), _cpu()
            step(runners[r], m)
            times[c].append((time.perf_counter() - w0, _cpu() - c0))
    torch.set_num_threads(default_threads)
    set_filter_threads(1)
    print(f"B={args.batch} T={args.steps} float64, {os.cpu_count()} CPUs, torch {torch.__version__}, median of {args.repeats}")
    print(f"{'runner':9s} {'mode':8s} {'torch thr':>9s} {'filter thr':>10s} {'wall ms':>9s} {'cpu ms':>9s} {'cpu / 1-thread':>14s}")
    med = {c: (sorted(w for w, _ in v)[len(v) // 2], sorted(x for _, x in v)[len(v) // 2]) for c, v in times.items()}
    for c in configs:
        r, m, tt, ft = c
        base = med.get((r, m, 1, 1), med[c])
        print(f"{r:9s} {m:8s} {tt:9d} {ft or 'torch':>10} {med[c][0] * 1e3:9.1f} {med[c][1] * 1e3:9.1f} {med[c][1] / base[1]:14.2f}")


if __name__ == "__main__":
    main()
