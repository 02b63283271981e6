"""p002's table from a sweep: ``python experiments/train.py -m experiment=p002_pdr
scenario.blockage_prob=0.8,0.6,0.4,0.2,0.05`` writes one run per blockage probability ``P``;
``python -m difffilter.papers.p002.report <multirun dir> [column...]`` prints the ``filter x P``
table next to p002's published numbers."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

from omegaconf import OmegaConf

__all__ = ["PAPER_RMSE", "sweep_table"]

#: p002's position RMSE table (m), by row and outage probability P.
PAPER_RMSE: dict[str, dict[float, float]] = {
    "GPS only": {0.8: 12.17, 0.6: 9.42, 0.4: 5.83, 0.2: 2.88, 0.05: 2.67},
    "PDR only": {0.8: 8.31, 0.6: 7.98, 0.4: 8.16, 0.2: 8.23, 0.05: 7.96},
    "UKF": {0.8: 7.38, 0.6: 7.19, 0.4: 4.46, 0.2: 3.97, 0.05: 2.41},
    "RC-UKF": {0.8: 6.78, 0.6: 6.42, 0.4: 3.12, 0.2: 2.60, 0.05: 1.94},
}

_ROW_NAMES = {"hand-tuned": "RC-UKF (hand-tuned)", "learned": "RC-UKF (learned)"}
_PAPER_ROW = {"GPS only": "GPS only", "PDR only": "PDR only", "UKF": "UKF", "RC-UKF (hand-tuned)": "RC-UKF"}


def _blockage_prob(run_dir: Path) -> float | None:
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if overrides.exists():
        for line in overrides.read_text().splitlines():
            if "scenario.blockage_prob=" in line:
                return float(line.split("=", 1)[1].strip().strip("'\""))
    config = run_dir / ".hydra" / "config.yaml"
    if config.exists():
        return float(OmegaConf.load(config).scenario.blockage_prob)
    return None


def sweep_table(multirun_dir: str | Path, column: str = "rmse_pos") -> str:
    """Markdown table ``filter x P`` of ``column`` from every ``results.csv`` below
    ``multirun_dir`` (one sweep job per ``P``), with p002's published RMSE in brackets."""
    table: dict[str, dict[float, float]] = {}
    for csv_path in sorted(Path(multirun_dir).rglob("results.csv")):
        prob = _blockage_prob(csv_path.parent)
        if prob is None:
            continue
        with csv_path.open() as fh:
            for row in csv.DictReader(fh):
                name = _ROW_NAMES.get(row["filter"], row["filter"])
                value = row.get(column, "")
                table.setdefault(name, {})[prob] = float(value) if value not in ("", None) else math.nan
    probs = sorted({p for v in table.values() for p in v}, reverse=True)
    head = f"{column} (m) [p002]" if column == "rmse_pos" else column
    lines = [f"| {head} | " + " | ".join(f"P={p:g}" for p in probs) + " |", "|---|" + "---|" * len(probs)]
    for name, vals in table.items():
        paper = PAPER_RMSE.get(_PAPER_ROW.get(name, ""), {})
        cells = []
        for p in probs:
            cell = f"{vals[p]:.3g}" if p in vals else "-"
            if p in paper and column == "rmse_pos":
                cell += f" [{paper[p]:.2f}]"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover - command-line helper
    for arg in sys.argv[2:] or ["rmse_pos"]:
        print(sweep_table(sys.argv[1], arg))
