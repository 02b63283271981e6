"""experiments/learned_values.py: learned parameter values per seed of a sweep, grouped as the
sweep summary groups its jobs."""

from __future__ import annotations

import csv
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from difffilter.evaluate.evaluation import write_per_run

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "learned_values.py"


def _module():
    spec = importlib.util.spec_from_file_location("learned_values", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def _job(root: Path, num: int, overrides: list[str], learned: str) -> None:
    d = root / str(num)
    (d / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(overrides), d / ".hydra" / "overrides.yaml")
    write_per_run({"hand-tuned": {"rmse_pos": torch.ones(3)}, "learned": {"rmse_pos": torch.ones(3)}}, d / "per_run.csv")
    with (d / "results.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["filter", "rmse_pos", "parameters"])
        w.writeheader()
        w.writerow({"filter": "hand-tuned", "rmse_pos": 1.0, "parameters": "psi=[0.7, 0.7]; R=[9]"})
        w.writerow({"filter": "learned", "rmse_pos": 1.0, "parameters": learned})


def test_values_per_seed_and_group(tmp_path):
    mod = _module()
    assert mod.parse_parameters("psi=[0.7, 0.69]; model.R=[9, 8.5]") == {"psi": [0.7, 0.69], "model.R": [9.0, 8.5]}
    # the formats of experiments/train.py's parameters / parameter_values columns
    assert mod.parse_parameters("delta=0.85; R=diag[0.01, 0.02]; s=2.4e-06") == {"delta": [0.85], "R": [0.01, 0.02], "s": [2.4e-06]}
    assert mod.parse_parameters("R=[[0.01, 0], [0, 0.02]]; psi=[0.7, -0.1]") == {"R": [0.01, 0.02], "psi": [0.7, -0.1]}
    _job(tmp_path, 0, ["experiment=a", "seed=0"], "psi=[0.6, 0.8]; R=[8]")
    _job(tmp_path, 1, ["experiment=a", "seed=1"], "psi=[0.9, 0.9]; R=[10]")
    _job(tmp_path, 2, ["experiment=b", "seed=0"], "psi=[0.1, 0.1]; R=[1]")
    text = mod.values_table(tmp_path)
    lines = text.splitlines()
    assert "### experiment=a" in lines and "### experiment=b" in lines
    assert "| learned, seed 0 | 0.7 (0.6-0.8) | 8 |" in lines
    assert "| learned, seed 1 | 0.9 | 10 |" in lines
    assert "| learned, mean over seeds | 0.8 | 9 |" in lines  # group a only
    assert lines.count("| hand-tuned | 0.7 | 9 |") == 2
    with pytest.raises(FileNotFoundError):
        mod.values_table(tmp_path / "none")


def test_command_line_prints_the_table(tmp_path):
    _job(tmp_path, 0, ["experiment=a", "seed=0"], "psi=[0.6, 0.8]; R=[8]")
    env = {**os.environ, "PYTHONPATH": str(SCRIPT.parents[1])}
    out = subprocess.run([sys.executable, str(SCRIPT), f"sweep_dir={tmp_path}"], capture_output=True, text=True, env=env, check=True)
    assert "| learned, seed 0 | 0.7 (0.6-0.8) | 8 |" in out.stdout
