"""Markdown tables of a finished real-data run (``experiments/realdata.py``), read from its files.

    python experiments/realdata_tables.py outputs/realdata/smartloc/default_v3

Prints, from ``<run>/<fold>/results.csv``: per fold every filter's test median / RMS / p95 and the
paired block-bootstrap differences to the hand-tuned filter (``d_*``) and to the untrained gated
filter (``u_*``; *win* / *loss* when the 95 % interval excludes zero, *tie* otherwise); and from
``<run>/summary.json`` what validation selected for each learned row, with the validation scores of
the hand-tuned filter, the untrained start and the best learned (seed, epoch); and, for a run that
learned the sensor-model extras (protocol v4), their values in each selected learned row; for a run
with the significance gate (protocol v5), the best learned model's validation score minus the
hand-tuned filter's and the untrained start's with the gate's 95 % intervals, and its verdict.
Nothing is recomputed: the numbers are the run's own.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

__all__ = ["main", "tables"]

_EXTRAS = ("lever_arm", "latency", "elevation_bias")


def _verdict(row: dict[str, str], prefix: str, stat: str) -> str:
    if not row.get(f"{prefix}_{stat}"):
        return ""
    d, lo, hi = (float(row[f"{prefix}_{stat}{s}"]) for s in ("", "_lo", "_hi"))
    word = "win" if hi < 0 else "loss" if lo > 0 else "tie"
    return f"{d:+.2f} [{lo:+.2f}, {hi:+.2f}] {word}"


def _gate(sel: dict) -> dict | None:
    """The significance gate's record of a selection (protocol v5), if it ran."""
    return (sel.get("best_learned") or {}).get("significance")


def tables(run: str | Path) -> str:
    """The markdown of the run in ``run`` (module docstring)."""
    run = Path(run)
    summary = json.loads((run / "summary.json").read_text())
    main = f"learned-{summary['config']['variants'][0]}"
    out = [
        "| fold | filter | median (m) | RMS (m) | p95 (m) | median - hand [95 % CI] | RMS - hand [95 % CI] "
        "| median - untrained [95 % CI] | RMS - untrained [95 % CI] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for fold in summary["folds"]:
        with open(run / fold / "results.csv", newline="") as fh:
            for row in csv.DictReader(fh):
                name = main if row["filter"] == "learned" else row["filter"]
                stats = " | ".join(f"{float(row[k]):.2f}" for k in ("pos_err_p50", "rmse_pos", "pos_err_p95"))
                diffs = " | ".join(_verdict(row, p, s) for p in ("d", "u") for s in ("median", "rms"))
                out.append(f"| {fold} | {name} | {stats} | {diffs} |")
    out += [
        "",
        "| fold | row | selected (seed, epoch) | its validation score | hand-tuned | untrained start | best learned (seed, epoch, score) |",
        "|---|---|---|---|---|---|---|",
    ]
    for fold, fs in summary["folds"].items():
        hand = fs["hand_val"]["median"] + fs["hand_val"]["rms"]
        for name, sel in fs["selection"].items():
            variant = name.removeprefix("learned-").split(" ")[0]
            start = fs.get("val_scores", {}).get(f"{variant}/seedstart", [float("nan")])[0]
            b = sel.get("best_learned")
            best = f"{b['seed']}, {b['epoch']}, {b['val_score']:.2f}" if b else ""
            out.append(f"| {fold} | {name} | {sel['seed']}, {sel['epoch']} | {sel['val_score']:.2f} | {hand:.2f} | {start:.2f} | {best} |")
    extras = [
        (fold, name, sel["values"])
        for fold, fs in summary["folds"].items()
        for name, sel in fs["selection"].items()
        if any(k.endswith(_EXTRAS) for k in sel.get("values", {}))
    ]
    if extras:
        out += [
            "",
            "| fold | row | lever arm forward, left, up (m) | latency (s) | elevation bias GPS, GLONASS (m at zenith) |",
            "|---|---|---|---|---|",
        ]
        for fold, name, values in extras:
            cell = {e: ", ".join(f"{v:+.2f}" for v in next((x for k, x in values.items() if k.endswith(e)), [])) for e in _EXTRAS}
            out.append(f"| {fold} | {name} | {cell['lever_arm']} | {cell['latency']} | {cell['elevation_bias']} |")
    gated = [(fold, name, sel) for fold, fs in summary["folds"].items() for name, sel in fs["selection"].items() if _gate(sel)]
    if gated:
        out += [
            "",
            "| fold | row | best learned score | - hand-tuned [95 % CI] | - untrained start [95 % CI] | gate |",
            "|---|---|---|---|---|---|",
        ]
        for fold, name, sel in gated:
            fs = summary["folds"][fold]
            b, g = sel["best_learned"], _gate(sel)
            start = fs["val_scores"][f"{name.removeprefix('learned-').split(' ')[0]}/seedstart"][0]
            refs = {"hand-tuned": fs["hand_val"]["median"] + fs["hand_val"]["rms"], "start": start}
            cells = [
                f"{b['val_score'] - refs[k]:+.2f} [{g['intervals'][k][0]:+.2f}, {g['intervals'][k][1]:+.2f}]" if k in g["intervals"] else ""
                for k in ("hand-tuned", "start")
            ]
            verdict = "passed" if g["passed"] else f"not passed: {sel['seed']}"
            out.append(f"| {fold} | {name} | {b['val_score']:.2f} | {cells[0]} | {cells[1]} | {verdict} |")
    out.append("")
    out.append(f"Run time: {summary['total_seconds']:.0f} s wall (training {summary['train_seconds']:.0f} s).")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run directory of experiments/realdata.py")
    print(tables(parser.parse_args(argv).run), end="")


if __name__ == "__main__":
    main()
