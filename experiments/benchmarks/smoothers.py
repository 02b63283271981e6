"""Smoother speed beside its filter: same model, same data, same run as the filter benchmark.

Each case is ``(filter, dtype, B, mode)`` for difffilter's reference filters of the benchmark
(``kf``, ``ekf``, ``ukf``, ``imm``) and their smoothers (RTS; unscented RTS for the UKF; Kim's
smoother for the IMM).  ``forward`` times the filter alone and the filter followed by the
smoother without gradients; ``train`` times a training step, value and gradient w.r.t. the
learnable parameters (``Q``, ``R``; the IMM's probabilities) of the position mean squared error
against the truth, of the filtered and of the smoothed states respectively.  Times are the best
of the repeats, wall clock (``*_s``) and process CPU time (``*_cpu_s``, steadier on a shared
machine); ``smoother_over_filter`` is the time of filter + smoother over the filter's.

Where dynamax is among the benchmark's libraries, its smoother of the same filter (RTS,
extended RTS, unscented RTS; no IMM smoother) is timed on the same data and loss
(:func:`~.dynamax_peer.prepare_dynamax` with ``smoother=True``): ``dynamax_s`` and
``dynamax_cpu_s``, and ``smoother_over_dynamax`` (``_cpu``), dynamax's time over difffilter's
filter + smoother (> 1: difffilter faster).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch

from difffilter.smoothers import make_smoother

from .dynamax_peer import dynamax_available, prepare_dynamax
from .gpsdr import BenchData
from .runner import DTYPES, BenchSettings, make_difffilter
from .timing import time_callable

__all__ = ["SMOOTHER_COLUMNS", "run_smoother_benchmark"]

SMOOTHER_COLUMNS = [
    "filter", "smoother", "dtype", "B", "T", "mode", "filter_s", "smoother_s", "filter_steps_per_s", "smoother_steps_per_s",
    "smoother_over_filter", "filter_cpu_s", "smoother_cpu_s", "smoother_over_filter_cpu", "repeats",
    "dynamax_s", "dynamax_cpu_s", "smoother_over_dynamax", "smoother_over_dynamax_cpu",
]  # fmt: skip
MODES = ("forward", "train")
SMOOTHER_NAMES = {"kf": "RTS", "ekf": "extended RTS", "ukf": "unscented RTS", "imm": "Kim IMM"}


def _inputs(kind: str, data: BenchData) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]:
    if kind == "kf":
        return data.cv_measurements, data.cv_initial_mean, data.cv_initial_cov, [0, 2]
    return data.measurements, data.initial_mean, data.initial_cov, [0, 3]


def _case(kind: str, dtype: torch.dtype, data: BenchData, settings: BenchSettings, mode: str, smoothed: bool) -> Callable[[], Any]:
    filt = make_difffilter(kind, dtype, settings)
    smoother = make_smoother(filt) if smoothed else None
    z, m0, p0, pos = _inputs(kind, data)
    truth = data.truth[:, 1:, [0, 3]].to(dtype)
    params = [p for p in filt.parameters() if p.requires_grad]

    def run() -> Any:
        return filt(z, m0, p0) if smoother is None else smoother(z, m0, p0)

    def forward() -> Any:
        with torch.no_grad():
            return run().mean

    def train() -> Any:
        for p in params:
            p.grad = None
        loss = (run().mean[..., pos] - truth).square().mean()
        loss.backward()
        return loss.detach()

    return forward if mode == "forward" else train


def run_smoother_benchmark(
    settings: BenchSettings, cfg: dict[str, Any], data_for: Callable[[torch.dtype, int], BenchData], log: Callable[[str], None] = print
) -> list[dict[str, Any]]:
    """Rows of :data:`SMOOTHER_COLUMNS`, one per ``(filter, dtype, B, mode)`` of ``cfg``
    (``filters``, ``dtypes``, ``batch_sizes``, ``modes``; defaults from ``settings``);
    ``data_for(dtype, B)`` gives the benchmark's data."""
    filters = list(cfg.get("filters", ["kf", "ekf", "ukf"]))
    modes = list(cfg.get("modes", MODES))
    bad = [m for m in modes if m not in MODES] + [f for f in filters if f not in ("kf", "ekf", "ukf", "imm")]
    if bad:
        raise ValueError(f"benchmark.smoothers: unknown {bad}; filters from kf, ekf, ukf, imm and modes from {list(MODES)}")
    rows = []
    for kind in filters:
        for dname in cfg.get("dtypes", settings.dtypes):
            for batch in sorted(cfg.get("batch_sizes", settings.batch_sizes)):
                data = data_for(DTYPES[dname], int(batch))
                for mode in modes:
                    times = {}
                    for smoothed in (False, True):
                        fn = _case(kind, DTYPES[dname], data, settings, mode, smoothed)
                        # warmed up on the timed call itself: the default engine policy compiles only
                        # calls this large, and a training loss of the means needs its own reverse
                        # kernel, so a short warm-up would leave the kernel builds in the timed call
                        times[smoothed] = time_callable(fn, min_time_s=settings.min_time_s, max_repeats=settings.max_repeats, warmup=fn)
                    steps = data.measurements.shape[1]
                    f_s, s_s = times[False].best_s, times[True].best_s
                    row = {
                        "filter": kind, "smoother": SMOOTHER_NAMES[kind],
                        "dtype": dname, "B": int(batch), "T": steps, "mode": mode, "filter_s": f_s, "smoother_s": s_s,
                        "filter_steps_per_s": batch * steps / f_s, "smoother_steps_per_s": batch * steps / s_s,
                        "smoother_over_filter": s_s / f_s, "filter_cpu_s": times[False].cpu_s, "smoother_cpu_s": times[True].cpu_s,
                        "smoother_over_filter_cpu": times[True].cpu_s / times[False].cpu_s,
                        "repeats": min(times[False].repeats, times[True].repeats),
                        "dynamax_s": math.nan, "dynamax_cpu_s": math.nan, "smoother_over_dynamax": math.nan,
                        "smoother_over_dynamax_cpu": math.nan,
                    }  # fmt: skip
                    if kind != "imm" and "dynamax" in settings.libraries and dynamax_available() is None:
                        peer = prepare_dynamax(
                            kind, data, DTYPES[dname], mode, ukf_alpha=settings.ukf_alpha, ukf_beta=settings.ukf_beta,
                            ukf_kappa=settings.ukf_kappa, smoother=True,
                        )  # fmt: skip
                        dx = time_callable(peer.run, min_time_s=settings.min_time_s, max_repeats=settings.max_repeats)
                        row.update(
                            dynamax_s=dx.best_s, dynamax_cpu_s=dx.cpu_s, smoother_over_dynamax=dx.best_s / s_s,
                            smoother_over_dynamax_cpu=dx.cpu_s / times[True].cpu_s,
                        )  # fmt: skip
                        log(f"smoother {kind:4s} {dname} B={batch:<5d} {mode:8s} dynamax / difffilter: {row['smoother_over_dynamax']:.2f}x")
                    rows.append(row)
                    log(
                        f"smoother {kind:4s} {dname} B={batch:<5d} {mode:8s} filter {row['filter_steps_per_s']:11.0f} steps/s, "
                        f"filter+smoother {row['smoother_steps_per_s']:11.0f} steps/s ({row['smoother_over_filter']:.2f}x the time, "
                        f"{row['smoother_over_filter_cpu']:.2f}x the CPU time)"
                    )
    return rows
