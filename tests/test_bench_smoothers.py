"""The benchmark's smoother section: rows beside the filter, same data (no timing asserts)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.benchmarks.runner import BenchSettings
from experiments.benchmarks.smoothers import SMOOTHER_COLUMNS, run_smoother_benchmark
from experiments.benchmarks.suite import run_suite
from tests.smoke_helpers import read_rows

ROOT = Path(__file__).resolve().parents[1]


def test_smoke_config_writes_smoother_rows(tmp_path: Path) -> None:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="benchmark", overrides=["benchmark=smoke", "benchmark.libraries=[difffilter]", "benchmark.filters=[kf]"])
    md = run_suite(OmegaConf.to_container(cfg.benchmark, resolve=True), tmp_path, log=lambda s: None)
    rows = read_rows(tmp_path / "smoothers.csv")
    assert list(rows[0]) == SMOOTHER_COLUMNS
    assert {(r["filter"], r["mode"]) for r in rows} == {(k, m) for k in ("kf", "ukf", "imm") for m in ("forward", "train")}
    for r in rows:
        assert r["B"] == "2" and r["T"] == "5"
        assert math.isfinite(float(r["smoother_over_filter"])) and float(r["smoother_steps_per_s"]) > 0
    assert "## smoothers" in md


def test_bad_smoother_section_is_refused() -> None:
    with pytest.raises(ValueError, match="benchmark.smoothers"):
        run_smoother_benchmark(BenchSettings(), {"filters": ["sqrt"]}, lambda dt, b: None)
