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


@pytest.mark.slow  # two jax compilations: ~20 s CPU
def test_dynamax_smoother_peer_computes_the_same_loss() -> None:
    """The smoother rows' dynamax twin (RTS, unscented RTS) smooths the same model: its training
    loss, the position mean squared error of the smoothed means, equals difffilter's."""
    pytest.importorskip("dynamax")
    import torch

    from difffilter.smoothers import make_smoother
    from experiments.benchmarks.dynamax_peer import prepare_dynamax
    from experiments.benchmarks.gpsdr import simulate_gpsdr
    from experiments.benchmarks.runner import make_difffilter
    from experiments.benchmarks.smoothers import _inputs

    s = BenchSettings()
    data = simulate_gpsdr(batch_size=2, steps=8, seed=3)
    truth = data.truth[:, 1:, [0, 3]]
    for kind in ("kf", "ukf"):
        peer = prepare_dynamax(
            kind, data, torch.float64, "train", ukf_alpha=s.ukf_alpha, ukf_beta=s.ukf_beta, ukf_kappa=s.ukf_kappa, smoother=True
        )
        theirs = float(peer.run()[0])
        z, m0, p0, pos = _inputs(kind, data)
        with torch.no_grad():
            ours = float((make_smoother(make_difffilter(kind, torch.float64, s))(z, m0, p0).mean[..., pos] - truth).square().mean())
        assert ours == pytest.approx(theirs, rel=1e-7), kind
