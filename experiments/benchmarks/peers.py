"""The peer libraries' rows: dynamax (``jax.jit`` over ``jax.vmap``; ``value_and_grad`` for the
training step) and filterpy (a Python loop per trajectory, forward only, extrapolated)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from .dynamax_peer import dynamax_available, prepare_dynamax
from .filterpy_peer import filterpy_available, run_filterpy
from .timing import time_callable

__all__ = ["PeerRunner", "filterpy_available"]

DYNAMAX_KINDS = ("kf", "ekf", "ukf")
FILTERPY_KINDS = ("kf", "ekf", "ukf", "imm")


class PeerRunner:
    """Runs the peers of one case of a :class:`~.runner._Bench` (which owns data and rows)."""

    def __init__(self, settings: Any, bench: Any) -> None:
        self.s, self.bench = settings, bench
        self.ok = {"dynamax": dynamax_available() is None, "filterpy": filterpy_available() is None}
        self.filterpy_rate: dict[str, tuple[float, float, str]] = {}

    def run(self, kind: str, dname: str, batch: int, mode: str, ours: np.ndarray | None) -> Iterator[dict[str, Any]]:
        """Peer rows of this case (``ours``: difffilter's per-trajectory log-likelihood, for the
        agreement check)."""
        s = self.s
        if "dynamax" in s.libraries and self.ok["dynamax"] and kind in DYNAMAX_KINDS:
            out = self.run_dynamax(kind, dname, batch, mode)
            if out is not None:
                row, ll = out
                if ll is not None and ours is not None and batch == min(s.batch_sizes):
                    self.bench.check_agreement(kind, "dynamax", dname, batch, s.steps, ll, ours)
                yield row
        if "filterpy" in s.libraries and self.ok["filterpy"] and kind in FILTERPY_KINDS and mode == "forward" and dname == "float64":
            yield self.run_filterpy(kind, dname, batch, mode)

    def run_dynamax(self, kind: str, dname: str, batch: int, mode: str) -> tuple[dict[str, Any], np.ndarray | None] | None:
        if self.bench.too_big(kind, "dynamax", dname, batch, mode):
            return None
        dtype = self.bench_dtype(dname)
        run = prepare_dynamax(
            kind, self.bench.data(dtype, batch), dtype, mode,
            ukf_alpha=self.s.ukf_alpha, ukf_beta=self.s.ukf_beta, ukf_kappa=self.s.ukf_kappa,
        )  # fmt: skip
        tm = time_callable(run.run, min_time_s=self.s.min_time_s, max_repeats=self.s.max_repeats)
        note = "jax.jit(jax.vmap(...))" + ("" if mode == "forward" else " + jax.value_and_grad w.r.t. log diag R")
        row = self.bench.row(
            kind, "dynamax", dname, batch, mode, tm.best_s, cpu_seconds=tm.cpu_s, peak_mb=tm.peak_mb, repeats=tm.repeats,
            compile_s=run.compile_s, note=note,
        )  # fmt: skip
        ll = np.asarray(tm.result.marginal_loglik, dtype=np.float64) if mode == "forward" else None
        return row, ll

    @staticmethod
    def bench_dtype(dname: str) -> torch.dtype:
        return torch.float64 if dname == "float64" else torch.float32

    def run_filterpy(self, kind: str, dname: str, batch: int, mode: str) -> dict[str, Any]:
        s = self.s
        if kind not in self.filterpy_rate:
            ntraj, steps = min(s.filterpy_trajectories, batch), min(s.filterpy_steps, s.steps)
            data = self.bench.data(torch.float64, max(ntraj, 1), steps)
            kw: dict[str, Any] = {
                "ukf_alpha": s.ukf_alpha,
                "ukf_beta": s.ukf_beta,
                "ukf_kappa": s.ukf_kappa,
                "imm_q_scales": tuple(s.imm_q_scales),
            }
            if kind == "imm":
                k = len(s.imm_q_scales)
                off = (1.0 - s.imm_stay_prob) / max(k - 1, 1)
                kw["imm_transition"] = np.full((k, k), off) + np.eye(k) * (s.imm_stay_prob - off)

            def go() -> np.ndarray:
                return run_filterpy(kind, data, num_trajectories=ntraj, steps=steps, **kw)

            def warm() -> np.ndarray:  # first calls import scipy's stats machinery
                return run_filterpy(kind, self.bench.data(torch.float64, 1, 2), num_trajectories=1, steps=2, **kw)

            tm = time_callable(go, min_time_s=0.0, max_repeats=1, warmup=warm)
            note = f"Python loop; measured on {ntraj} traj x {steps} steps, extrapolated to B"
            self.filterpy_rate[kind] = (tm.best_s / (ntraj * steps), tm.cpu_s / (ntraj * steps), note)
            case = self.bench.case(kind, "float64", max(ntraj, 1))
            cut = type(case)(case.filter, case.measurements[:, :steps], case.initial_mean, case.initial_cov)
            with torch.no_grad():
                ours = cut.run(cut.filter).log_likelihood.sum(-1).double().numpy()
            self.bench.check_agreement(kind, "filterpy", dname, ntraj, steps, tm.result, ours)
        per_step, cpu_per_step, note = self.filterpy_rate[kind]
        work = batch * s.steps
        return self.bench.row(kind, "filterpy", dname, batch, mode, per_step * work, cpu_seconds=cpu_per_step * work, note=note)
