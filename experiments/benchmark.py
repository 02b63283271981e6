"""Benchmark difffilter against dynamax (JAX) and filterpy on the p000 GPS/DR model (Hydra entry point).

    python experiments/benchmark.py                                   # full: B in {1,16,256,4096}, T=500
    python experiments/benchmark.py benchmark=dev                     # a few minutes
    python experiments/benchmark.py benchmark=smoke                   # seconds (what the smoke test runs)
    python experiments/benchmark.py benchmark.batch_sizes=[256] benchmark.filters=[ukf] benchmark.dtypes=[float64]

Times every library in the same run on the same data, checks that they compute the same
log-likelihood, then (optionally) compares eager and ``torch.compile``d filter steps and measures
the peak memory of a truncated-BPTT training step in a subprocess per configuration.  Writes
``results.md`` and CSV tables to the Hydra run directory and prints the markdown.  Peers are
optional (``pip install difffilter[bench]``); a missing one is skipped with a message.
"""

from __future__ import annotations

import logging

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from difffilter.bench.suite import run_suite

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="../conf", config_name="benchmark")
def main(cfg: DictConfig) -> None:
    """Run the configured benchmark and write its tables to the run directory."""
    outdir = HydraConfig.get().runtime.output_dir
    overrides = " ".join(HydraConfig.get().overrides.task)
    markdown = run_suite(cfg.benchmark, outdir, command=f"python experiments/benchmark.py {overrides}".strip(), log=log.info)
    print(markdown)
    log.info("results written to %s", outdir)


if __name__ == "__main__":
    main()
