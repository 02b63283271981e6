"""The benchmark proper: difffilter and its peers timed in the same run on the same data.

Every case is one ``(filter, library, dtype, batch size, mode)``; ``mode`` is ``forward``
(filter, no gradient) or ``fwd+bwd`` (filter, total log-likelihood, gradient w.r.t. the
learnable parameters: ``Q``/``R``, plus the IMM's transition and initial probabilities).
Throughput is trajectory-steps per second, ``B * T / seconds`` (best of the repeats); peak
memory is the rise of the resident set during the first timed call (:class:`MemoryProbe`).
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..filters import EKF, UKF, FusedFilter, KalmanFilter, MerweScaled
from ..filters.base import RecursiveFilter
from ..mixers import IMM
from .dynamax_peer import dynamax_available, prepare_dynamax
from .filterpy_peer import filterpy_available, run_filterpy
from .gpsdr import BenchData, make_cv_model, make_gpsdr_model, simulate_gpsdr
from .timing import time_callable

__all__ = ["BenchSettings", "BenchReport", "make_difffilter", "run_benchmark", "DTYPES", "MAIN_COLUMNS"]

DTYPES = {"float64": torch.float64, "float32": torch.float32}
MODES = ("forward", "fwd+bwd")
LIBRARIES = ("difffilter", "difffilter-fused", "dynamax", "filterpy")
MAIN_COLUMNS = [
    "filter",
    "library",
    "dtype",
    "B",
    "T",
    "mode",
    "seconds",
    "cpu_seconds",
    "steps_per_s",
    "us_per_step",
    "peak_mb",
    "compile_s",
    "repeats",
    "difffilter_over_peer",
    "difffilter_over_peer_cpu",
    "fused_over_peer",
    "fb_over_f",
    "note",
]


@dataclass
class BenchSettings:
    """What to run (the Hydra group ``benchmark`` maps onto these fields)."""

    filters: list[str] = field(default_factory=lambda: ["kf", "ekf", "ukf", "imm"])
    libraries: list[str] = field(default_factory=lambda: list(LIBRARIES))
    dtypes: list[str] = field(default_factory=lambda: ["float64", "float32"])
    batch_sizes: list[int] = field(default_factory=lambda: [1, 16, 256, 4096])
    steps: int = 500
    modes: list[str] = field(default_factory=lambda: ["forward", "fwd+bwd"])
    threads: int = 2
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
    fused_compile: bool = True

    def __post_init__(self) -> None:
        for name, allowed, got in (
            ("filters", ("kf", "ekf", "ukf", "imm"), self.filters),
            ("libraries", LIBRARIES, self.libraries),
            ("dtypes", tuple(DTYPES), self.dtypes),
            ("modes", MODES, self.modes),
        ):
            bad = [g for g in got if g not in allowed]
            if bad:
                raise ValueError(f"benchmark.{name}: unknown {bad}, choose from {list(allowed)}")


@dataclass
class BenchReport:
    rows: list[dict[str, Any]] = field(default_factory=list)
    agreement: list[dict[str, Any]] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    extra_tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


def make_difffilter(kind: str, dtype: torch.dtype, s: BenchSettings) -> RecursiveFilter:
    """The difffilter filter of case ``kind`` (``kf``, ``ekf``, ``ukf``, ``imm``)."""
    pts = MerweScaled(alpha=s.ukf_alpha, beta=s.ukf_beta, kappa=s.ukf_kappa)
    if kind == "kf":
        return KalmanFilter(make_cv_model(dtype=dtype))
    if kind == "ekf":
        return EKF(make_gpsdr_model(dtype=dtype, analytic_jacobian=s.ekf_analytic_jacobian))
    if kind == "ukf":
        return UKF(make_gpsdr_model(dtype=dtype), sigma_points=pts, redraw_after_predict=True)
    k = len(s.imm_q_scales)
    off = (1.0 - s.imm_stay_prob) / max(k - 1, 1)
    trans = torch.full((k, k), off, dtype=dtype) + torch.eye(k, dtype=dtype) * (s.imm_stay_prob - off)
    modes = [UKF(make_gpsdr_model(dtype=dtype, q_scale=q), sigma_points=pts, redraw_after_predict=True) for q in s.imm_q_scales]
    return IMM(modes, transition=trans, initial_probs=torch.full((k,), 1.0 / k, dtype=dtype), prob_floor=0.0)


def _inputs(kind: str, data: BenchData) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    if kind == "kf":
        return data.cv_measurements, data.cv_initial_mean, data.cv_initial_cov
    return data.measurements, data.initial_mean, data.initial_cov


def _torch_run(filt: RecursiveFilter, z: torch.Tensor, m0: torch.Tensor, p0: torch.Tensor, mode: str) -> Callable[[], np.ndarray]:
    params = [p for p in filt.parameters() if p.requires_grad]

    def forward() -> np.ndarray:
        with torch.no_grad():
            return filt(z, m0, p0).log_likelihood.sum(-1).double().numpy()

    def forward_backward() -> np.ndarray:
        for p in params:
            p.grad = None
        ll = filt(z, m0, p0).log_likelihood.sum(-1)
        (-ll.sum()).backward()
        return ll.detach().double().numpy()

    return forward if mode == "forward" else forward_backward


class _Bench:
    def __init__(self, s: BenchSettings, log: Callable[[str], None]) -> None:
        self.s, self.log = s, log
        self.report = BenchReport()
        self.base = simulate_gpsdr(batch_size=max(s.batch_sizes + [s.filterpy_trajectories]), steps=s.steps, seed=s.seed)
        self.peer_ok = {"difffilter": None, "difffilter-fused": None, "dynamax": dynamax_available(), "filterpy": filterpy_available()}
        for lib in s.libraries:
            if self.peer_ok[lib] is not None:
                self.message(f"skipping {lib}: {self.peer_ok[lib]}")
        self.filterpy_rate: dict[str, tuple[float, float, str]] = {}
        if s.xla_flags and "jax" not in sys.modules:
            os.environ.setdefault("XLA_FLAGS", s.xla_flags)  # only effective before jax is first imported

    def message(self, text: str) -> None:
        self.report.messages.append(text)
        self.log(text)

    def data(self, dtype: torch.dtype, batch: int, steps: int | None = None) -> BenchData:
        d = self.base.subset(batch)
        t = self.s.steps if steps is None else steps
        return BenchData(
            d.truth[:, : t + 1].to(dtype),
            d.measurements[:, :t].to(dtype),
            d.initial_mean.to(dtype),
            d.initial_cov.to(dtype),
            d.cv_measurements[:, :t].to(dtype),
            d.cv_initial_mean.to(dtype),
            d.cv_initial_cov.to(dtype),
        )

    def too_big(self, kind: str, lib: str, dname: str, batch: int, mode: str) -> bool:
        """Skip a case whose memory, extrapolated from the same case at a smaller batch, would
        exceed ``max_memory_mb`` (the fwd+bwd autograd graph grows like ``B * T``)."""
        prev = [r for r in self.report.rows if (r["filter"], r["library"], r["dtype"], r["mode"]) == (kind, lib, dname, mode)]
        prev = [r for r in prev if r["B"] < batch and math.isfinite(r["peak_mb"]) and r["peak_mb"] > 0]
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
        steps = kw.pop("steps", self.s.steps)
        r = {
            "filter": kind,
            "library": lib,
            "dtype": dname,
            "B": batch,
            "T": steps,
            "mode": mode,
            "seconds": seconds,
            "cpu_seconds": math.nan,
            "steps_per_s": batch * steps / seconds,
            "us_per_step": seconds / steps * 1e6,
            "peak_mb": math.nan,
            "compile_s": math.nan,
            "repeats": 1,
            "difffilter_over_peer": math.nan,
            "difffilter_over_peer_cpu": math.nan,
            "fused_over_peer": math.nan,
            "fb_over_f": math.nan,
            "note": "",
        }
        r.update(kw)
        self.report.rows.append(r)
        self.log(
            f"{kind:4s} {lib:10s} {dname} B={batch:<5d} {mode:8s} {r['steps_per_s']:12.0f} steps/s "
            f"{r['us_per_step']:10.1f} us/step  peak {r['peak_mb']:8.1f} MB {r['note']}"
        )
        return r

    # -- cases -------------------------------------------------------------------------------
    def run_difffilter(
        self, kind: str, dname: str, batch: int, mode: str, *, fused: bool = False
    ) -> tuple[dict[str, Any], np.ndarray] | None:
        """The reference filter (``fused=False``) or its compiled :class:`FusedFilter` twin;
        the fused row's ``compile_s`` is the first (compiling) call on the warm-up sequence."""
        dtype = DTYPES[dname]
        lib = "difffilter-fused" if fused else "difffilter"
        try:
            filt: Any = make_difffilter(kind, dtype, self.s)
            if fused:
                filt = FusedFilter(filt, compile=self.s.fused_compile)
        except (ImportError, TypeError, ValueError) as exc:
            self.message(f"skipping {lib} {kind}: {type(exc).__name__}: {exc}")
            return None
        if self.too_big(kind, lib, dname, batch, mode):
            return None
        z, m0, p0 = _inputs(kind, self.data(dtype, batch))
        warm = _torch_run(filt, z[:, : self.s.warmup_steps], m0, p0, mode)
        t0 = time.perf_counter()
        warm()  # the warm-up call, timed: for the fused step it is the compilation
        first_s = time.perf_counter() - t0
        tm = time_callable(_torch_run(filt, z, m0, p0, mode), min_time_s=self.s.min_time_s, max_repeats=self.s.max_repeats)
        note = "torch.compile'd fused step" if self.s.fused_compile else "fused step, eager (fused_compile=false)"
        kw: dict[str, Any] = {"compile_s": first_s, "note": note} if fused else {}
        r = self.row(kind, lib, dname, batch, mode, tm.best_s, cpu_seconds=tm.cpu_s, peak_mb=tm.peak_mb, repeats=tm.repeats, **kw)
        return r, tm.result

    def run_dynamax(self, kind: str, dname: str, batch: int, mode: str) -> tuple[dict[str, Any], np.ndarray] | None:
        if kind == "imm" or self.too_big(kind, "dynamax", dname, batch, mode):
            return None
        run = prepare_dynamax(
            kind, self.data(DTYPES[dname], batch), DTYPES[dname], "forward" if mode == "forward" else "backward",
            ukf_alpha=self.s.ukf_alpha, ukf_beta=self.s.ukf_beta, ukf_kappa=self.s.ukf_kappa,
        )  # fmt: skip
        tm = time_callable(run.run, min_time_s=self.s.min_time_s, max_repeats=self.s.max_repeats)
        note = "jax.jit(jax.vmap(...))" + ("" if mode == "forward" else " + jax.value_and_grad w.r.t. (Q, R)")
        r = self.row(
            kind,
            "dynamax",
            dname,
            batch,
            mode,
            tm.best_s,
            cpu_seconds=tm.cpu_s,
            peak_mb=tm.peak_mb,
            repeats=tm.repeats,
            compile_s=run.compile_s,
            note=note,
        )
        ll = np.asarray(tm.result.marginal_loglik, dtype=np.float64) if mode == "forward" else None
        return r, ll

    def run_filterpy(self, kind: str, dname: str, batch: int, mode: str) -> dict[str, Any] | None:
        if mode != "forward" or dname != "float64":
            return None
        if kind not in self.filterpy_rate:
            ntraj, steps = min(self.s.filterpy_trajectories, batch), min(self.s.filterpy_steps, self.s.steps)
            data = self.data(torch.float64, max(ntraj, 1), steps)
            kw = dict(
                ukf_alpha=self.s.ukf_alpha, ukf_beta=self.s.ukf_beta, ukf_kappa=self.s.ukf_kappa, imm_q_scales=tuple(self.s.imm_q_scales)
            )
            if kind == "imm":
                k = len(self.s.imm_q_scales)
                off = (1.0 - self.s.imm_stay_prob) / max(k - 1, 1)
                kw["imm_transition"] = np.full((k, k), off) + np.eye(k) * (self.s.imm_stay_prob - off)

            def go() -> np.ndarray:
                return run_filterpy(kind, data, num_trajectories=ntraj, steps=steps, **kw)

            def warm() -> np.ndarray:  # first calls import scipy's stats machinery
                return run_filterpy(kind, self.data(torch.float64, 1, 2), num_trajectories=1, steps=2, **kw)

            tm = time_callable(go, min_time_s=0.0, max_repeats=1, warmup=warm)
            note = f"Python loop; measured on {ntraj} traj x {steps} steps, extrapolated to B"
            self.filterpy_rate[kind] = (tm.best_s / (ntraj * steps), tm.cpu_s / (ntraj * steps), note)
            self.check_agreement(kind, "filterpy", dname, data, tm.result)
        per_step, cpu_per_step, note = self.filterpy_rate[kind]
        work = batch * self.s.steps
        return self.row(kind, "filterpy", dname, batch, mode, per_step * work, cpu_seconds=cpu_per_step * work, note=note)

    def check_agreement(
        self, kind: str, peer: str, dname: str, data: BenchData, peer_ll: np.ndarray, ours: np.ndarray | None = None
    ) -> None:
        z, m0, p0 = _inputs(kind, data)
        if ours is None:
            ours = _torch_run(make_difffilter(kind, DTYPES[dname], self.s), z, m0, p0, "forward")()
        diff = float(np.max(np.abs(ours - peer_ll)))
        scale = float(np.max(np.abs(ours)))
        entry = {
            "filter": kind,
            "peer": peer,
            "dtype": dname,
            "B": z.shape[0],
            "T": z.shape[1],
            "max_abs_diff": diff,
            "max_rel_diff": diff / scale,
        }
        self.report.agreement.append(entry)
        self.log(
            f"agreement {kind} difffilter vs {peer} ({dname}, B={z.shape[0]}, T={z.shape[1]}): "
            f"max |dlogL| = {diff:.3g} (rel {diff / scale:.2g})"
        )

    def run(self) -> BenchReport:
        s = self.s
        torch.set_num_threads(s.threads)
        for kind in s.filters:
            for dname in s.dtypes:
                for batch in sorted(s.batch_sizes):
                    fwd_time: dict[str, float] = {}
                    for mode in s.modes:
                        ours = self.run_difffilter(kind, dname, batch, mode) if "difffilter" in s.libraries else None
                        if ours is None and kind == "imm" and "difffilter" in s.libraries:
                            break
                        fused = None
                        if "difffilter-fused" in s.libraries and kind != "imm":
                            fused = self.run_difffilter(kind, dname, batch, mode, fused=True)
                            if fused is not None and ours is not None and mode == "forward":
                                self.check_agreement(kind, "difffilter-fused", dname, self.data(DTYPES[dname], batch), fused[1], ours[1])
                        for lib in ("dynamax", "filterpy"):
                            if lib not in s.libraries or self.peer_ok[lib] is not None:
                                continue
                            if lib == "dynamax":
                                out = self.run_dynamax(kind, dname, batch, mode)
                                peer_row = None if out is None else out[0]
                                if out is not None and out[1] is not None and ours is not None and batch == min(s.batch_sizes):
                                    self.check_agreement(kind, "dynamax", dname, self.data(DTYPES[dname], batch), out[1], ours[1])
                            else:
                                peer_row = self.run_filterpy(kind, dname, batch, mode)
                            if peer_row is not None and ours is not None:
                                peer_row["difffilter_over_peer"] = ours[0]["steps_per_s"] / peer_row["steps_per_s"]
                                peer_row["difffilter_over_peer_cpu"] = peer_row["cpu_seconds"] / ours[0]["cpu_seconds"]
                            if peer_row is not None and fused is not None:
                                peer_row["fused_over_peer"] = fused[0]["steps_per_s"] / peer_row["steps_per_s"]
                        for r in self.report.rows:
                            if (r["filter"], r["dtype"], r["B"]) == (kind, dname, batch):
                                if r["mode"] == "forward":
                                    fwd_time[r["library"]] = r["seconds"]
                                elif r["library"] in fwd_time:
                                    r["fb_over_f"] = r["seconds"] / fwd_time[r["library"]]
        return self.report


def run_benchmark(settings: BenchSettings, log: Callable[[str], None] = print) -> BenchReport:
    """Run every configured case and return the tables (see :mod:`difffilter.bench.report`)."""
    return _Bench(settings, log).run()
