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
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch

from difffilter.engines.policy import last_engine, set_engine
from difffilter.filters import KalmanFilter, ParallelKalmanFilter
from difffilter.models import LinearModel
from difffilter.smoothers import ParallelRTSSmoother, RTSSmoother

__all__ = ["Row", "constant_velocity", "dynamax_available", "jax_setup", "markdown", "measurements", "run_grid"]


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


def jax_setup(device: str) -> str:
    """Import JAX for the peer (on the CPU: its CPU backend) and describe it for the table's header.

    XLA keeps its own thread pool (``XLA_FLAGS`` as set by the caller): the single-thread flags
    ``--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1`` deadlocked this
    benchmark with jax 0.10.2 (as they did ``experiments/benchmark.py``'s, conf/benchmark/full.yaml)."""
    import jax  # optional peer

    if device == "cpu":
        jax.config.update("jax_platforms", "cpu")
    import dynamax

    flags = os.environ.get("XLA_FLAGS", "")
    pool = f"XLA_FLAGS={flags!r}" if flags else "XLA's default thread pool"
    return f"jax {jax.__version__} on {jax.default_backend()} ({jax.devices()[0].device_kind}), dynamax {dynamax.__version__}, {pool}"


class _Dynamax:
    """dynamax's associative-scan filter and smoother (``parallel_inference.lgssm_filter`` /
    ``lgssm_smoother``) on the same model and data, vmapped over the batch and jitted (compile time
    excluded by a warm-up); ``fwd+bwd`` is ``jax.grad`` of the summed log-likelihood with
    respect to ``Q`` and ``R``, as the torch rows differentiate with respect to their parameters."""

    def __init__(self, model: LinearModel, dtype: torch.dtype) -> None:
        import jax  # optional peer
        import jax.numpy as jnp
        from dynamax.linear_gaussian_ssm import parallel_inference
        from dynamax.linear_gaussian_ssm.inference import ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial

        jax.config.update("jax_enable_x64", dtype == torch.float64)
        self.jax = jax
        a = lambda t: jnp.asarray(t.detach().cpu().numpy())  # noqa: E731
        f, h, q, r = (a(x) for x in (model.dynamics.F, model.measurement.H, model.dynamics.Q, model.measurement.R))
        n, m = f.shape[0], h.shape[0]

        def params(q: object, r: object) -> ParamsLGSSM:
            # dynamax's initial state is x_0 (updated by the first measurement); difffilter's
            # x_{-1} is predicted first: N(F m0, F P0 F^T + Q) with m0 = 0, P0 = I
            return ParamsLGSSM(
                initial=ParamsLGSSMInitial(mean=jnp.zeros(n), cov=f @ f.T + q),
                dynamics=ParamsLGSSMDynamics(weights=f, bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)), cov=q),
                emissions=ParamsLGSSMEmissions(weights=h, bias=jnp.zeros(m), input_weights=jnp.zeros((m, 0)), cov=r),
            )

        def loglik(q: object, r: object, ys: object) -> object:
            return jax.vmap(lambda y: parallel_inference.lgssm_filter(params(q, r), y).marginal_loglik)(ys)

        def filtered(ys: object) -> object:
            post = jax.vmap(lambda y: parallel_inference.lgssm_filter(params(q, r), y))(ys)
            return post.marginal_loglik, post.filtered_means

        self.q, self.r = q, r
        self.filter = jax.jit(filtered)
        self.grad = jax.jit(jax.grad(lambda q, r, ys: loglik(q, r, ys).sum(), argnums=(0, 1)))
        self.smoother = jax.jit(jax.vmap(lambda y: parallel_inference.lgssm_smoother(params(q, r), y).smoothed_means))

    def time(self, what: str, z: torch.Tensor, repeats: int) -> tuple[float, tuple[torch.Tensor, torch.Tensor] | None]:
        """Best time of ``what`` on ``z [B, T, m]``; for ``"filter"`` also the log-likelihoods
        ``[B]`` and the filtered means ``[B, T, n]``."""
        ys = self.jax.device_put(z.detach().cpu().numpy())
        fn = {
            "filter": lambda: self.filter(ys),
            "filter fwd+bwd": lambda: self.grad(self.q, self.r, ys),
            "smoother": lambda: self.smoother(ys),
        }[what]
        out = self.jax.block_until_ready(fn())  # compiles
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            self.jax.block_until_ready(fn())
            best = min(best, time.perf_counter() - start)
        if what != "filter":
            return best, None
        ll, means = (torch.as_tensor(self.jax.device_get(x).copy()) for x in out)
        return best, (ll, means)


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
) -> list[Row]:
    """Rows for every ``(T, B)`` with ``B T <= max_elements``: the sequential filter on the default
    path up to ``B T <= max_sequential`` and forced eager up to ``B T <= max_eager`` (a Python loop
    over ``T``; not timed on another device than the CPU, where the default path is eager), the
    parallel filter, and dynamax's parallel filter when ``peer`` and it is importable (on the
    rows named in ``peer_rows``: each shape costs dynamax a JIT compilation, tens of seconds on
    a loaded CPU)."""
    rows: list[Row] = []
    model = constant_velocity(dtype, device)
    par = ParallelKalmanFilter(model)
    m0 = torch.zeros(4, dtype=dtype, device=device)
    p0 = torch.eye(4, dtype=dtype, device=device)
    whats = ["filter"] + (["filter fwd+bwd"] if backward else []) + (["smoother"] if smoother else [])
    peer_runner = _Dynamax(model, dtype) if peer and dynamax_available() else None
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
            for what in whats:
                with torch.set_grad_enabled(what == "filter fwd+bwd"):
                    fn = partial(_call(what, par), z, m0, p0)
                    fn()
                    t_p = _time(fn, reps, device)
                t_d, engine = (None, "-")
                if elements <= max_sequential:
                    t_d, engine = _default_path(what, model, z, m0, p0, reps, device)
                t_e = _eager(what, model, z, m0, p0, reps, device) if elements <= max_eager and device == "cpu" else None
                t_x, dx = None, None
                if peer_runner is not None and what in peer_rows:
                    t_x, check = peer_runner.time(what, z, reps)
                    if check is not None:
                        dx = (float((check[0].to(ll_p.dtype) - ll_p.cpu()).abs().max()), float((check[1] - out_p.mean.cpu()).abs().max()))
                rows.append(Row(steps, batch, what, t_d, engine, t_e, t_p, t_x, diff, dx))
    return rows


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
