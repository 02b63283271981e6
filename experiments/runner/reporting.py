"""What a run reports beyond its training curves: parameter summaries for result tables, and the
final results sent to every logger.

* :func:`parameter_summary` - a short text for a result table (a matrix becomes its diagonal's
  range, a long vector its range) and :func:`parameter_values` - the full values (for the CSV);
* :func:`log_results` - at the end of a run: the whole resolved config as hyperparameters with
  the final test metrics as their metrics (TensorBoard's HPARAMS tab compares runs and sweep
  members), the results table as text (TensorBoard) or as a file beside the logger's metrics
  (CSV), and the metrics as scalars.

(The per-epoch parameter scalars are the library's :func:`difffilter.learn.reporting.parameter_scalars`.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from difffilter.selection import match_parameters, parameter_owners

__all__ = ["flatten_config", "log_results", "parameter_summary", "parameter_values", "result_metrics"]


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def _describe(v: Tensor) -> str:
    """A short text for one constrained value (what a result table shows)."""
    if v.ndim == 0:
        return _fmt(float(v))
    if v.ndim >= 2 and v.shape[-1] == v.shape[-2]:
        diag = torch.diagonal(v, dim1=-2, dim2=-1).flatten()
        off = v - torch.diag_embed(torch.diagonal(v, dim1=-2, dim2=-1))
        tag = "diag" if not bool(off.abs().gt(0).any()) else "full, diag"
        if diag.numel() <= 4:
            return f"{tag}[{', '.join(_fmt(x) for x in diag.tolist())}]"
        return f"{tag} of {diag.numel()} in [{_fmt(float(diag.min()))}, {_fmt(float(diag.max()))}]"
    flat = v.flatten()
    if flat.numel() <= 4:
        return f"[{', '.join(_fmt(x) for x in flat.tolist())}]"
    return f"{flat.numel()} values in [{_fmt(float(flat.min()))}, {_fmt(float(flat.max()))}]"


def _values(filt: torch.nn.Module, names: Sequence[str]) -> list[tuple[str, Tensor]]:
    out = []
    owners = parameter_owners(filt)
    for pattern, hits in match_parameters(filt, list(names)).items():
        for name in hits:
            mod, attr, _ = owners[name]
            out.append((name if len(hits) > 1 else pattern, getattr(mod, attr).detach().to("cpu", torch.float64)))
    return out


def parameter_summary(filt: torch.nn.Module, names: Sequence[str]) -> str:
    """``"tau=[39.5, 41.7]; R=diag[92.2, 92.4]; Q=diag of 20 in [1e-9, 3.2]"``: the learnable values
    ``names`` of ``filt`` in a few characters each (a result table's ``parameters`` column)."""
    return "; ".join(f"{name}={_describe(v)}" for name, v in _values(filt, names))


def parameter_values(filt: torch.nn.Module, names: Sequence[str]) -> str:
    """The full values of :func:`parameter_summary` (nested lists, 6 significant digits), for the CSV."""

    def nested(x: Any) -> str:
        return "[" + ", ".join(nested(y) for y in x) + "]" if isinstance(x, list) else f"{x:.6g}"

    return "; ".join(f"{name}={nested(v.tolist())}" for name, v in _values(filt, names))


#: The pooled metrics of a results row that become hyperparameter metrics.
RESULT_METRICS = ("rmse_pos", "rmse_state", "anees", "nis", "nll")


def result_metrics(rows: Sequence[Mapping[str, Any]], metrics: Sequence[str] = RESULT_METRICS) -> dict[str, float]:
    """``{"results/<filter>/<metric>": value}`` of every finite metric of every results row."""
    out = {}
    for row in rows:
        for key in metrics:
            value = row.get(key)
            if isinstance(value, int | float) and math.isfinite(float(value)):
                out[f"results/{row['filter']}/{key}"] = float(value)
    return out


def flatten_config(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"model/_target_": ..., "optimizer/lr": 0.05, ...}``: a nested config as flat scalars
    (lists and ``None`` as text), what a hyperparameter table holds."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten_config(value, name))
        elif isinstance(value, bool | int | float | str):
            out[name] = value
        else:
            out[name] = str(value)
    return out


def log_results(loggers: Sequence[Any], *, config: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], text: str, step: int = 0) -> None:
    """Send a run's final results to every Lightning logger: the config as hyperparameters with
    :func:`result_metrics` as their metrics (TensorBoard: the HPARAMS tab; others: the metrics
    as values at ``step``), the results table ``text`` (TensorBoard: a text summary ``results``;
    loggers with a ``log_dir``: ``results.md`` there)."""
    params = flatten_config(config)
    metrics = result_metrics(rows)
    for logger in loggers:
        writer = getattr(logger, "experiment", None)
        if hasattr(writer, "add_text"):
            logger.log_hyperparams(params, metrics=metrics, step=step)
            writer.add_text("results", text, global_step=step)
        else:
            logger.log_hyperparams(params)
            logger.log_metrics(metrics, step=step)
            log_dir = getattr(logger, "log_dir", None)
            if log_dir:
                Path(log_dir).mkdir(parents=True, exist_ok=True)
                (Path(log_dir) / "results.md").write_text(text)
        logger.save()
