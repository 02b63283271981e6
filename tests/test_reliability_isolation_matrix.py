"""Batch isolation, the full matrix of issue 27: filters x corruptions x dtypes x engines.

Trajectory 1 of a batch of three is corrupted at one step; the others' values (mean, covariance,
log-likelihood) and gradients (shared parameters, measurements, initial means) must equal a run
of the clean trajectories alone to 1e-12 (in practice bit-identical), and the corrupted one must
be flagged in ``extras["untrusted"]`` -- or, for an input the contract forbids (a NaN measurement
under a True mask, a non-finite initial covariance), the batch is refused with a ``ValueError``
that names trajectory 1 (nothing silent either way).

The compiled-engine cases build one kernel per filter and are marked slow.
"""

from __future__ import annotations

import pytest
import torch

from difffilter.engines import FusedFilter
from difffilter.engines.build import compiler_available
from experiments.benchmarks.isolation import COMPILED, EAGER, F64, REFUSED, check_isolated, make_filter


@pytest.mark.parametrize(("kind", "dtype", "corruption"), EAGER, ids=[f"{k}-{str(d)[6:]}-{c}" for k, d, c in EAGER])
def test_eager_isolation(kind: str, dtype: torch.dtype, corruption: str) -> None:
    check_isolated(make_filter(kind, dtype), dtype, corruption)


@pytest.mark.slow
@pytest.mark.skipif(compiler_available() is not None, reason="no C++ compiler")
@pytest.mark.parametrize(("kind", "corruption"), COMPILED, ids=[f"{k}-{c}" for k, c in COMPILED])
def test_compiled_isolation(kind: str, corruption: str) -> None:
    fused = FusedFilter(make_filter(kind, F64), engine="generated")
    check_isolated(fused, F64, corruption)
    if corruption not in REFUSED:
        assert fused.last_engine == "generated"
