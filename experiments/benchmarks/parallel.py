"""Timing of the parallel-in-time (associative-scan) Kalman filter and RTS smoother against the
sequential ones (``experiments/benchmark_parallel.py``), with dynamax's parallel filter as an
optional peer when JAX and dynamax are importable.

Every row times both implementations in the same process on the same data and reports their
log-likelihood difference, so a speed figure never stands without the check that both computed
the same thing.
"""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch

from difffilter.filters import KalmanFilter, ParallelKalmanFilter
from difffilter.models import LinearModel
from difffilter.smoothers import ParallelRTSSmoother, RTSSmoother

__all__ = ["Row", "constant_velocity", "dynamax_available", "markdown", "measurements", "run_grid"]


@dataclass
class Row:
    steps: int
    batch: int
    what: str  # "filter", "filter fwd+bwd", "smoother", "dynamax parallel filter"
    sequential_s: float | None
    parallel_s: float
    max_abs_loglik_diff: float | None


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
    """Best of ``repeats`` wall-clock times (the caller has run ``fn`` once before when it wants a
    warm-up: the first eager call costs no compilation, only allocator warm-up)."""
    best = float("inf")
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        best = min(best, time.perf_counter() - start)
    return best


def dynamax_available() -> bool:
    return importlib.util.find_spec("jax") is not None and importlib.util.find_spec("dynamax") is not None


def _dynamax_parallel(model: LinearModel, z: torch.Tensor, repeats: int) -> tuple[float, torch.Tensor]:
    """dynamax's associative-scan filter (``parallel_inference.lgssm_filter``) on the same data,
    vmapped over the batch and jitted (compile time excluded by the warm-up)."""
    import jax  # optional peer
    import jax.numpy as jnp
    from dynamax.linear_gaussian_ssm import parallel_inference
    from dynamax.linear_gaussian_ssm.inference import ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial

    jax.config.update("jax_enable_x64", z.dtype == torch.float64)
    a = lambda t: jnp.asarray(t.detach().cpu().numpy())  # noqa: E731
    f, h, q, r = (a(x) for x in (model.dynamics.F, model.measurement.H, model.dynamics.Q, model.measurement.R))
    n = f.shape[0]
    # dynamax's initial state is x_0 (updated by the first measurement); difffilter's x_{-1} is
    # predicted first: N(F m0, F P0 F^T + Q) with m0 = 0, P0 = I
    params = ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=jnp.zeros(n), cov=f @ f.T + q),
        dynamics=ParamsLGSSMDynamics(weights=f, bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)), cov=q),
        emissions=ParamsLGSSMEmissions(weights=h, bias=jnp.zeros(h.shape[0]), input_weights=jnp.zeros((h.shape[0], 0)), cov=r),
    )
    run = jax.jit(jax.vmap(lambda y: parallel_inference.lgssm_filter(params, y).marginal_loglik))
    ys = a(z)
    out = run(ys).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        run(ys).block_until_ready()
        best = min(best, time.perf_counter() - start)
    return best, torch.as_tensor(jax.device_get(out).copy())


def _fwd_bwd(filt: KalmanFilter, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor) -> None:
    """Forward, then the gradient of the negative log-likelihood with respect to Q and R."""
    loss = -filt(z, m0, p0).total_log_likelihood.sum()
    torch.autograd.grad(loss, list(filt.parameters()))


def run_grid(
    steps_list: list[int],
    batches: list[int],
    *,
    dtype: torch.dtype,
    device: str,
    max_elements: int,
    max_sequential: int,
    backward: bool,
    smoother: bool,
    repeats: Callable[[int], int],
) -> list[Row]:
    """Rows for every ``(T, B)`` with ``B T <= max_elements``; the sequential filter is timed only
    up to ``B T <= max_sequential`` (its time grows linearly in ``T`` through a Python loop)."""
    rows: list[Row] = []
    model = constant_velocity(dtype, device)
    seq, par = KalmanFilter(model), ParallelKalmanFilter(model)
    m0 = torch.zeros(4, dtype=dtype, device=device)
    p0 = torch.eye(4, dtype=dtype, device=device)
    for steps in steps_list:
        for batch in batches:
            if batch * steps > max_elements:
                continue
            z = measurements(batch, steps, dtype, device)
            reps = repeats(batch * steps)
            timed_seq = batch * steps <= max_sequential
            with torch.no_grad():
                ll_p = par(z, m0, p0).total_log_likelihood  # also the warm-up
                t_p = _time(partial(par, z, m0, p0), reps, device)
                t_s, diff = None, None
                if timed_seq:
                    ll_s = seq(z, m0, p0).total_log_likelihood
                    diff = float((ll_s - ll_p).abs().max())
                    t_s = _time(partial(seq, z, m0, p0), reps, device)
            rows.append(Row(steps, batch, "filter", t_s, t_p, diff))
            if backward:
                t_bs = _time(partial(_fwd_bwd, seq, z, m0, p0), reps, device) if timed_seq else None
                rows.append(Row(steps, batch, "filter fwd+bwd", t_bs, _time(partial(_fwd_bwd, par, z, m0, p0), reps, device), diff))
            if smoother:
                with torch.no_grad():
                    s_seq, s_par = RTSSmoother(seq), ParallelRTSSmoother(par)
                    t_ss = _time(partial(s_seq, z, m0, p0), reps, device) if timed_seq else None
                    rows.append(Row(steps, batch, "smoother", t_ss, _time(partial(s_par, z, m0, p0), reps, device), diff))
            if dynamax_available():
                t_d, ll_d = _dynamax_parallel(model, z, reps)
                rows.append(Row(steps, batch, "dynamax parallel filter", None, t_d, float((ll_d.to(ll_p.dtype) - ll_p.cpu()).abs().max())))
    return rows


def markdown(rows: list[Row]) -> str:
    """The rows as a markdown table; ``parallel / sequential`` < 1 means the scan is faster."""
    out = [
        "| T | B | what | sequential [s] | parallel [s] | parallel / sequential | max abs loglik diff |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        seq = "-" if r.sequential_s is None else f"{r.sequential_s:.4f}"
        ratio = "-" if r.sequential_s is None else f"{r.parallel_s / r.sequential_s:.2f}"
        diff = "-" if r.max_abs_loglik_diff is None else f"{r.max_abs_loglik_diff:.1e}"
        out.append(f"| {r.steps} | {r.batch} | {r.what} | {seq} | {r.parallel_s:.4f} | {ratio} | {diff} |")
    return "\n".join(out)
