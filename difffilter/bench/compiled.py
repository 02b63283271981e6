"""Eager vs ``torch.compile`` of one filter step (predict + update), driven by a Python time loop.

Compiling ``RecursiveFilter.forward`` itself would unroll the whole ``T``-step loop into one
graph (compile time grows with ``T``), so the experiment compiles the *step*: the same
``predict``/``update`` the filter's loop calls, on a belief dict, for a fixed batch size.  Both
variants run inside ``parametrize.cached()`` like ``forward`` does.  Graph breaks (e.g. the
data-dependent ``bool(...)`` in ``safe_cholesky``) are counted with ``torch._dynamo.explain``.
"""

from __future__ import annotations

import time
import traceback
from typing import Any

import torch
import torch._dynamo as dynamo
from torch.nn.utils import parametrize

from ..filters.base import RecursiveFilter
from .gpsdr import simulate_gpsdr
from .runner import DTYPES, BenchSettings, _inputs, make_difffilter

__all__ = ["compile_experiment"]


def _step_fn(filt: RecursiveFilter):  # type: ignore[no-untyped-def]
    def step(belief: dict[str, torch.Tensor], z: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        prior = filt.predict(belief, None)
        post, info = filt.update(prior, z, None, None)
        return filt.finalize_belief(post), info.log_likelihood

    return step


def _loop(filt, step, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor, backward: bool, params: list[torch.Tensor]) -> float:  # type: ignore[no-untyped-def]
    total = torch.zeros((), dtype=z.dtype)
    with torch.set_grad_enabled(backward), parametrize.cached():
        belief = filt.init_belief(m0.expand(z.shape[0], -1), p0.expand(z.shape[0], -1, -1))
        for t in range(z.shape[1]):
            belief, ll = step(belief, z[:, t])
            total = total + ll.sum()
    if backward:
        for p in params:
            p.grad = None
        (-total).backward()
    return float(total)


def compile_experiment(
    kind: str, *, batch: int, steps: int, dtype: str = "float64", mode: str = "default", seed: int = 0
) -> list[dict[str, Any]]:
    """Rows comparing ``filter.forward``, the eager step loop and the compiled step loop."""
    dt = DTYPES[dtype]
    s = BenchSettings()
    filt = make_difffilter(kind, dt, s)
    z, m0, p0 = _inputs(kind, simulate_gpsdr(batch_size=batch, steps=steps, seed=seed, dtype=dt))
    params = [p for p in filt.parameters() if p.requires_grad]
    rows: list[dict[str, Any]] = []

    def timed(fn) -> float:  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    def add(variant: str, fwd: float, fb: float, **kw: Any) -> None:
        rows.append(
            {
                "filter": kind,
                "dtype": dtype,
                "B": batch,
                "T": steps,
                "variant": variant,
                "forward_us_per_step": fwd / steps * 1e6,
                "fwd+bwd_us_per_step": fb / steps * 1e6,
                "compile_s": kw.get("compile_s", float("nan")),
                "graph_breaks": kw.get("graph_breaks", ""),
                "note": kw.get("note", ""),
            }
        )

    def fwd_module() -> None:
        with torch.no_grad():
            filt(z, m0, p0)

    def fb_module() -> None:
        for p in params:
            p.grad = None
        (-filt(z, m0, p0).log_likelihood.sum()).backward()

    fwd_module()
    add("filter.forward (eager)", min(timed(fwd_module) for _ in range(2)), min(timed(fb_module) for _ in range(2)))
    eager = _step_fn(filt)
    _loop(filt, eager, z, m0, p0, False, params)
    add(
        "step loop (eager)",
        min(timed(lambda: _loop(filt, eager, z, m0, p0, False, params)) for _ in range(2)),
        min(timed(lambda: _loop(filt, eager, z, m0, p0, True, params)) for _ in range(2)),
    )
    try:
        dynamo.reset()
        breaks = ""
        try:
            with parametrize.cached():
                expl = dynamo.explain(eager)(filt.init_belief(m0.expand(batch, -1), p0.expand(batch, -1, -1)), z[:, 0])
            breaks = f"{expl.graph_count} graphs, {expl.graph_break_count} breaks"
            dynamo.reset()
        except Exception as exc:  # noqa: BLE001 - explain is best-effort diagnostics
            breaks = f"explain failed: {type(exc).__name__}"
        compiled = torch.compile(eager, mode=mode, dynamic=False)
        t0 = time.perf_counter()
        _loop(filt, compiled, z[:, :2], m0, p0, False, params)
        _loop(filt, compiled, z[:, :2], m0, p0, True, params)
        compile_s = time.perf_counter() - t0
        fwd = min(timed(lambda: _loop(filt, compiled, z, m0, p0, False, params)) for _ in range(2))
        fb = min(timed(lambda: _loop(filt, compiled, z, m0, p0, True, params)) for _ in range(2))
        add(f"step loop (torch.compile mode={mode})", fwd, fb, compile_s=compile_s, graph_breaks=breaks)
    except Exception as exc:  # noqa: BLE001 - report any compiler failure instead of aborting the benchmark
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        add(f"step loop (torch.compile mode={mode})", float("nan"), float("nan"), note=f"FAILED: {tb[:300]}")
    return rows
