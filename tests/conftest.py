"""Test-session settings."""

import os
import shutil
import tempfile

import torch

# The filters work on many small tensors: intra-op threading only adds overhead (and contention
# on the 2-core CI machine), so tests run single-threaded.
torch.set_num_threads(1)

_KERNEL_CACHE: list[str] = []


def pytest_configure(config):  # noqa: ANN001, ARG001 - pytest hook
    """Generated filter kernels compile into a fresh cache per test session (honest compile
    times, nothing left in the user's cache), unless DIFFFILTER_CACHE_DIR is set."""
    if "DIFFFILTER_CACHE_DIR" not in os.environ:
        path = tempfile.mkdtemp(prefix="difffilter-kernels-")
        _KERNEL_CACHE.append(path)
        os.environ["DIFFFILTER_CACHE_DIR"] = path


def pytest_unconfigure(config):  # noqa: ANN001, ARG001 - pytest hook
    for path in _KERNEL_CACHE:
        shutil.rmtree(path, ignore_errors=True)
        os.environ.pop("DIFFFILTER_CACHE_DIR", None)
