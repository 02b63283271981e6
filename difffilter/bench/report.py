"""Benchmark tables: target checks, markdown and CSV output."""

from __future__ import annotations

import csv
import math
import os
import platform
from importlib.metadata import version
from pathlib import Path
from typing import Any

import torch

from .runner import MAIN_COLUMNS, BenchReport

__all__ = ["environment_lines", "markdown_table", "summarize_targets", "write_report"]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return ""
        if v == 0 or 1e-3 <= abs(v) < 1e6:
            return f"{v:.4g}" if abs(v) < 100 else f"{v:.0f}"
        return f"{v:.3g}"
    return str(v)


def markdown_table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    """GitHub markdown table of ``rows`` (dicts) in the order of ``columns``."""
    if not rows:
        return "_(no rows)_\n"
    cols = columns or list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _find(rows: list[dict[str, Any]], **key: Any) -> dict[str, Any] | None:
    for r in rows:
        if all(r.get(k) == v for k, v in key.items()):
            return r
    return None


def summarize_targets(report: BenchReport, *, batch: int = 256, dtype: str = "float64", imm_modes: int = 2) -> list[dict[str, Any]]:
    """The project's performance targets, checked on the measured rows (float64, ``B = batch``)."""
    rows = report.rows
    out: list[dict[str, Any]] = []

    def add(name: str, value: float | None, target: str, ok: bool | None) -> None:
        out.append(
            {
                "target": name,
                "measured": math.nan if value is None else value,
                "goal": target,
                "met": "n/a" if ok is None else ("yes" if ok else "NO"),
            }
        )

    def best_ratio(r: dict[str, Any] | None) -> tuple[float | None, str]:
        """The faster difffilter variant's ratio to a peer row (fused when measured)."""
        if r is None:
            return None, "difffilter"
        cands = [(r.get("fused_over_peer", math.nan), "difffilter-fused"), (r["difffilter_over_peer"], "difffilter")]
        cands = [c for c in cands if c[0] is not None and not math.isnan(c[0])]
        return max(cands) if cands else (None, "difffilter")

    for kind, goal in (("ukf", 2.0), ("ekf", 1.0)):
        v, lib = best_ratio(_find(rows, filter=kind, library="dynamax", dtype=dtype, B=batch, mode="forward"))
        add(f"{kind.upper()} forward B={batch}: {lib} / dynamax throughput", v, f">= {goal:g}", None if v is None else v >= goal)
    for kind in ("kf", "ekf", "ukf", "imm"):
        v, lib = best_ratio(_find(rows, filter=kind, library="filterpy", dtype=dtype, B=batch, mode="forward"))
        add(f"{kind.upper()} forward B={batch}: {lib} / filterpy throughput", v, ">= 300", None if v is None else v >= 300)
    for kind in ("kf", "ekf", "ukf", "imm"):
        for lib in ("difffilter", "difffilter-fused"):
            r = _find(rows, filter=kind, library=lib, dtype=dtype, B=batch, mode="fwd+bwd")
            if r is None and lib == "difffilter-fused":
                continue
            v = None if r is None or math.isnan(r["fb_over_f"]) else r["fb_over_f"] - 1.0
            add(
                f"{kind.upper()} B={batch} {lib}: backward / forward time ((fwd+bwd) / fwd - 1)", v, "<= 3", None if v is None else v <= 3.0
            )
    imm = _find(rows, filter="imm", library="difffilter", dtype=dtype, B=batch, mode="forward")
    ukf = _find(rows, filter="ukf", library="difffilter", dtype=dtype, B=batch, mode="forward")
    v = None if imm is None or ukf is None else imm["seconds"] / (imm_modes * ukf["seconds"])
    add(f"IMM of {imm_modes} UKFs B={batch}: time / ({imm_modes} x UKF time)", v, "<= 1.2", None if v is None else v <= 1.2)
    return out


def environment_lines() -> list[str]:
    """Machine and library versions, load average (the timings depend on them)."""
    lines = [f"- python {platform.python_version()}, torch {torch.__version__} ({torch.get_num_threads()} threads), {os.cpu_count()} CPUs"]
    try:
        import jax  # noqa: PLC0415

        lines.append(f"- jax {jax.__version__}")
    except ImportError:
        pass
    for mod in ("dynamax", "filterpy"):
        try:
            lines.append(f"- {mod} {version(mod)}")
        except Exception:  # noqa: BLE001 - any metadata failure just omits the line
            pass
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
        if model:
            lines.append(f"- CPU: {model}")
    except OSError:
        pass
    try:
        lines.append(f"- load average (1, 5, 15 min) at report time: {os.getloadavg()}")
    except OSError:
        pass
    return lines


def _write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str] | None = None) -> None:
    cols = columns or list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow(r)


def write_report(
    report: BenchReport, outdir: str | os.PathLike[str], *, command: str = "", header: list[str] | None = None, **target_kw: Any
) -> str:
    """Write ``benchmark.csv``, ``agreement.csv``, ``targets.csv``, one CSV per extra table and
    ``results.md`` into ``outdir``; return the markdown."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    targets = summarize_targets(report, **target_kw)
    _write_csv(out / "benchmark.csv", report.rows, MAIN_COLUMNS)
    _write_csv(out / "agreement.csv", report.agreement, ["filter", "peer", "dtype", "B", "T", "max_abs_diff", "max_rel_diff"])
    _write_csv(out / "targets.csv", targets, ["target", "measured", "goal", "met"])
    md = ["# difffilter benchmark", ""]
    if command:
        md += [f"Command: `{command}`", ""]
    md += (header or []) + environment_lines() + [""]
    md += [
        "Throughput = trajectory-steps per second (B x T / best wall time). `difffilter_over_peer` = difffilter's "
        "throughput / the peer's in the same configuration (> 1: difffilter faster); `fused_over_peer` the same for "
        "`difffilter-fused` (`FusedFilter`, the compiled batch-last step; its `compile_s` is the first call). "
        "`fb_over_f` = forward+backward time / forward time of the same library. `cpu_seconds`: process CPU time "
        "of the best run (all threads; less sensitive than wall time to other processes on a shared machine), "
        "`difffilter_over_peer_cpu` the ratio on it. "
        "peak_mb = rise of the resident set (VmHWM) during the first timed call.",
        "",
    ]
    if report.messages:
        md += ["## Messages", ""] + [f"- {m}" for m in report.messages] + [""]
    md += ["## Targets", "", markdown_table(targets), "## Throughput and memory", "", markdown_table(report.rows, MAIN_COLUMNS)]
    md += ["## Log-likelihood agreement (same data, total log-likelihood per trajectory)", "", markdown_table(report.agreement)]
    for name, rows in report.extra_tables.items():
        _write_csv(out / f"{name}.csv", rows)
        md += [f"## {name}", "", markdown_table(rows)]
    text = "\n".join(md)
    (out / "results.md").write_text(text)
    return text
