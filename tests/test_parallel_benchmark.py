"""The parallel benchmark script runs and its rows check the filters against each other."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.benchmark_parallel import main  # noqa: E402
from experiments.benchmarks.parallel import dynamax_available  # noqa: E402


def _rows(text: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("| ").split("|")] for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]


def test_benchmark_parallel_smoke(tmp_path, monkeypatch):
    monkeypatch.setenv("DIFFFILTER_ENGINE", "auto")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "10000")
    out = tmp_path / "bench.md"
    args = ["--steps", "8", "--batches", "1", "2", "--repeats", "1", "--smoother", "--no-peer", "--out", str(out)]
    rows = _rows(main(args))
    assert len(rows) == 2 * 3  # (T, B) x (filter, fwd+bwd, smoother)
    for _t, _b, _what, default, engine, eager, par, peer, *_, diff, peer_diff in rows:
        assert float(default) > 0 and float(eager) > 0 and float(par) > 0 and peer == "-" and peer_diff == "-"
        assert engine == "eager"  # B * T below the auto threshold: the default path is the eager loop
        assert float(diff) < 1e-9
    first, second = out.read_text().splitlines()[:2]
    assert first == f"<!-- generated file: python experiments/benchmark_parallel.py {' '.join(args)} -->"
    assert second.startswith("# Parallel-in-time")


@pytest.mark.slow  # a kernel build
def test_benchmark_parallel_names_the_compiled_default_path(monkeypatch):
    # a threshold of 1: the default path of every row is the compiled engine, and the row says so
    from difffilter.engines import build

    if build.compiler_available() is not None:
        pytest.skip("needs a C++ compiler")
    monkeypatch.setenv("DIFFFILTER_ENGINE", "auto")
    monkeypatch.setenv("DIFFFILTER_AUTO_MIN_WORK", "1")
    rows = _rows(main(["--steps", "16", "--batches", "2", "--repeats", "1", "--no-peer", "--no-backward", "--max-eager", "0"]))
    assert [(r[2], r[4], r[5]) for r in rows] == [("filter", "generated", "-")]
    assert float(rows[0][-2]) < 1e-9


@pytest.mark.slow
@pytest.mark.skipif(not dynamax_available(), reason="dynamax (optional peer) not installed")
def test_benchmark_parallel_dynamax_peer():
    rows = _rows(main(["--steps", "8", "--batches", "2", "--repeats", "1", "--no-backward", "--max-eager", "0"]))
    (row,) = rows
    assert float(row[7]) > 0 and float(row[10]) > 0
    ll_diff, mean_diff = (float(x) for x in row[-1].split(","))
    # float64 in both; dynamax's parallel log-likelihood is the less exact of its outputs
    assert mean_diff < 1e-7 and ll_diff < 1e-5
