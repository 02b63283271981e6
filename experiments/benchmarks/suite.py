"""The whole benchmark suite from a config mapping (the ``benchmark`` Hydra group)."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Mapping
from typing import Any

from omegaconf import OmegaConf

from .cases import CaseFactory
from .compiled import compile_costs
from .memory import measure_training_memory
from .report import write_report
from .runner import BenchSettings, _Bench, run_benchmark
from .smoothers import run_smoother_benchmark

__all__ = ["run_suite", "settings_from_config"]


def _plain(cfg: Any) -> Any:
    if OmegaConf.is_config(cfg):
        return OmegaConf.to_container(cfg, resolve=True)
    return cfg


def settings_from_config(cfg: Mapping[str, Any]) -> BenchSettings:
    """:class:`BenchSettings` from the group's keys (``compile``/``memory``/``smoothers`` sections ignored)."""
    names = {f.name for f in dataclasses.fields(BenchSettings)}
    sections = {"compile", "memory", "smoothers"}
    unknown = set(cfg) - names - sections
    if unknown:
        raise ValueError(f"unknown benchmark settings {sorted(unknown)}; known: {sorted(names | sections)}")
    return BenchSettings(**{k: v for k, v in cfg.items() if k in names})


def run_suite(
    cfg: Mapping[str, Any],
    outdir: str | os.PathLike[str],
    *,
    command: str = "",
    log: Callable[[str], None] = print,
    cases: Mapping[str, CaseFactory] | None = None,
) -> str:
    """Run the throughput cases (``cases`` adds filter kinds beyond the built-in ones), then the
    compile-cost, smoother and memory sections if enabled; write the report into ``outdir`` and
    return its markdown."""
    cfg = dict(_plain(cfg))
    settings = settings_from_config(cfg)
    report = run_benchmark(settings, log=log, cases=cases)
    comp = cfg.get("compile") or {}
    if comp.get("enabled"):
        rows: list[dict[str, Any]] = []
        for kind in comp.get("filters", ["ukf"]):
            for engine in comp.get("engines", ["generated"]):
                log(f"first-call cost: {kind}, engine {engine}")
                try:
                    rows += compile_costs(
                        kind, engine=engine, dtype=comp.get("dtype", "float64"), batch=int(comp.get("batch_size", 256)),
                        steps=int(comp.get("steps", 20)), threads=int(comp.get("threads", 1)), timeout_s=comp.get("timeout_s"),
                    )  # fmt: skip
                except Exception as exc:  # noqa: BLE001 - one failed engine must not lose the others
                    rows.append({"filter": kind, "engine": engine, "error": f"{type(exc).__name__}: {exc}"[:300]})
                log(f"  -> {rows[-1]}")
        report.extra_tables["compile"] = rows
    smo = cfg.get("smoothers") or {}
    if smo.get("enabled"):
        log("smoothers beside their filters")
        bench = _Bench(settings, cases or {}, log=lambda s: None)  # the throughput cases' data: same trajectories
        largest = bench.base.measurements.shape[0]
        if max(smo.get("batch_sizes", settings.batch_sizes)) > largest:
            raise ValueError(f"benchmark.smoothers.batch_sizes must not exceed the largest benchmark batch size ({largest})")
        report.extra_tables["smoothers"] = run_smoother_benchmark(settings, smo, lambda dt, b: bench.data(dt, b), log=log)
    mem = cfg.get("memory") or {}
    if mem.get("enabled"):
        rows = []
        for c in mem.get("configs", []):
            log(f"TBPTT memory: {c}")
            try:
                rows.append(
                    measure_training_memory(
                        kind=c["kind"],
                        dtype=c.get("dtype", "float64"),
                        steps=int(c.get("steps", mem.get("steps", 5000))),
                        batch=int(c.get("batch", mem.get("batch", 1024))),
                        window=int(c["window"]),
                        threads=settings.threads,
                        max_windows=c.get("max_windows", mem.get("max_windows")),
                        timeout_s=mem.get("timeout_s"),
                        engine=c.get("engine", "reference"),
                    )  # fmt: skip
                )
            except Exception as exc:  # noqa: BLE001 - one failed configuration must not lose the others
                rows.append(
                    {
                        "filter": c["kind"],
                        "dtype": c.get("dtype"),
                        "W": c["window"],
                        "error": f"{type(exc).__name__}: {exc}"[:300],
                        "peak_rss_mb": math.nan,
                    }
                )
            log(f"  -> {rows[-1]}")
        report.extra_tables["memory"] = rows
    return write_report(report, outdir, command=command, batch=settings.target_batch)
