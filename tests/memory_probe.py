"""Peak resident memory of a BPTT / windowed-TBPTT pass, measured in a fresh process.

Usage (from the repository root): ``python -m tests.memory_probe WINDOW [BATCH] [STEPS]`` prints two
integers in KiB: the resident set size after data and model setup, and the peak resident set size
reached by the training pass (``WINDOW`` steps per backward pass, the belief detached between
windows; ``WINDOW >= STEPS`` is full BPTT).

Why ``/proc/self/status`` and not ``resource.getrusage(...).ru_maxrss``: on Linux the child of a
``subprocess.run`` inherits its parent's peak into ``ru_maxrss`` (the pre-``exec`` address space is
the parent's, via vfork/fork, and ``execve`` folds its high-water mark into the process's
``maxrss``).  Launched from a pytest process that has already grown past the probe's own peak, the
probe then reads the parent's peak twice and reports no growth at all.  ``VmHWM`` belongs to the
address space created by ``execve``, so it only counts this process, and writing ``5`` to
``/proc/self/clear_refs`` resets it to the current RSS, which isolates the training pass from the
setup's temporaries.

The /proc helpers import nothing heavy, so a test can call them in a cheap child process.
"""

from __future__ import annotations

import gc
import sys
from pathlib import Path

_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def available() -> bool:
    """Whether this platform exposes ``VmHWM``/``VmRSS`` in ``/proc/self/status`` (Linux)."""
    try:
        text = _STATUS.read_text()
    except OSError:
        return False
    return "VmHWM:" in text and "VmRSS:" in text


def _status_kib(field: str) -> int:
    for line in _STATUS.read_text().splitlines():
        if line.startswith(field + ":"):
            value, unit = line.split()[1:3]
            if unit != "kB":
                raise ValueError(f"unexpected unit {unit!r} for {field} in {_STATUS}")
            return int(value)
    raise ValueError(f"{field} not found in {_STATUS}")


def current_kib() -> int:
    """Resident set size of this process now (KiB)."""
    return _status_kib("VmRSS")


def peak_kib() -> int:
    """High-water resident set size of this process's address space (KiB)."""
    return _status_kib("VmHWM")


def reset_peak() -> bool:
    """Reset ``VmHWM`` to the current RSS (Linux >= 4.0); ``False`` where the kernel refuses."""
    try:
        _CLEAR_REFS.write_text("5")
    except OSError:
        return False
    return True


def measure(window: int, batch: int = 8, steps: int = 5000) -> tuple[int, int]:
    """``(rss after setup, peak rss of the pass)`` in KiB for a constant-velocity Kalman filter
    trained with NLL on ``batch`` trajectories of ``steps`` steps, ``window`` steps per backward."""
    for name, value in (("window", window), ("batch", batch), ("steps", steps)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name} must be an int, got {type(value).__name__}")
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    if not available():
        raise RuntimeError(f"{_STATUS} with VmHWM/VmRSS is needed to measure peak memory")

    import torch

    from difffilter.engines import set_engine
    from difffilter.filters import KalmanFilter
    from difffilter.filters.base import detach_belief
    from difffilter.learn import NLLLoss
    from difffilter.models import tracking_model
    from difffilter.models.motion import ConstantVelocity
    from difffilter.sim import sample_trajectories

    torch.set_num_threads(1)
    set_engine("eager")  # what is measured is the autograd graph of the filter's own loop
    f64 = torch.float64

    def cv(q: float) -> object:
        return tracking_model(dynamics=ConstantVelocity(axes=2, dt=1.0, q=q, dtype=f64), R=[25.0, 25.0], time_invariant=True)

    prior = ([0.0, 10.0, 0.0, 5.0], [100.0, 4.0, 100.0, 4.0])
    data = sample_trajectories(cv(0.5), batch_size=batch, num_steps=steps, initial_mean=prior[0], initial_cov=prior[1], seed=0)
    kf = KalmanFilter(cv(2.0))
    loss = NLLLoss()
    gc.collect()
    base = current_kib() if reset_peak() else peak_kib()
    belief = None
    for start in range(0, steps, window):
        res = kf(data.measurements[:, start : start + window], data.initial_mean, data.initial_cov, belief=belief)
        loss(res, {}).mean().backward()
        belief = detach_belief(res.final_belief)
        del res
    return base, peak_kib()


def main(argv: list[str]) -> None:
    if not 1 <= len(argv) <= 3:
        raise SystemExit("usage: python -m tests.memory_probe WINDOW [BATCH] [STEPS]")
    base, peak = measure(*(int(a) for a in argv))
    print(base, peak)


if __name__ == "__main__":
    main(sys.argv[1:])
