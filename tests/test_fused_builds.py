"""Kernel builds do not block each other (difffilter.engines.build, .kernel): different
kernels build at the same time, one kernel builds once across threads and processes sharing a
cache, and a forward-only call runs while the reverse kernel is still being built.

A wrapper compiler (``CXX``) logs every build and can hold the reverse kernel's build at a gate,
so the order of events is observed, not timed."""

from __future__ import annotations

import shutil
import stat
import subprocess
import sys
import threading
from concurrent.futures import Future
from pathlib import Path

import pytest
import torch

from difffilter.engines import FusedFilter, build
from difffilter.filters import UKF
from difffilter.models import FunctionalModel

pytestmark = pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
D = torch.float64
WRAPPER = """#!/bin/sh
src=""
for a in "$@"; do case "$a" in *.cpp) src="$a";; esac; done
if [ -n "$src" ]; then
  echo "start $(date +%s.%N)" >> "$BUILD_LOG"
  if [ -n "$BUILD_GATE" ] && grep -q "void backward" "$src"; then
    while [ ! -e "$BUILD_GATE" ]; do sleep 0.05; done
  fi
  if [ -n "$BUILD_DELAY" ]; then sleep "$BUILD_DELAY"; fi
fi
g++ "$@"
rc=$?
if [ -n "$src" ]; then echo "end $(date +%s.%N)" >> "$BUILD_LOG"; fi
exit $rc
"""


@pytest.fixture
def wrapped(tmp_path, monkeypatch):
    cxx = tmp_path / "logging-g++"
    cxx.write_text(WRAPPER)
    cxx.chmod(cxx.stat().st_mode | stat.S_IXUSR)
    log = tmp_path / "builds.log"
    monkeypatch.setenv("CXX", str(cxx))
    monkeypatch.setenv("BUILD_LOG", str(log))
    monkeypatch.setenv("DIFFFILTER_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("DIFFFILTER_PROGRAM_CACHE", "0")
    return tmp_path, log


def _source(i: int) -> str:
    return f'extern "C" int value() {{ return {i}; }}\n'


def _events(log: Path) -> list[str]:
    return [line.split()[0] for line in sorted(log.read_text().splitlines(), key=lambda ln: float(ln.split()[1]))]


def test_different_kernels_build_at_the_same_time(wrapped, monkeypatch):
    _, log = wrapped
    monkeypatch.setenv("BUILD_DELAY", "1")
    libs: dict[int, int] = {}
    threads = [
        threading.Thread(target=lambda i=i: libs.__setitem__(i, build.compile_library(_source(i), tag="t").value())) for i in (101, 102)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert libs == {101: 101, 102: 102}
    assert _events(log) == ["start", "start", "end", "end"]  # the second began before the first ended


def test_one_kernel_builds_once_across_threads_and_processes(wrapped, monkeypatch):
    _, log = wrapped
    monkeypatch.setenv("BUILD_DELAY", "1")
    # the build module alone (standard library only), as a sweep's worker process would use it
    code = (
        "import importlib.util, sys; spec = importlib.util.spec_from_file_location('b', sys.argv[1]); "
        "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); "
        f"print(m.compile_library({_source(7)!r}, tag='t').value())"
    )
    procs = [subprocess.Popen([sys.executable, "-c", code, build.__file__], stdout=subprocess.PIPE, text=True) for _ in range(2)]
    values: list[int] = []
    threads = [threading.Thread(target=lambda: values.append(build.compile_library(_source(7), tag="t").value())) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    outs = [p.communicate(timeout=120)[0].strip() for p in procs]
    assert values == [7, 7, 7] and outs == ["7", "7"]
    assert _events(log) == ["start", "end"]


@pytest.mark.slow  # builds a small UKF's kernels on an empty cache (~10 s)
def test_forward_runs_while_the_reverse_kernel_builds(wrapped, monkeypatch):
    tmp, log = wrapped
    gate = tmp / "gate"
    monkeypatch.setenv("BUILD_GATE", str(gate))
    model = FunctionalModel(
        f=lambda x: 0.9 * x, h=lambda x: x[..., :1] ** 2 + x[..., 1:], Q=0.1 * torch.eye(2, dtype=D), R=0.2 * torch.eye(1, dtype=D)
    )
    ukf = UKF(model)
    fused = FusedFilter(ukf, engine="generated")
    z = torch.randn(3, 5, 1, dtype=D, generator=torch.Generator().manual_seed(0))
    m0, p0 = torch.zeros(2, dtype=D), torch.eye(2, dtype=D)
    done: list[torch.Tensor] = []

    def forward_only() -> None:
        with torch.no_grad():
            done.append(fused(z, m0, p0).mean)

    worker = threading.Thread(target=forward_only, daemon=True)
    worker.start()
    worker.join(timeout=300)
    try:
        assert done, "the forward-only call waited for the reverse kernel's build"
        (prog,) = fused.generated_engine()._programs.values()
        pending = [f for f in prog._backward.values() if isinstance(f, Future)]
        assert pending and not any(f.done() for f in pending)  # held at the gate all along
    finally:
        gate.touch()
    torch.testing.assert_close(done[0], ukf(z, m0, p0).mean.detach(), rtol=1e-10, atol=1e-12)
    grads = torch.autograd.grad(fused(z, m0, p0).log_likelihood.sum(), list(ukf.parameters()))
    want = torch.autograd.grad(ukf(z, m0, p0).log_likelihood.sum(), list(ukf.parameters()))
    for a, b in zip(grads, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
