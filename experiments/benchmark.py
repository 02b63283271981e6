"""Benchmark difffilter against dynamax (JAX) and filterpy (Hydra entry point).

    python experiments/benchmark.py                                   # full: the README's table (about 1-2 h on 2 cores)
    python experiments/benchmark.py benchmark=dev                     # a few minutes
    python experiments/benchmark.py benchmark=smoke                   # seconds (what the smoke test runs)
    python experiments/benchmark.py benchmark.batch_sizes=[256] benchmark.filters=[ukf] benchmark.dtypes=[float64]

Times every library in the same run on the same data (the p000 GPS/DR model, and p003's IMM bank
for difffilter alone), checks that they compute the same log-likelihood, measures FusedFilter's
first-call costs in fresh processes and the peak memory of truncated-BPTT training in a
subprocess per configuration.  Writes ``results.md`` and CSV tables to the Hydra run directory
and prints the markdown.  Peers are optional (``pip install difffilter[bench]``); a missing one
is skipped with a message.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import logging  # noqa: E402

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from experiments.benchmarks.cases import BenchCase  # noqa: E402
from experiments.benchmarks.suite import run_suite  # noqa: E402
from experiments.papers.p003.experiment import p003_imm, simulate  # noqa: E402

log = logging.getLogger(__name__)

#: p003's filter configuration (experiments/papers/p003/conf/filter/p003_imm_simplified.yaml)
P003_MODEL = {"num_satellites": 8, "linearized": False, "position_in_metres": True, "discretization": "expm"}


def p003_case(*, dtype: torch.dtype, batch: int, steps: int, seed: int) -> BenchCase:
    """p003's IMM bank (two 20-state simplified UKFs) on simulated 1 Hz flights of ``steps``
    seconds; only the modes' measurement-noise scales train."""
    imm = p003_imm(filter="simplified", model=P003_MODEL, dtype=dtype)
    for name, p in imm.named_parameters():
        p.requires_grad_(name.endswith("measurement.parametrizations.R.original"))
    sc = simulate(batch, seed, dtype, num_steps=steps)
    return BenchCase(imm, sc.measurements, sc.initial_mean, sc.initial_cov, sc.mask, sc.controls)


@hydra.main(version_base="1.3", config_path="../conf", config_name="benchmark")
def main(cfg: DictConfig) -> None:
    """Run the configured benchmark and write its tables to the run directory."""
    outdir = HydraConfig.get().runtime.output_dir
    overrides = " ".join(HydraConfig.get().overrides.task)
    command = f"python experiments/benchmark.py {overrides}".strip()
    markdown = run_suite(cfg.benchmark, outdir, command=command, log=log.info, cases={"p003": p003_case})
    print(markdown)
    log.info("results written to %s", outdir)


if __name__ == "__main__":
    main()
