"""The parallel benchmark script runs and its rows check the two filters against each other."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.benchmark_parallel import main  # noqa: E402
from experiments.benchmarks.parallel import dynamax_available  # noqa: E402


def test_benchmark_parallel_smoke(tmp_path):
    out = tmp_path / "bench.md"
    text = main(["--steps", "8", "30", "--batches", "1", "2", "--repeats", "1", "--smoother", "--out", str(out)])
    all_rows = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
    rows = [line for line in all_rows if "dynamax" not in line]
    peer = [line for line in all_rows if "dynamax" in line]
    assert len(rows) == 2 * 2 * 3  # (T, B) x (filter, fwd+bwd, smoother)
    # dynamax's parallel filter is an optional peer: one row per (T, B) where it is installed, none otherwise
    assert len(peer) == (2 * 2 if dynamax_available() else 0)
    for row in rows:
        diff = float(row.strip("| ").split("|")[-1])
        assert diff < 1e-9
    for row in peer:  # JAX runs in float32 unless told otherwise, so the peer agrees to single precision
        assert float(row.strip("| ").split("|")[-1]) < 1e-3
    first, second = out.read_text().splitlines()[:2]
    args = f"--steps 8 30 --batches 1 2 --repeats 1 --smoother --out {out}"
    assert first == f"<!-- generated file: python experiments/benchmark_parallel.py {args} -->"
    assert second.startswith("# Parallel-in-time")
