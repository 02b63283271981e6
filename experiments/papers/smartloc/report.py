"""Running the real-data protocol end to end and writing its report (``experiments/realdata.py``).

:func:`run_protocol` trains every (fold, variant, seed), selects on validation
(:mod:`experiments.papers.smartloc.protocol`), evaluates the test blocks and writes to the output
folder: ``results.md`` (tables), ``<fold>/results.csv`` (rows ``hand-tuned``, ``learned`` (the
first variant's selection), the other variants' ``learned-<variant>``, ``untrained-gate`` (the
first variant's gated filter at its untrained start) and the baselines ``ekf-no-gate``,
``snapshot-wls``, ``sage-husa``, ``vb-adaptive-r``; columns ``pos_err_p50``, ``rmse_pos``,
``pos_err_p95`` and the paired differences to hand-tuned ``d_*`` and to the untrained gated
filter ``u_*``, as the 2-D ranging protocol writes them), ``summary.json`` (numbers, selections, learned values),
``selected.pt`` (what :func:`run_transfer` needs to rebuild the selected filters),
``noise_model.png`` and TensorBoard events (``tb/``: training curves, validation scores, the
noise-model curves).  :func:`run_transfer` evaluates a finished run's selected filters against the
hand-tuned one on other drives (e.g. a second processing of the same drive), each drive whole.
:func:`run_evaluation` recomputes a finished run's test tables from its saved selections (no
training: a cheap check that other code reproduces them) and adds paired comparisons against
other reference rows and every row's validation score.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.tensorboard import SummaryWriter

from difffilter.filters import EKF, SageHusa, VBAdaptiveR
from difffilter.learn.data import TrajectorySet
from difffilter.selection import learnable_values
from experiments.holdout import paired_error_table, select_candidate
from experiments.ranging.report import write_csv

from .data import default_smartloc_path
from .filters import SnapshotWLS
from .model import make_smartloc_model
from .noise_plots import plot_noise_models
from .protocol import (
    Drive,
    block_sets,
    build_filter,
    cached_drives,
    fold_coefficients,
    fold_data,
    hand_tuned_filter,
    horizontal_errors,
    learned_filter,
    select_with_fallbacks,
    selected_filter,
    start_candidate,
    train_jobs,
    validation_score,
)
from .significance import significance_gate, significance_options, validation_epochs

__all__ = ["format_tables", "resolve_config", "run_evaluation", "run_protocol", "run_transfer", "untrained_filter", "write_fold_csv"]


def resolve_config(cfg: Mapping[str, Any], folder: str | Path | Sequence[str | Path] | None = None) -> dict[str, Any]:
    """A plain, JSON-able configuration: ``folder`` (one folder or several, if given) replaces the
    drives by every drive of those folders; a drive folder ``null`` is the smartLoc default folder."""
    out = json.loads(json.dumps(dict(cfg)))
    if folder is not None:
        folders = [folder] if isinstance(folder, (str, Path)) else list(folder)
        out["drives"] = [{"folder": str(f), "input_file": None, "truth_file": None} for f in folders]
    for spec in out["drives"]:
        if spec.get("folder") is None:
            spec["folder"] = str(default_smartloc_path())
    return out


def _baselines(drive: Drive, cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The rows every test block gets besides the configured filters: the hand-tuned EKF without
    its gate, the robust single-epoch WLS fix, and the adaptive-R filters (Sage-Husa, VB-AKF) on
    the hand-tuned model without gate, started at the receiver's variances (their default
    hyperparameters, untrained).  The adaptive filters estimate ``R`` per satellite slot; the
    slots' satellites change over the drive, so their estimate mixes satellites - what these
    filters can do with a varying constellation.  No EM row: ``fit_em`` refuses the
    control-dependent ``R`` (the receiver's per-epoch variances)."""
    hand = {k: float(v) for k, v in dict(cfg["hand_tuned"]).items()}
    model = lambda: make_smartloc_model(drive.data, robust=None, **hand)  # noqa: E731
    return {
        "ekf-no-gate": EKF(model()),
        "snapshot-wls": SnapshotWLS(make_smartloc_model(drive.data), robust="cauchy", threshold=1.5),
        "sage-husa": SageHusa(EKF(model())),
        "vb-adaptive-r": VBAdaptiveR(EKF(model())),
    }


def untrained_filter(cfg: Mapping[str, Any], drives: Sequence[Drive], fold: str, selected: Mapping[str, Any] | None = None) -> Any:
    """The first variant's learned filter at its untrained start (start coefficients fitted on the
    fold's training blocks, the configured gate at its start values): the ``untrained-gate`` row.
    The coefficients come from ``selected`` (the run's entry for this fold and variant) when it
    has them: the fit is iterative and refitting can differ in the last bits."""
    variant = str(cfg["variants"][0])
    coef = (selected or {}).get("coefficients")
    if coef is None:
        coef = fold_coefficients(cfg, drives, fold, variant)
    return build_filter(cfg, drives, variant, torch.as_tensor(coef, dtype=torch.float64), learned=True)


def write_fold_csv(path: Path, errors: Mapping[str, torch.Tensor], cfg: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``path`` (a fold's ``results.csv``): one row per filter with ``pos_err_p50``, ``rmse_pos``,
    ``pos_err_p95`` and the paired differences to ``hand-tuned`` (``d_*``) and to
    ``untrained-gate`` (``u_*``, same resamples); the first variant's row is named ``learned``."""
    boot = dict(cfg["bootstrap"])
    kw = {"block": int(boot["block"]), "draws": int(boot["draws"]), "seed": int(boot["seed"])}
    main = f"learned-{cfg['variants'][0]}"
    vs_start = {r["filter"]: r for r in paired_error_table(errors, "untrained-gate", **kw)}
    rows = []
    for r in paired_error_table(errors, "hand-tuned", **kw):
        row = {"filter": "learned" if r["filter"] == main else r["filter"], "pos_err_p50": r["median"], "rmse_pos": r["rms"]}
        row |= {"pos_err_p95": r["p95"], **{k: v for k, v in r.items() if k.startswith("d_")}}
        row |= {f"u_{k[2:]}": v for k, v in vs_start[r["filter"]].items() if k.startswith("d_")}
        rows.append(row)
    write_csv(path, rows)
    return rows


def _test_errors(
    filters: Mapping[str, Any], drives: Sequence[Drive], sets: Sequence[TrajectorySet], cfg: Mapping[str, Any]
) -> dict[str, torch.Tensor]:
    """Per-epoch horizontal errors of every filter (and the baselines) on the test sets, drives concatenated."""
    out: dict[str, list[torch.Tensor]] = {}
    by_name = {d.data.name: d for d in drives}
    for s in sets:
        rows = dict(filters)
        rows.update(_baselines(by_name[str(s.source)], cfg))
        for name, filt in rows.items():
            out.setdefault(name, []).append(horizontal_errors(filt, [s]))
    return {k: torch.cat(v) for k, v in out.items()}


def _paired(errors: Mapping[str, torch.Tensor], cfg: Mapping[str, Any]) -> list[dict[str, Any]]:
    boot = dict(cfg["bootstrap"])
    return paired_error_table(errors, "hand-tuned", block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"]))


def _values(filt: torch.nn.Module, names: Sequence[str]) -> dict[str, list[float]]:
    vals = learnable_values(filt)
    return {n.removeprefix("model."): [round(float(x), 6) for x in vals[n].detach().reshape(-1)] for n in names if n in vals}


def run_protocol(cfg: Mapping[str, Any], output_dir: str | Path, *, workers: int = 1) -> dict[str, Any]:
    """Train, select and test as :mod:`~experiments.papers.smartloc.protocol` describes; write the report."""
    selection = dict(cfg.get("selection") or {})
    # significance: a learned choice must also beat the non-learned candidates by a validation block bootstrap.
    significance = significance_options(selection)
    if significance is not None and not selection.get("start_candidate"):
        raise ValueError("selection.significance needs selection.start_candidate: true (the untrained start is one of its references)")
    t0 = time.time()
    out_dir = Path(output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg, drives = cached_drives(json.dumps(cfg, sort_keys=True))
    horizons = sorted(int(h) for h in cfg.get("horizons", [1]))
    epochs = int(cfg["epochs"]) * horizons[-1]
    coefs = {(f, v): fold_coefficients(cfg, drives, f, v) for f in cfg["folds"] for v in cfg["variants"]}
    jobs = [
        {
            "cfg": cfg,
            "fold": f,
            "variant": v,
            "seed": s,
            "coefficients": coefs[(f, v)].tolist(),
            "epochs": epochs,
            "log_dir": str(out_dir / "tb"),
        }
        for f in cfg["folds"]
        for v in cfg["variants"]
        for s in range(int(cfg["seeds"]))
    ]
    runs = train_jobs(jobs, workers=workers)
    runs += [start_candidate(cfg, drives, f, v, coefs[(f, v)]) for f in cfg["folds"] for v in cfg["variants"]]
    train_s = time.time() - t0
    summary: dict[str, Any] = {"config": cfg, "drives": [d.data.name for d in drives], "folds": {}, "train_seconds": train_s}
    selected: dict[str, Any] = {}
    writer = SummaryWriter(str(out_dir / "tb" / "noise_models"))
    for fold in cfg["folds"]:
        sets = fold_data(cfg, drives, fold)
        filters: dict[str, Any] = {"hand-tuned": hand_tuned_filter(cfg, drives)}
        fold_sum: dict[str, Any] = {"selection": {}}
        hand_score, hand_extra = validation_score(filters["hand-tuned"], sets["val"])
        fold_sum["hand_val"] = dict(hand_extra)
        # The hand-tuned filter as a candidate of its own: it keeps its place unless a learned model validates strictly better.
        fallback = bool(dict(cfg.get("selection") or {}).get("hand_tuned_candidate", False))
        # start_candidate: the untrained start is a non-learned candidate too; a learned model must beat it strictly.
        strict_start = bool(dict(cfg.get("selection") or {}).get("start_candidate", False))
        for variant in cfg["variants"]:
            mine = [r for r in runs if r["fold"] == fold and r["variant"] == variant]
            for h in horizons:
                if strict_start:
                    trained = [r for r in mine if r["seed"] != "start"]
                    start = next(r for r in mine if r["seed"] == "start")
                    kind, rep, ep = select_with_fallbacks(
                        [r["scores"] for r in trained],
                        start=start["scores"][0],
                        hand=hand_score if fallback else None,
                        horizon=int(cfg["epochs"]) * h,
                    )
                    best = select_candidate([r["scores"] for r in trained], int(cfg["epochs"]) * h)
                    best_learned = {"seed": trained[best[0]]["seed"], "epoch": best[1], "val_score": trained[best[0]]["scores"][best[1]]}
                    if kind == "learned" and significance is not None:
                        coef = coefs[(fold, variant)]
                        kind, best_learned["significance"] = significance_gate(
                            learned_filter(cfg, drives, variant, coef, trained[rep]["snapshots"][ep]),
                            {"hand-tuned": (filters["hand-tuned"], hand_score)} if fallback else {},
                            ("start", learned_filter(cfg, drives, variant, coef, start["snapshots"][0]), start["scores"][0]),
                            sets["val"],
                            significance,
                            validation_epochs(cfg, drives, fold),
                        )
                        rep, ep = (rep, ep) if kind == "learned" else (0, 0)
                    run = trained[rep] if kind == "learned" else start
                else:
                    rep, ep = select_candidate([r["scores"] for r in mine], int(cfg["epochs"]) * h)
                    run, kind, best_learned = mine[rep], "learned", None
                name = f"learned-{variant}" + ("" if h == horizons[0] else f" ({h}x epochs)")
                if fallback and (kind == "hand-tuned" or (not strict_start and not run["scores"][ep] < hand_score)):
                    filters[name] = filters["hand-tuned"]
                    fold_sum["selection"][name] = {"seed": "hand-tuned", "epoch": 0, "val_score": hand_score, "values": {}}
                    fold_sum["selection"][name] |= {f"val_{k}": v for k, v in hand_extra.items()}
                    fold_sum["selection"][name]["best_learned"] = best_learned or {
                        "seed": run["seed"],
                        "epoch": ep,
                        "val_score": run["scores"][ep],
                    }
                    if h == horizons[0]:
                        selected[f"{fold}/{variant}"] = {"hand_tuned": True, "coefficients": coefs[(fold, variant)]}
                    continue
                filt = learned_filter(cfg, drives, variant, coefs[(fold, variant)], run["snapshots"][ep])
                filters[name] = filt
                fold_sum["selection"][name] = {
                    "seed": run["seed"],
                    "epoch": ep,
                    "val_score": run["scores"][ep],
                    **{f"val_{k}": v for k, v in run["extras"][ep].items()},
                    "values": _values(filt, list(run["snapshots"][ep])),
                }
                if best_learned is not None:
                    fold_sum["selection"][name]["best_learned"] = best_learned
                if h == horizons[0]:
                    selected[f"{fold}/{variant}"] = {"coefficients": coefs[(fold, variant)], "snapshot": run["snapshots"][ep]}
            fold_sum["val_scores"] = fold_sum.get("val_scores", {}) | {f"{variant}/seed{r['seed']}": r["scores"] for r in mine}
        v0 = cfg["variants"][0]
        filters["untrained-gate"] = untrained_filter(cfg, drives, fold, {"coefficients": coefs[(fold, v0)]})
        errors = _test_errors(filters, drives, sets["test"], cfg)
        write_fold_csv(out_dir / fold / "results.csv", errors, cfg)
        boot = dict(cfg["bootstrap"])
        fold_sum["test"] = paired_error_table(
            errors, "hand-tuned", block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"])
        )
        fold_sum["test_epochs"] = int(errors["hand-tuned"].numel())
        summary["folds"][fold] = fold_sum
        fig = plot_noise_models(
            {k: v for k, v in filters.items() if k.startswith("learned-") and "x epochs" not in k},
            drives,
            title=f"fold {fold}",
            gates={k: filters[k] for k in ("hand-tuned", "untrained-gate")},
        )
        for name, sel in fold_sum["selection"].items():  # the selected learned values as scalars (TensorBoard)
            for key, vals in sel["values"].items():
                for j, v in enumerate(vals):
                    writer.add_scalar(f"extras/fold_{fold}/{name}/{key}{'' if len(vals) == 1 else f'_{j + 1}'}", float(v), 0)
        writer.add_figure(f"noise_model/fold_{fold}", fig, close=False)
        fig.savefig(out_dir / f"noise_model_fold_{fold}.png", dpi=110)
    writer.close()
    summary["total_seconds"] = time.time() - t0
    torch.save(selected, out_dir / "selected.pt")
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    (out_dir / "results.md").write_text(format_tables(summary))
    return summary


def run_transfer(run_dir: str | Path, cfg: Mapping[str, Any], output_dir: str | Path) -> dict[str, Any]:
    """The selected learned filters of a finished run (``run_dir``) vs the hand-tuned filter on the
    drives of ``cfg`` (each drive whole), with paired block-bootstrap intervals."""
    run_dir, out_dir = Path(run_dir), Path(output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    trained = json.loads((run_dir / "summary.json").read_text())["config"]
    selected = torch.load(run_dir / "selected.pt", weights_only=False)
    cfg, drives = cached_drives(json.dumps(cfg, sort_keys=True))
    sets = block_sets(
        drives, {i: (0, d.data.num_epochs) for i, d in enumerate(drives)}, elevation_mask_deg=float(cfg["elevation_mask_deg"])
    )
    filters: dict[str, Any] = {"hand-tuned": hand_tuned_filter(trained, drives)}
    for key, sel in selected.items():
        fold, variant = key.split("/")
        filters[f"learned-{variant} (fold {fold})"] = selected_filter(trained, drives, variant, sel)
    errors = _test_errors(filters, drives, sets, cfg)
    boot = dict(cfg["bootstrap"])
    rows = paired_error_table(errors, "hand-tuned", block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"]))
    summary = {
        "trained_in": str(run_dir),
        "drives": [d.data.name for d in drives],
        "epochs": int(errors["hand-tuned"].numel()),
        "test": rows,
    }
    (out_dir / "transfer.json").write_text(json.dumps(summary, indent=1, default=float))
    (out_dir / "results.md").write_text(
        _table(rows, f"Transfer: filters trained in {run_dir} on {summary['drives']} ({summary['epochs']} epochs)")
    )
    return summary


def run_evaluation(
    run_dir: str | Path,
    output_dir: str | Path,
    *,
    references: Sequence[str] = ("hand-tuned", "ekf-no-gate", "learned-scale"),
    compare_with: str | Path | None = None,
) -> dict[str, Any]:
    """Rebuild a finished run's hand-tuned, baseline and selected learned filters (first horizon)
    from its ``summary.json`` + ``selected.pt`` and evaluate them again on every fold's test block:
    one paired table per reference row in ``references`` (those a fold lacks are skipped), and the
    validation median and RMS of every row (of the baselines only for a single drive).  Nothing is trained or
    selected here, so the tables with reference ``hand-tuned`` must equal the run's own.

    ``compare_with``: another finished run on the same drives and folds (e.g. an earlier protocol
    version); its selected filters join as rows ``<its folder name>/learned-<variant>`` and each is
    also a reference, so the tables give this run's rows minus the other run's, paired.

    Each fold also gets the paired intervals of every row against the hand-tuned filter on the
    validation windows (``validation_paired``): how well the block used for selection resolves
    the differences it chose between."""
    run_dir, out_dir = Path(run_dir), Path(output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = json.loads((run_dir / "summary.json").read_text())["config"]
    selected = torch.load(run_dir / "selected.pt", weights_only=False)
    cfg, drives = cached_drives(json.dumps(cfg, sort_keys=True))
    boot = dict(cfg["bootstrap"])
    other: dict[str, Any] = {}
    if compare_with is not None:
        other_dir = Path(compare_with)
        other_cfg = json.loads((other_dir / "summary.json").read_text())["config"]
        if other_cfg["folds"] != cfg["folds"] or _drive_files(other_cfg) != _drive_files(cfg):
            raise ValueError(f"compare_with must be a run on the same drives and folds as {run_dir}, got {other_dir}")
        other = {"tag": other_dir.name, "cfg": other_cfg, "selected": torch.load(other_dir / "selected.pt", weights_only=False)}
    summary: dict[str, Any] = {"evaluated": str(run_dir), "drives": [d.data.name for d in drives], "folds": {}}
    if other:
        summary["compared_with"] = str(compare_with)
    parts = [f"# Re-evaluation of {run_dir} (selections as saved, nothing trained)", ""]
    for fold in cfg["folds"]:
        sets = fold_data(cfg, drives, fold)
        filters: dict[str, Any] = {"hand-tuned": hand_tuned_filter(cfg, drives)}
        for key, sel in selected.items():
            f, variant = key.split("/")
            if f == fold:
                filters[f"learned-{variant}"] = selected_filter(cfg, drives, variant, sel)
        filters["untrained-gate"] = untrained_filter(cfg, drives, fold, selected.get(f"{fold}/{cfg['variants'][0]}"))
        extra_refs = []
        for key, sel in (other.get("selected") or {}).items():
            f, variant = key.split("/")
            if f == fold:
                extra_refs.append(f"{other['tag']}/learned-{variant}")
                filters[extra_refs[-1]] = selected_filter(other["cfg"], drives, variant, sel)
        errors = _test_errors(filters, drives, sets["test"], cfg)
        # Validation windows are pooled across drives; the baselines (built per drive) join when there is one drive.
        on_val = dict(filters) | (_baselines(drives[0], cfg) if len(drives) == 1 else {})
        val = {name: horizontal_errors(filt, sets["val"]) for name, filt in on_val.items()}
        fold_sum: dict[str, Any] = {"test_epochs": int(errors["hand-tuned"].numel()), "tables": {}, "validation": {}}
        for name, e in val.items():
            fold_sum["validation"][name] = {"median": float(e.median()), "rms": float(e.pow(2).mean().sqrt())}
        for ref in (r for r in [*references, *extra_refs] if r in errors):
            rows = paired_error_table(errors, ref, block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"]))
            fold_sum["tables"][ref] = rows
            title = f"Fold {fold}: test blocks ({fold_sum['test_epochs']} epochs), paired against {ref}"
            parts.append(_table(rows, title, "hand" if ref == "hand-tuned" else ref))
        vals = ", ".join(f"{k} {v['median']:.2f} + {v['rms']:.2f}" for k, v in fold_sum["validation"].items())
        parts += [f"Validation windows (median + RMS, m): {vals}.", ""]
        # How far the validation block itself resolves the selection: the same paired bootstrap on the
        # concatenated validation windows (blocks may straddle two windows).
        rows = paired_error_table(val, "hand-tuned", block=int(boot["block"]), draws=int(boot["draws"]), seed=int(boot["seed"]))
        fold_sum["validation_paired"] = rows
        parts.append(_table(rows, f"Fold {fold}: validation windows ({int(val['hand-tuned'].numel())} epochs), paired against hand-tuned"))
        summary["folds"][fold] = fold_sum
    (out_dir / "evaluation.json").write_text(json.dumps(summary, indent=1, default=float))
    (out_dir / "results.md").write_text("\n".join(parts) + "\n")
    return summary


def _drive_files(cfg: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    return [(str(Path(str(d["folder"])).resolve()), d.get("input_file"), d.get("truth_file")) for d in cfg["drives"]]


def _table(rows: Sequence[Mapping[str, Any]], title: str, ref: str = "hand") -> str:
    lines = [
        f"### {title}",
        "",
        f"| filter | median (m) | RMS (m) | p95 (m) | median - {ref} [95 % CI] | RMS - {ref} [95 % CI] |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        diff = lambda s, r=r: f"{r[f'd_{s}']:+.2f} [{r[f'd_{s}_lo']:+.2f}, {r[f'd_{s}_hi']:+.2f}]" if f"d_{s}" in r else ""  # noqa: E731
        lines.append(f"| {r['filter']} | {r['median']:.2f} | {r['rms']:.2f} | {r['p95']:.2f} | {diff('median')} | {diff('rms')} |")
    return "\n".join(lines) + "\n"


def format_tables(summary: Mapping[str, Any]) -> str:
    """The markdown report of :func:`run_protocol`'s summary: per fold the test table, then the
    selections (seed, epoch, validation score, learned values)."""
    parts = [f"# Real-data protocol: {', '.join(summary['drives'])}", ""]
    for fold, fs in summary["folds"].items():
        parts.append(_table(fs["test"], f"Fold {fold}: test blocks ({fs['test_epochs']} epochs), errors horizontal"))
        hv = fs["hand_val"]
        parts.append(f"Validation (median + RMS, m): hand-tuned {hv['median']:.2f} + {hv['rms']:.2f}.")
        for name, sel in fs["selection"].items():
            vals = "; ".join(f"{k} {v if len(v) > 1 else v[0]}" for k, v in sel["values"].items())
            if sel["seed"] == "hand-tuned":
                b = sel["best_learned"]
                vals = f"no learned model validates better (best: seed {b['seed']}, epoch {b['epoch']}, {b['val_score']:.2f})"
            elif sel["seed"] == "start" and "best_learned" in sel:
                b = sel["best_learned"]
                best = f"best: seed {b['seed']}, epoch {b['epoch']}, {b['val_score']:.2f}"
                vals = f"the untrained start; no learned model validates better ({best}); {vals}"
            parts.append(
                f"- {name}: seed {sel['seed']}, epoch {sel['epoch']}, validation {sel['val_median']:.2f} + {sel['val_rms']:.2f}; {vals}"
            )
        parts.append("")
    parts.append(f"Wall time: {summary['total_seconds']:.0f} s (training {summary['train_seconds']:.0f} s).")
    return "\n".join(parts) + "\n"
