"""Wall-clock timing and peak-memory probes for the benchmark (Linux ``/proc``, no psutil needed).

Peak memory is the process's resident-set high-water mark (``VmHWM``), which sees every
allocator (torch's CPU allocator, XLA's, numpy's), unlike ``tracemalloc``.  Linux lets a process
reset its own high-water mark by writing ``5`` to ``/proc/self/clear_refs``; before a case the
probe collects garbage, returns freed heap pages to the OS (``malloc_trim``) and resets the mark,
so ``peak - baseline`` is the extra memory that case needed.  Where ``/proc`` is unavailable the
probe reports ``nan``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import math
import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["MemoryProbe", "Timing", "best_of", "cpu_with_children", "read_status_mb", "time_callable"]

_STATUS = "/proc/self/status"


def cpu_with_children() -> float:
    """CPU seconds (user + system) of this process and of its finished child processes (e.g. the
    C++ compiler a kernel build runs): differences of it time a call with its builds."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def best_of(fn: Callable[[], object], repeats: int, clock: Callable[[], float] = time.perf_counter) -> float:
    """The shortest time of ``repeats`` calls of ``fn`` by ``clock`` (wall time by default;
    ``time.process_time`` for process CPU time), after one untimed warm-up call."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = clock()
        fn()
        best = min(best, clock() - start)
    return best


def read_status_mb(field: str) -> float:
    """``VmRSS``/``VmHWM``... of this process in MiB (``nan`` if ``/proc`` is unavailable)."""
    try:
        with open(_STATUS) as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def _malloc_trim() -> None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


class MemoryProbe:
    """Context manager measuring the peak resident memory above the level at entry (MiB)."""

    def __init__(self) -> None:
        self.baseline_mb = math.nan
        self.peak_mb = math.nan

    def __enter__(self) -> MemoryProbe:
        gc.collect()
        _malloc_trim()
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")
            resettable = True
        except OSError:
            resettable = False
        self.baseline_mb = read_status_mb("VmRSS") if resettable else math.nan
        return self

    def __exit__(self, *exc: Any) -> None:
        self.peak_mb = read_status_mb("VmHWM")

    @property
    def extra_mb(self) -> float:
        """Peak minus baseline (``nan`` if it could not be measured)."""
        return self.peak_mb - self.baseline_mb


@dataclass
class Timing:
    """Best and median wall time (s) of ``repeats`` calls, the best process CPU time (s, all
    threads; robust to other processes on a shared machine) and the peak extra memory (MiB)."""

    best_s: float
    median_s: float
    repeats: int
    peak_mb: float
    cpu_s: float = math.nan
    result: Any = None


def time_callable(
    fn: Callable[[], Any], *, min_time_s: float = 1.0, max_repeats: int = 5, warmup: Callable[[], Any] | None = None
) -> Timing:
    """Time ``fn()`` (which must block until its work is done).

    ``warmup`` (e.g. the same computation on a short sequence, to pay first-call costs) runs once
    before timing, outside the memory probe.  Repeats continue until ``min_time_s`` of total time
    or ``max_repeats`` calls; the first timed call runs inside a :class:`MemoryProbe` and its
    return value is kept in ``Timing.result``.
    """
    if warmup is not None:
        warmup()
    with MemoryProbe() as probe:
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        times, cpu = [time.perf_counter() - t0], [time.process_time() - c0]
    while sum(times) < min_time_s and len(times) < max_repeats:
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return Timing(min(times), statistics.median(times), len(times), probe.extra_mb, min(cpu), result)
