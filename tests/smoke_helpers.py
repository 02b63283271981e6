"""Shared pieces of the end-to-end smoke tests: read a results CSV, run `experiments/train.py`,
interrupt a run with a signal."""

from __future__ import annotations

import csv
import importlib.util
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import pytorch_lightning as pl

from experiments.papers.smartloc import default_smartloc_path

ROOT = Path(__file__).resolve().parents[1]
#: results.csv columns that are measured times (they differ between runs that agree in every number)
TIMING_COLUMNS = ("time_per_step_ms", "tuning_cpu_s")


def read_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV file as dicts (header = keys)."""
    with Path(path).open(newline="") as fh:
        return list(csv.DictReader(fh))


def run_train_smoke(tmp_path: Path, experiment: str) -> tuple[list[dict[str, str]], str]:
    """`python experiments/train.py experiment=<experiment> debug=smoke` into ``tmp_path``;
    asserts it exits 0 and returns ``(results.csv rows, results.md text)``."""
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), f"experiment={experiment}", "debug=smoke"]
    cmd += [f"hydra.run.dir={tmp_path}", f"paths.log_dir={tmp_path}/logs"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return read_rows(tmp_path / "results.csv"), (tmp_path / "results.md").read_text()


class SignalAt(pl.Callback):
    """Send ``signum`` to this process after training step ``step`` (a scheduler's SIGTERM, a
    Ctrl+C), from inside the training loop: what an interrupted run experiences."""

    def __init__(self, step: int, signum: int = int(signal.SIGTERM)) -> None:
        self.step, self.signum = int(step), int(signum)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), self.signum)


def plugin_installed(name: str) -> bool:
    """Whether the Hydra plugin ``hydra_plugins.<name>`` (optional extra ``sweep``) is installed;
    False also when no plugin at all is (``hydra_plugins`` itself is missing)."""
    try:
        return importlib.util.find_spec(f"hydra_plugins.{name}") is not None
    except ModuleNotFoundError:
        return False


def config_files(group: str) -> list[Path]:
    """Every option file of the config group ``group``: conf/<group>/ and each paper's
    experiments/papers/<paper>/conf/<group>/ (on train.yaml's search path), sorted by name."""
    dirs = [ROOT / "conf" / group, *sorted((ROOT / "experiments" / "papers").glob(f"*/conf/{group}"))]
    return sorted((f for d in dirs for f in d.glob("*.yaml")), key=lambda f: f.name)


def needs_smartloc_drive() -> pytest.MarkDecorator:
    """Skip (with the reason) where the smartLoc drive's files are absent: a fresh clone without
    ../shared (its model and scenarios read them)."""
    drive = default_smartloc_path() / "Berlin_Potsdamer_Platz_Input.txt"
    return pytest.mark.skipif(not drive.exists(), reason=f"smartLoc data not found at {drive.parent}")
