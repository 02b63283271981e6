"""Running the 2-D ranging protocol (:mod:`.protocol`) on a folder of libRSF recordings
and writing its report: ``<fold>/results.csv`` per fold (rows ``hand-tuned``, ``learned`` and
every baseline; columns ``pos_err_p50``, ``rmse_pos``, ``pos_err_p95``, the paired differences
to hand-tuned (``d_*``) and to the untrained gated filter (``u_*``) with their 95 % block-bootstrap
intervals), ``results.md``, ``summary.json``,
``learned_extras.png`` and TensorBoard events (``tb/``: training loss and validation score per
seed, the learned extras and the figure)."""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from matplotlib.figure import Figure
from torch.utils.tensorboard import SummaryWriter

from difffilter.datasets.ranging import RangingRecording, find_recordings, load_ranging

from .protocol import ProtocolResult, fold_pieces, run_fold

__all__ = ["extras", "fold_specs", "gate_curve", "plot_extras", "run_ranging", "write_csv"]

COLUMNS = (
    "filter",
    "pos_err_p50",
    "rmse_pos",
    "pos_err_p95",
    "d_median",
    "d_median_lo",
    "d_median_hi",
    "d_rms",
    "d_rms_lo",
    "d_rms_hi",
    "u_median",
    "u_median_lo",
    "u_median_hi",
    "u_rms",
    "u_rms_lo",
    "u_rms_hi",
)


def fold_specs(recordings: Sequence[RangingRecording], cfg: Mapping[str, Any]) -> dict[str, tuple[list[RangingRecording], dict[str, Any]]]:
    """``{fold name: (recordings, spec)}``: every block fold on every recording alone
    (``<name>/<fold>``) and, with several recordings and ``by_dataset``, one leave-one-out
    data-set fold per recording (``leave_out_<name>``)."""
    out: dict[str, tuple[list[RangingRecording], dict[str, Any]]] = {}
    for r in recordings:
        for f, spec in dict(cfg["folds"]).items():
            out[f"{r.name}/{f}"] = ([r], dict(spec))
    if len(recordings) > 1 and cfg.get("by_dataset", True):
        for r in recordings:
            others = [o.name for o in recordings if o.name != r.name]
            out[f"leave_out_{r.name}"] = (
                list(recordings),
                {"train_sets": others, "test_sets": [r.name], "val_fraction": float(cfg.get("val_fraction", 0.2))},
            )
    return out


def extras(filt: torch.nn.Module) -> dict[str, list[float]]:
    """The learned extras of a ranging EKF: range bias, noise scale (per anchor), gate
    threshold / floor / softness (a :class:`~difffilter.filters.GatedEKF`'s gate, else the
    measurement model's), odometry scale, process noise (absent ones left out)."""
    meas, dyn = filt.model.measurement, filt.model.dynamics
    out: dict[str, list[float]] = {}
    if getattr(meas, "bias_mode", None) is not None:
        out["range_bias"] = [float(v) for v in meas.range_bias.detach().reshape(-1)]
    if getattr(meas, "noise_mode", None) is not None:
        out["noise_scale"] = [float(v) for v in meas.noise_scale.detach().reshape(-1)]
    if hasattr(dyn, "odom_scale"):  # a 3-D recording without odometry has none
        out["odom_scale"] = [float(dyn.odom_scale.detach())]
    # process noise density: the odometry models' process_psd, the constant-velocity model's q (3-D without odometry)
    psd = dyn.process_psd if hasattr(dyn, "process_psd") else dyn.q
    out["process_psd"] = [float(v) for v in psd.detach().reshape(-1)]
    gate = getattr(filt, "gate", None) or getattr(meas, "gate", None)
    if gate is not None:
        out["gate_threshold"] = [float(torch.as_tensor(gate.threshold).detach())]
        out["gate_floor"] = [float(torch.as_tensor(gate.floor).detach())]
        if gate.soft:
            out["gate_softness"] = [float(gate.gate_softness.detach())]
    return out


def gate_curve(ex: Mapping[str, list[float]], n: torch.Tensor) -> torch.Tensor:
    """Variance factor ``f`` of a reject gate with the extras' threshold / softness against the
    normalised innovation ``n = |e| / sqrt(S + floor^2)``."""
    soft = ex.get("gate_softness", [0.0])[0]
    if soft <= 0:
        return torch.where(n > ex["gate_threshold"][0], torch.full_like(n, 1e6), torch.ones_like(n))
    return torch.exp(math.log(1e6) * torch.sigmoid((n - ex["gate_threshold"][0]) / soft))


def plot_extras(results: Mapping[str, ProtocolResult]) -> Figure:
    """One figure: range bias and noise scale per anchor (each fold's selection against the
    untrained 0 / 1), the gate's weight ``1 / f`` against the normalised innovation (untrained
    and learned), and test-error CDFs of hand-tuned vs learned."""
    fig = Figure(figsize=(16, 4.2), layout="constrained")
    ax = fig.subplots(1, 4)
    res = torch.linspace(0.0, 8.0, 321, dtype=torch.float64)
    for i, (fold, r) in enumerate(results.items()):
        ex, color = extras(r.learned), f"C{i % 10}"
        label = f"{fold} ({r.selected['candidate']})"
        if "range_bias" in ex:
            ax[0].plot(range(1, len(ex["range_bias"]) + 1), ex["range_bias"], "o-", color=color, label=label)
        if "noise_scale" in ex:
            ax[1].semilogy(range(1, len(ex["noise_scale"]) + 1), ex["noise_scale"], "o-", color=color)
        if "gate_threshold" in ex:
            ax[2].semilogy(res, 1.0 / gate_curve(ex, res), color=color)
        for row, style in (("hand-tuned", ":"), ("learned", "-")):
            e = torch.sort(r.errors[row]).values
            ax[3].plot(e, torch.linspace(0, 1, len(e)), style, color=color, label=label if row == "learned" else None)
    fell_back = [fold for fold, r in results.items() if r.selected["candidate"] == "hand-tuned"]
    if fell_back:  # those folds have no gate, bias or scale to draw: say so instead of an empty panel
        ax[0].text(
            0.02,
            0.02,
            "validation chose hand-tuned (no extras):\n" + "\n".join(fell_back),
            transform=ax[0].transAxes,
            fontsize=7,
            va="bottom",
        )
    first = next(iter(results.values()))
    ax[2].semilogy(res, 1.0 / gate_curve(extras(first.start), res), "k--", label="untrained gate")
    ax[0].axhline(0.0, color="k", ls="--", lw=0.8)
    ax[1].axhline(1.0, color="k", ls="--", lw=0.8)
    ax[0].set(xlabel="anchor", ylabel="m")
    ax[1].set(xlabel="anchor", ylabel="factor")
    ax[2].set(xlabel="normalised innovation |e| / sqrt(S + floor²)", ylabel="weight 1/f", ylim=(1e-6, 2))
    ax[3].set(xlabel="position error (m)", ylabel="fraction of test steps", xscale="log")
    titles = (
        "range bias per anchor (untrained: 0)",
        "noise scale on the file's variance (untrained: 1)",
        "gate weight vs normalised innovation (S = H P H^T + R)",
        "test error CDF (dotted: hand-tuned)",
    )
    for a, title in zip(ax, titles, strict=True):
        a.set_title(title, fontsize=9)
    ax[3].legend(fontsize=6, loc="lower right")
    ax[2].legend(fontsize=7)
    return fig


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """``rows`` as CSV with :data:`COLUMNS` (missing differences of the reference row left empty)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.6g}" if isinstance(r.get(k), float) else r.get(k, "")) for k in COLUMNS})


def _diff(row: Mapping[str, Any], stat: str, prefix: str = "d") -> str:
    if f"{prefix}_{stat}" not in row:
        return ""
    return f"{row[f'{prefix}_{stat}']:+.3f} [{row[f'{prefix}_{stat}_lo']:+.3f}, {row[f'{prefix}_{stat}_hi']:+.3f}]"


def _markdown(results: Mapping[str, ProtocolResult]) -> str:
    out = [
        "| fold | filter | p50 (m) | RMS (m) | p95 (m) | Δ p50 vs hand-tuned [95 % CI] | Δ RMS vs hand-tuned [95 % CI] "
        "| Δ p50 vs untrained gate [95 % CI] | Δ RMS vs untrained gate [95 % CI] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for fold, r in results.items():
        for row in r.rows:
            stats = f"{row['pos_err_p50']:.3f} | {row['rmse_pos']:.3f} | {row['pos_err_p95']:.3f}"
            diffs = " | ".join(_diff(row, stat, prefix) for prefix in ("d", "u") for stat in ("median", "rms"))
            out.append(f"| {fold} | {row['filter']} | {stats} | {diffs} |")
    out += [
        "",
        "| fold | selected | validation score (median + RMS, m): selected / untrained gate / hand-tuned "
        "| start position variance (m²) | seconds |",
        "|---|---|---|---|---|",
    ]
    for fold, r in results.items():
        s = r.selected
        scores = f"{s['val_score']:.3f} / {s['val_untrained']:.3f} / {s['val_hand_tuned']:.3f}"
        out.append(f"| {fold} | {s['candidate']} epoch {s['epoch']} | {scores} | {s['start_pos_var']:.2f} | {r.seconds:.0f} |")
    return "\n".join(out) + "\n"


def run_ranging(
    folder: str | Path | Sequence[str | Path], cfg: Mapping[str, Any], output_dir: str | Path, *, only: Sequence[str] | None = None
) -> dict[str, ProtocolResult]:
    """Every fold of :func:`fold_specs` on the recordings of ``folder`` (one folder or several;
    ``only``: these names); writes the report (module docstring) and returns ``{fold: result}``.

    Raises:
        ValueError: two folders hold recordings of the same name (the folds are named by them).
    """
    t0 = time.time()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    folders = [folder] if isinstance(folder, (str, Path)) else list(folder)
    found = [f for d in folders for f in find_recordings(d) if only is None or f[0] in only]
    if not found:
        raise ValueError(f"{folder}: no recording named {list(only or [])}")
    names = [f[0] for f in found]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        where = {n: [str(f[1]) for f in found if f[0] == n] for n in twice}
        raise ValueError(f"recordings of the same name in several folders: {where}; rename one (<name>_Input.txt)")
    recordings = [load_ranging(inp, gt, min_ranges=int(cfg.get("min_ranges", 1))) for _name, inp, gt in found]
    missing = [r.name for r in recordings if not bool((~torch.as_tensor(r.truth).isnan()).any())]
    if missing:
        raise ValueError(f"recordings without point2 ground truth cannot be scored: {missing}")
    writer = SummaryWriter(str(out / "tb"))
    results: dict[str, ProtocolResult] = {}
    for fold, (recs, spec) in fold_specs(recordings, cfg).items():
        log = lambda key, v, step, fold=fold: writer.add_scalar(f"{fold}/{key}", v, step)  # noqa: E731
        r = run_fold(fold_pieces(recs, spec), cfg, log=log)
        results[fold] = r
        write_csv(out / fold / "results.csv", r.rows)
        for key, vals in extras(r.learned).items():
            for j, v in enumerate(vals):
                writer.add_scalar(f"{fold}/extras/{key}{'' if len(vals) == 1 else f'_{j + 1}'}", v, 0)
    fig = plot_extras(results)
    fig.savefig(out / "learned_extras.png", dpi=110)
    writer.add_figure("learned_extras", fig)
    writer.close()
    (out / "results.md").write_text(_markdown(results))
    summary = {
        "folder": [str(d) for d in folders] if len(folders) > 1 else str(folders[0]),
        "recordings": [r.name for r in recordings],
        "issues": {r.name: r.issues for r in recordings},
        "config": json.loads(json.dumps(dict(cfg))),
        "folds": {
            f: {"rows": r.rows, "selected": r.selected, "extras": extras(r.learned), "seconds": r.seconds, "history": r.history}
            for f, r in results.items()
        },
        "seconds": time.time() - t0,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return results
