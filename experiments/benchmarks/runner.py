"""The benchmark proper: difffilter and its peers timed in the same run on the same data.

Every case is one ``(filter, library, dtype, batch size, mode)``; ``mode`` is ``forward``
(filter, no gradient) or ``train`` (the training step: the batch's total log-likelihood and its
gradient w.r.t. the trained parameters, see :mod:`.cases`).  Throughput is trajectory-steps per
second, ``B * T / seconds`` (best of the repeats); peak memory is the rise of the resident set
during the first timed call (:class:`~.timing.MemoryProbe`).
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from difffilter.engines import chosen_engine, last_engine

from .cases import BUILT_IN, BenchCase, CaseFactory, builtin_case, make_difffilter, torch_runner
from .dynamax_peer import dynamax_available
from .gpsdr import BenchData, simulate_gpsdr
from .peers import PeerRunner, filterpy_available
from .timing import time_callable

#: plain-call warm-up calls at most (a training loop's first steps, before the engine policy settles)
_POLICY_WARMUP_CALLS = 20
__all__ = ["BenchSettings", "BenchReport", "make_difffilter", "run_benchmark", "DTYPES", "MAIN_COLUMNS", "MODES"]

DTYPES = {"float64": torch.float64, "float32": torch.float32}
MODES = ("forward", "train")
LIBRARIES = ("difffilter", "difffilter-fused", "dynamax", "filterpy")
MAIN_COLUMNS = [
    "filter", "library", "dtype", "B", "T", "mode", "seconds", "cpu_seconds", "steps_per_s", "us_per_step", "peak_mb",
    "compile_s", "repeats", "difffilter_over_peer", "difffilter_over_peer_cpu", "fused_over_peer", "fb_over_f", "note",
]  # fmt: skip


@dataclass
class BenchSettings:
    """What to run (the Hydra group ``benchmark`` maps onto these fields)."""

    filters: list[str] = field(default_factory=lambda: ["kf", "ekf", "ukf", "imm"])
    libraries: list[str] = field(default_factory=lambda: list(LIBRARIES))
    dtypes: list[str] = field(default_factory=lambda: ["float64", "float32"])
    batch_sizes: list[int] = field(default_factory=lambda: [16, 256, 4096])
    steps: int = 500
    modes: list[str] = field(default_factory=lambda: list(MODES))
    threads: int = 2
    fused_threads: int | None = None  # FusedFilter(threads=...); None: the same as ``threads``
    fused_engine: str = "auto"  # FusedFilter(engine=...)
    max_batch: dict[str, int] = field(default_factory=dict)  # per filter kind, e.g. {p003: 256}
    steps_by_filter: dict[str, int] = field(default_factory=dict)  # per filter kind T, e.g. {p003: 100}
    seed: int = 0
    min_time_s: float = 2.0
    max_repeats: int = 5
    warmup_steps: int = 5
    ukf_alpha: float = 1.0
    ukf_beta: float = 2.0
    ukf_kappa: float = 0.0
    imm_q_scales: list[float] = field(default_factory=lambda: [1.0, 10.0])
    imm_stay_prob: float = 0.95
    ekf_analytic_jacobian: bool = True
    filterpy_trajectories: int = 2
    filterpy_steps: int = 500
    target_batch: int = 256
    max_memory_mb: float = 8000.0
    xla_flags: str = ""

    def __post_init__(self) -> None:
        for name, allowed, got in (
            ("libraries", LIBRARIES, self.libraries),
            ("dtypes", tuple(DTYPES), self.dtypes),
            ("modes", MODES, self.modes),
        ):
            bad = [g for g in got if g not in allowed]
            if bad:
                raise ValueError(f"benchmark.{name}: unknown {bad}, choose from {list(allowed)}")

    def steps_for(self, kind: str) -> int:
        return int(self.steps_by_filter.get(kind, self.steps))


@dataclass
class BenchReport:
    rows: list[dict[str, Any]] = field(default_factory=list)
    agreement: list[dict[str, Any]] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    extra_tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


class _Bench:
    def __init__(self, s: BenchSettings, cases: Mapping[str, CaseFactory], log: Callable[[str], None]) -> None:
        self.s, self.cases, self.log = s, dict(cases), log
        unknown = [k for k in s.filters if k not in BUILT_IN and k not in self.cases]
        if unknown:
            raise ValueError(f"benchmark.filters: unknown {unknown}, choose from {list(BUILT_IN) + sorted(self.cases)}")
        self.report = BenchReport()
        self.base = simulate_gpsdr(batch_size=max(s.batch_sizes + [s.filterpy_trajectories]), steps=s.steps, seed=s.seed)
        if s.xla_flags and "jax" not in sys.modules:
            os.environ.setdefault("XLA_FLAGS", s.xla_flags)  # only effective before jax is first imported
        self.peers = PeerRunner(s, self)
        for lib, why in (("dynamax", dynamax_available()), ("filterpy", filterpy_available())):
            if lib in s.libraries and why is not None:
                self.message(f"skipping {lib}: {why}")

    def message(self, text: str) -> None:
        self.report.messages.append(text)
        self.log(text)

    def data(self, dtype: torch.dtype, batch: int, steps: int | None = None) -> BenchData:
        """The first ``batch`` trajectories and ``steps`` steps of the GPS/DR data in ``dtype``."""
        d = self.base.subset(batch)
        t = self.s.steps if steps is None else steps
        return BenchData(
            d.truth[:, : t + 1].to(dtype), d.measurements[:, :t].to(dtype), d.initial_mean.to(dtype), d.initial_cov.to(dtype),
            d.cv_measurements[:, :t].to(dtype), d.cv_initial_mean.to(dtype), d.cv_initial_cov.to(dtype),
        )  # fmt: skip

    def case(self, kind: str, dname: str, batch: int) -> BenchCase:
        dtype = DTYPES[dname]
        if kind in BUILT_IN:
            return builtin_case(kind, dtype, self.data(dtype, batch), self.s)
        return self.cases[kind](dtype=dtype, batch=batch, steps=self.s.steps_for(kind), seed=self.s.seed)

    def too_big(self, kind: str, lib: str, dname: str, batch: int, mode: str) -> bool:
        """Skip a case whose memory, extrapolated from the same case at a smaller batch, would
        exceed ``max_memory_mb`` (a training step's autograd graph grows like ``B * T``)."""
        prev = [r for r in self.report.rows if (r["filter"], r["library"], r["dtype"], r["mode"]) == (kind, lib, dname, mode)]
        prev = [r for r in prev if r["B"] < batch and math.isfinite(r["peak_mb"]) and r["peak_mb"] > 0]
        if lib == "difffilter" and chosen_engine() != "eager":
            # a plain call that ran eagerly at a small batch says nothing of a large one, which the
            # engine policy compiles (small graphs); a compiled row bounds either
            prev = [r for r in prev if str(r["note"]).endswith("ran: generated")]
        if not prev:
            return False
        ref = max(prev, key=lambda r: r["B"])
        estimate = ref["peak_mb"] * batch / ref["B"]
        if estimate <= self.s.max_memory_mb:
            return False
        self.message(
            f"skipping {lib} {kind} {dname} B={batch} {mode}: needs ~{estimate:.0f} MB (extrapolated from B={ref['B']}), "
            f"over max_memory_mb={self.s.max_memory_mb:.0f}; see the TBPTT memory table for long sequences"
        )
        return True

    def row(self, kind: str, lib: str, dname: str, batch: int, mode: str, seconds: float, **kw: Any) -> dict[str, Any]:
        steps = kw.pop("steps", self.s.steps_for(kind))
        r: dict[str, Any] = {c: math.nan for c in MAIN_COLUMNS}
        r.update(filter=kind, library=lib, dtype=dname, B=batch, T=steps, mode=mode, seconds=seconds, repeats=1, note="")
        r.update(steps_per_s=batch * steps / seconds, us_per_step=seconds / steps * 1e6)
        r.update(kw)
        self.report.rows.append(r)
        self.log(
            f"{kind:4s} {lib:16s} {dname} B={batch:<5d} {mode:8s} {r['steps_per_s']:12.0f} steps/s "
            f"{r['us_per_step']:10.1f} us/step  peak {r['peak_mb']:8.1f} MB {r['note']}"
        )
        return r

    # -- difffilter ----------------------------------------------------------------------------
    def run_difffilter(
        self, kind: str, dname: str, batch: int, mode: str, *, fused: bool = False
    ) -> tuple[dict[str, Any], np.ndarray] | None:
        """The reference filter (``fused=False``) or :class:`FusedFilter`; the fused row's
        ``compile_s`` is its first call (on a short warm-up sequence), which builds its kernels."""
        lib = "difffilter-fused" if fused else "difffilter"
        if self.too_big(kind, lib, dname, batch, mode):
            return None
        case = self.case(kind, dname, batch)
        threads = self.s.fused_threads if self.s.fused_threads is not None else self.s.threads
        try:
            run = torch_runner(case, mode, fused=fused, threads=threads, engine=self.s.fused_engine)
        except (TypeError, ValueError) as exc:
            self.message(f"skipping {lib} {kind}: {type(exc).__name__}: {exc}")
            return None
        w = self.s.warmup_steps
        warm = BenchCase(case.filter, case.measurements[:, :w], case.initial_mean, case.initial_cov,
                         None if case.mask is None else case.mask[:, :w], _first_steps(case.controls, w))  # fmt: skip
        t0 = time.perf_counter()
        # the timed wrapper itself is warmed up: a fresh FusedFilter would trace and lower its
        # step again (seconds of Python) inside the first timed call
        torch_runner(warm, mode, runner=run.runner)()
        first_s = time.perf_counter() - t0
        if not fused and chosen_engine() != "eager":
            # A training loop calls one filter many times and the policy compiles once its calls add up
            # (DIFFFILTER_AUTO_MIN_TOTAL): warm up like such a loop, so any kernel build happens here and the
            # timed calls are the loop's steady state; the row's note names the engine that ran them.
            for _ in range(_POLICY_WARMUP_CALLS):
                run()
                if last_engine(case.filter) != "eager":
                    break
        tm = time_callable(run, min_time_s=self.s.min_time_s, max_repeats=self.s.max_repeats)
        kw: dict[str, Any] = {"note": f"plain call, DIFFFILTER_ENGINE={chosen_engine()} ran: {last_engine(case.filter)}"}
        if fused:
            ran = getattr(getattr(run, "runner", None), "last_engine", None)
            kw = {"compile_s": first_s, "note": f"FusedFilter(engine={self.s.fused_engine!r}, threads={threads}) ran: {ran}"}
        r = self.row(kind, lib, dname, batch, mode, tm.best_s, cpu_seconds=tm.cpu_s, peak_mb=tm.peak_mb, repeats=tm.repeats, **kw)
        return r, tm.result

    def check_agreement(self, kind: str, peer: str, dname: str, batch: int, steps: int, peer_ll: np.ndarray, ours: np.ndarray) -> None:
        diff = float(np.max(np.abs(ours - peer_ll)))
        scale = float(np.max(np.abs(ours)))
        self.report.agreement.append(
            {"filter": kind, "peer": peer, "dtype": dname, "B": batch, "T": steps, "max_abs_diff": diff, "max_rel_diff": diff / scale}
        )
        self.log(
            f"agreement {kind} difffilter vs {peer} ({dname}, B={batch}, T={steps}): max |dlogL| = {diff:.3g} (rel {diff / scale:.2g})"
        )

    def run(self) -> BenchReport:
        s = self.s
        torch.set_num_threads(s.threads)
        for kind in s.filters:
            for dname in s.dtypes:
                for batch in sorted(b for b in s.batch_sizes if b <= s.max_batch.get(kind, b)):
                    for mode in s.modes:
                        self.run_combination(kind, dname, batch, mode)
        return self.report

    def run_combination(self, kind: str, dname: str, batch: int, mode: str) -> None:
        s = self.s
        ours = self.run_difffilter(kind, dname, batch, mode) if "difffilter" in s.libraries else None
        fused = self.run_difffilter(kind, dname, batch, mode, fused=True) if "difffilter-fused" in s.libraries else None
        if fused is not None and ours is not None and mode == "forward":
            self.check_agreement(kind, "difffilter-fused", dname, batch, self.s.steps_for(kind), fused[1], ours[1])
        for peer_row in self.peers.run(kind, dname, batch, mode, None if ours is None else ours[1]):
            if ours is not None:
                peer_row["difffilter_over_peer"] = ours[0]["steps_per_s"] / peer_row["steps_per_s"]
                peer_row["difffilter_over_peer_cpu"] = peer_row["cpu_seconds"] / ours[0]["cpu_seconds"]
            if fused is not None:
                peer_row["fused_over_peer"] = fused[0]["steps_per_s"] / peer_row["steps_per_s"]
        if mode == "train":
            for r in self.report.rows:
                if (r["filter"], r["dtype"], r["B"], r["mode"]) == (kind, dname, batch, "train"):
                    fwd = [
                        f
                        for f in self.report.rows
                        if (f["filter"], f["dtype"], f["B"], f["library"], f["mode"]) == (kind, dname, batch, r["library"], "forward")
                    ]
                    if fwd:
                        r["fb_over_f"] = r["seconds"] / fwd[0]["seconds"]


def _first_steps(controls: Any, steps: int) -> Any:
    if controls is None:
        return None
    if isinstance(controls, torch.Tensor):
        return controls[:, :steps]
    return {k: v[:, :steps] for k, v in controls.items()}


def run_benchmark(
    settings: BenchSettings, log: Callable[[str], None] = print, *, cases: Mapping[str, CaseFactory] | None = None
) -> BenchReport:
    """Run every configured case and return the tables (see :mod:`experiments.benchmarks.report`);
    ``cases`` adds filter kinds beyond the built-in ones."""
    return _Bench(settings, cases or {}, log).run()
