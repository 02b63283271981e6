"""Timing of the parallel-in-time (associative-scan) Kalman filter and RTS smoother against the
sequential ones (``experiments/benchmark_parallel.py``), with dynamax's parallel filter and
smoother as the peer when JAX and dynamax are importable.

The sequential filter is timed twice: on the default path (a plain call under the engine policy
in force, ``auto`` unless ``DIFFFILTER_ENGINE`` says otherwise: on the CPU a call with
``B T >= 1e4``, or a filter's repeated calls, run the compiled engine; the row names the engine
that ran) and forced eager (the filter's own Python loop).  Every row times all implementations
in the same process on the same data and reports their log-likelihood differences, so a speed
figure never stands without the check that they computed the same thing.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from difffilter.engines.policy import last_engine, set_engine
from difffilter.filters import KalmanFilter, ParallelKalmanFilter
from difffilter.models import LinearModel
from difffilter.smoothers import ParallelRTSSmoother, RTSSmoother

__all__ = ["Row", "constant_velocity", "dynamax_available", "markdown", "measurements", "run_grid"]


@dataclass
class Row:
    """One timed ``(T, B, what)``: the sequential filter on the default path (the engine policy in
    force; ``engine`` names what ran the best repeat) and forced eager, the parallel filter, and
    dynamax's parallel filter; ``None`` where not timed."""

    steps: int
    batch: int
    what: str  # "filter", "filter fwd+bwd", "smoother"
    default_s: float | None
    engine: str  # the engine of the default path's best repeat ("generated", "eager"; "*": it changed during the repeats)
    eager_s: float | None
    parallel_s: float
    dynamax_s: float | None
    loglik_diff: float | None  # max |parallel - sequential| of the per-trajectory log-likelihoods
    dynamax_diff: tuple[float, float] | None  # max |parallel - dynamax| of those and of the filtered means


def constant_velocity(dtype: torch.dtype, device: str) -> LinearModel:
    """2-D constant-velocity model (n = 4, m = 2), dt = 0.1: the tracking workhorse."""
    dt = 0.1
    f = torch.eye(4, dtype=dtype)
    f[0, 2] = f[1, 3] = dt
    h = torch.zeros(2, 4, dtype=dtype)
    h[0, 0] = h[1, 1] = 1.0
    q1 = torch.tensor([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]], dtype=dtype)
    q = torch.zeros(4, 4, dtype=dtype)
    q[0::2, 0::2] = q1
    q[1::2, 1::2] = q1
    return LinearModel(F=f, H=h, Q=q, R=0.25 * torch.eye(2, dtype=dtype)).to(device)


def measurements(batch: int, steps: int, dtype: torch.dtype, device: str, seed: int = 0) -> torch.Tensor:
    """Noisy positions of random-walk-velocity trajectories ``[B, T, 2]`` (vectorised: no time loop)."""
    g = torch.Generator().manual_seed(seed)
    vel = torch.cumsum(0.3 * torch.randn(batch, steps, 2, generator=g, dtype=dtype), 1)
    pos = torch.cumsum(0.1 * vel, 1)
    return (pos + 0.5 * torch.randn(batch, steps, 2, generator=g, dtype=dtype)).to(device)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _time(fn: Callable[[], object], repeats: int, device: str) -> float:
    """Best of ``repeats`` wall-clock times (the caller has run ``fn`` once before as a warm-up)."""
    return min(_timed(fn, repeats, device))


def _timed(fn: Callable[[], object], repeats: int, device: str) -> list[float]:
    out = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - start)
    return out


def dynamax_available() -> bool:
    return importlib.util.find_spec("jax") is not None and importlib.util.find_spec("dynamax") is not None


def _fwd_bwd(filt: KalmanFilter, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor) -> None:
    """Forward, then the gradient of the negative log-likelihood with respect to Q and R."""
    loss = -filt(z, m0, p0).total_log_likelihood.sum()
    torch.autograd.grad(loss, list(filt.parameters()))


def _call(what: str, filt: KalmanFilter) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], object]:
    if what == "filter fwd+bwd":
        return partial(_fwd_bwd, filt)
    if what == "smoother":
        return ParallelRTSSmoother(filt) if isinstance(filt, ParallelKalmanFilter) else RTSSmoother(filt)
    return filt


def _default_path(
    what: str, model: LinearModel, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor, reps: int, device: str
) -> tuple[float, str]:
    """The sequential filter as a plain call runs it (engine policy in force): a fresh filter (the
    ``auto`` policy counts each filter's calls), one warm-up call (a kernel build, if any, is not
    timed), then the repeats; the engine of the best repeat, ``*`` when it changed between them."""
    filt = KalmanFilter(model)
    fn = partial(_call(what, filt), z, m0, p0)
    with torch.set_grad_enabled(what == "filter fwd+bwd"):
        fn()
        times, engines = [], []
        for _ in range(reps):
            times += _timed(fn, 1, device)
            engines.append(str(last_engine(filt)))
    best = min(range(reps), key=times.__getitem__)
    return times[best], engines[best] + ("*" if len(set(engines)) > 1 else "")


def _eager(what: str, model: LinearModel, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor, reps: int, device: str) -> float:
    filt = KalmanFilter(model)
    fn = partial(_call(what, filt), z, m0, p0)
    set_engine("eager")
    try:
        with torch.set_grad_enabled(what == "filter fwd+bwd"):
            return _time(fn, reps, device)
    finally:
        set_engine(None)


def run_grid(
    steps_list: list[int],
    batches: list[int],
    *,
    dtype: torch.dtype,
    device: str,
    max_elements: int,
    max_sequential: int,
    max_eager: int,
    backward: bool,
    smoother: bool,
    repeats: Callable[[int], int],
    peer: bool = True,
    peer_rows: tuple[str, ...] = ("filter",),
    peer_timeout_s: float = 1800.0,
    progress: Callable[[str], None] | None = None,
) -> tuple[list[Row], str]:
    """Rows for every ``(T, B)`` with ``B T <= max_elements``: the sequential filter on the default
    path up to ``B T <= max_sequential`` and forced eager up to ``B T <= max_eager`` (a Python loop
    over ``T``; not timed on another device than the CPU, where the default path is eager), the
    parallel filter, and dynamax's parallel filter when ``peer`` and it is importable (on the rows
    named in ``peer_rows``; each shape costs dynamax a JIT compilation, tens of seconds on a loaded
    CPU).  dynamax runs after the torch rows in a process of its own
    (:mod:`experiments.benchmarks.parallel_peer`), bounded by ``peer_timeout_s``.  Returns the rows
    and a description of the peer for the header."""
    rows: list[Row] = []
    model = constant_velocity(dtype, device)
    par = ParallelKalmanFilter(model)
    m0 = torch.zeros(4, dtype=dtype, device=device)
    p0 = torch.eye(4, dtype=dtype, device=device)
    whats = ["filter"] + (["filter fwd+bwd"] if backward else []) + (["smoother"] if smoother else [])
    use_peer = peer and dynamax_available()
    folder = Path(tempfile.mkdtemp(prefix="benchmark-parallel-peer-"))
    cells, means = [], {}
    for steps in steps_list:
        for batch in batches:
            elements = batch * steps
            if elements > max_elements:
                continue
            z = measurements(batch, steps, dtype, device)
            reps = repeats(elements)
            with torch.no_grad():
                out_p = par(z, m0, p0)  # also the warm-up
                ll_p = out_p.log_likelihood.sum(1)
                ll_s = KalmanFilter(model)(z, m0, p0).log_likelihood.sum(1) if elements <= max_sequential else None
            diff = None if ll_s is None else float((ll_s - ll_p).abs().max())
            name = f"z_{steps}_{batch}.npy"
            if use_peer:
                np.save(folder / name, z.cpu().numpy())
                cells.append({"file": name, "repeats": reps, "whats": [w for w in whats if w in peer_rows]})
                means[name] = (ll_p.cpu(), out_p.mean.detach().cpu())
            for what in whats:
                with torch.set_grad_enabled(what == "filter fwd+bwd"):
                    fn = partial(_call(what, par), z, m0, p0)
                    fn()
                    t_p = _time(fn, reps, device)
                t_d, engine = (None, "-")
                if elements <= max_sequential:
                    t_d, engine = _default_path(what, model, z, m0, p0, reps, device)
                t_e = _eager(what, model, z, m0, p0, reps, device) if elements <= max_eager and device == "cpu" else None
                rows.append(Row(steps, batch, what, t_d, engine, t_e, t_p, None, diff, None))
                if progress is not None:
                    progress(markdown(rows[-1:]).splitlines()[-1])
    about = "skipped (--no-peer)" if not peer else "not installed (no peer columns)"
    if use_peer:
        about = _run_peer(folder, model, dtype, device, cells, rows, means, peer_timeout_s)
    shutil.rmtree(folder, ignore_errors=True)
    return rows, about


def _run_peer(
    folder: Path, model: LinearModel, dtype: torch.dtype, device: str, cells: list, rows: list[Row], means: dict, timeout_s: float
) -> str:
    """dynamax in its own process over ``cells``; fills the rows' peer columns; the header text."""
    mats = {"F": model.dynamics.F, "H": model.measurement.H, "Q": model.dynamics.Q, "R": model.measurement.R}
    spec = {
        "device": device,
        "dtype": str(dtype).removeprefix("torch."),
        "cells": cells,
        "model": {k: v.detach().cpu().tolist() for k, v in mats.items()},
    }
    (folder / "spec.json").write_text(json.dumps(spec))
    script = Path(__file__).with_name("parallel_peer.py")
    note = ""
    try:
        done = subprocess.run([sys.executable, str(script), str(folder)], timeout=timeout_s, capture_output=True, text=True)
        if done.returncode != 0:
            note = f"; the peer process failed: {done.stderr.strip().splitlines()[-1][:200] if done.stderr.strip() else done.returncode}"
    except subprocess.TimeoutExpired:
        note = f"; the peer process stopped at its {timeout_s:.0f} s limit (rows without a dynamax time did not finish)"
    about_file = folder / "about.txt"
    about = (about_file.read_text() if about_file.exists() else "dynamax") + " (in a process of its own)" + note
    results = folder / "out.jsonl"
    for line in results.read_text().splitlines() if results.exists() else []:
        rec = json.loads(line)
        steps, batch = (int(x) for x in rec["cell"].removesuffix(".npy").split("_")[1:])
        row = next(r for r in rows if (r.steps, r.batch, r.what) == (steps, batch, rec["what"]))
        row.dynamax_s = rec["seconds"]
        if rec["what"] == "filter":
            ll_p, mean_p = means[rec["cell"]]
            ll_x = torch.as_tensor(np.load(folder / f"{rec['cell']}.ll.npy")).to(ll_p.dtype)
            mean_x = torch.as_tensor(np.load(folder / f"{rec['cell']}.mean.npy")).to(mean_p.dtype)
            row.dynamax_diff = (float((ll_x - ll_p).abs().max()), float((mean_x - mean_p).abs().max()))
    return about


def _s(x: float | None) -> str:
    return "-" if x is None else f"{x:.4f}"


def _ratio(a: float, b: float | None) -> str:
    return "-" if b is None else f"{a / b:.3g}"


def markdown(rows: list[Row]) -> str:
    """The rows as a markdown table; a ratio ``parallel / x`` < 1 means the scan is faster."""
    out = [
        "| T | B | what | sequential, default path [s] | its engine | sequential, eager [s] | parallel [s] | dynamax parallel [s] "
        "| parallel / default | parallel / eager | parallel / dynamax | loglik diff to sequential | diff to dynamax: loglik, mean |",
        "|---:|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        diffs = "-" if r.loglik_diff is None else f"{r.loglik_diff:.1e}"
        peer = "-" if r.dynamax_diff is None else f"{r.dynamax_diff[0]:.1e}, {r.dynamax_diff[1]:.1e}"
        out.append(
            f"| {r.steps} | {r.batch} | {r.what} | {_s(r.default_s)} | {r.engine} | {_s(r.eager_s)} | {r.parallel_s:.4f} "
            f"| {_s(r.dynamax_s)} | {_ratio(r.parallel_s, r.default_s)} | {_ratio(r.parallel_s, r.eager_s)} "
            f"| {_ratio(r.parallel_s, r.dynamax_s)} | {diffs} | {peer} |"
        )
    return "\n".join(out)
