"""Sensor error processes of p000's mis-specified scenario families (what the paper's filter does not model).

p000's filter assumes white GPS noise (15 m), a yaw-rate gyro whose drift is a stationary first-order
Gauss-Markov process (0.015 deg/s, 100 s) and an odometer with a slowly wandering scale factor
(sigma_psi = 0.005) and white 1 m noise.  :class:`SensorErrors` adds, on top of those, error
processes of real vehicles that the model cannot represent:

* **gyro bias instability** (MEMS yaw-rate sensors): a turn-on bias, constant over a run, and an
  in-run bias instability with a long correlation time (first-order Gauss-Markov);
* **odometer scale error and wheel slip**: the per-run scale error is the simulator's
  ``sigma_psi`` (tyre pressure, wear and load change the rolling radius by 1-3 %); wheel slip
  makes the wheel read ``(1 + lambda)`` times the distance, with a longitudinal slip ratio
  ``lambda = k a`` proportional to the longitudinal acceleration ``a`` (tyre slip stiffness) and
  random slip bursts (spin or lock-up on low-friction patches);
* **GPS multipath and outages**: a time-correlated multipath error (Gauss-Markov per axis), jumps
  of non-line-of-sight (NLOS) bias held for seconds, and outages (no fix at all) at random times.

Random windows (slip bursts, NLOS episodes, outages) arrive as a Poisson process of ``rate`` per
second; each lasts ``U(duration)`` seconds.  Every draw comes from the simulator's generator, so a
seed gives the same errors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["SensorErrors", "gauss_markov", "random_windows"]


def gauss_markov(gen: torch.Generator, shape: tuple[int, int], dt: float, std: float, tau: float, start: Tensor | None = None) -> Tensor:
    """``[B, steps + 1]`` first-order Gauss-Markov samples with stationary std ``std`` and
    correlation time ``tau``, starting at ``start [B]`` (default: a stationary draw)."""
    b, steps = shape
    phi = math.exp(-dt / tau)
    if start is None:
        start = std * torch.randn(b, generator=gen, dtype=torch.float64)
    w = torch.randn(b, steps, generator=gen, dtype=torch.float64) * std * math.sqrt(1.0 - phi * phi)
    out = [start]
    for k in range(steps):
        out.append(phi * out[-1] + w[:, k])
    return torch.stack(out, -1)


def random_windows(
    gen: torch.Generator,
    shape: tuple[int, int],
    dt: float,
    rate: float,
    duration: tuple[float, float],
    value: Callable[[int], Tensor] | None = None,
) -> Tensor:
    """``[B, steps, d]`` profile of random windows: a Poisson number (mean ``rate * steps * dt``)
    of windows per run, start uniform over the run, length ``U(duration)`` seconds; inside a window
    the profile holds ``value(b) [B, d]`` (one draw per window, ``d = 1`` and value 1 by default),
    zero elsewhere; a later window overwrites an earlier one where they overlap."""
    b, steps = shape
    lo, hi = duration
    if rate <= 0.0 or steps == 0:
        d = 1 if value is None else int(value(1).shape[-1])
        return torch.zeros(b, steps, d, dtype=torch.float64)
    counts = torch.poisson(torch.full((b,), rate * steps * dt, dtype=torch.float64), generator=gen).long()
    times = dt * torch.arange(1, steps + 1, dtype=torch.float64)
    out: Tensor | None = None
    for j in range(int(counts.max())):
        start = torch.rand(b, generator=gen, dtype=torch.float64) * steps * dt
        length = lo + (hi - lo) * torch.rand(b, generator=gen, dtype=torch.float64)
        val = torch.ones(b, 1, dtype=torch.float64) if value is None else value(b)
        if out is None:
            out = torch.zeros(b, steps, val.shape[-1], dtype=torch.float64)
        inside = (times[None] >= start[:, None]) & (times[None] < (start + length)[:, None]) & (j < counts)[:, None]
        out = torch.where(inside[..., None], val[:, None, :], out)
    if out is None:
        d = 1 if value is None else int(value(1).shape[-1])
        out = torch.zeros(b, steps, d, dtype=torch.float64)
    return out


@dataclass(frozen=True, kw_only=True)
class SensorErrors:
    """Error processes added to p000's simulated sensors (all off by default; module docstring).

    Attributes:
        gyro_turn_on_std: std of the per-run constant gyro bias (rad/s).
        gyro_instability_std, gyro_instability_tau: stationary std (rad/s) and correlation time
            (s) of the in-run Gauss-Markov bias instability.
        slip_per_accel: longitudinal slip ratio per m/s^2 of longitudinal acceleration (s^2/m).
        slip_burst_rate: slip bursts per second; ``slip_burst_size`` ``(lo, hi)`` range of the
            slip-ratio magnitude (sign random), ``slip_burst_duration`` ``(lo, hi)`` seconds.
        multipath_std, multipath_tau: Gauss-Markov multipath error per GPS axis (m, s).
        nlos_rate: NLOS episodes per second; ``nlos_std`` std of the bias per axis (m) held over
            an episode of ``nlos_duration`` ``(lo, hi)`` seconds.
        outage_rate: GPS outages per second, each ``outage_duration`` ``(lo, hi)`` seconds.
    """

    gyro_turn_on_std: float = 0.0
    gyro_instability_std: float = 0.0
    gyro_instability_tau: float = 300.0
    slip_per_accel: float = 0.0
    slip_burst_rate: float = 0.0
    slip_burst_size: tuple[float, float] = (0.1, 0.3)
    slip_burst_duration: tuple[float, float] = (0.5, 2.0)
    multipath_std: float = 0.0
    multipath_tau: float = 30.0
    nlos_rate: float = 0.0
    nlos_std: float = 30.0
    nlos_duration: tuple[float, float] = (5.0, 20.0)
    outage_rate: float = 0.0
    outage_duration: tuple[float, float] = (10.0, 30.0)

    def __post_init__(self) -> None:
        for name in ("gyro_turn_on_std", "gyro_instability_std", "slip_per_accel", "slip_burst_rate", "multipath_std", "nlos_rate"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.outage_rate >= 0.0:
            raise ValueError(f"outage_rate must be >= 0, got {self.outage_rate}")
        for name in ("gyro_instability_tau", "multipath_tau", "nlos_std"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("slip_burst_size", "slip_burst_duration", "nlos_duration", "outage_duration"):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi:
                raise ValueError(f"{name} must be a range (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")

    def gyro_bias(self, gen: torch.Generator, shape: tuple[int, int], dt: float) -> Tensor:
        """``[B, steps + 1]`` extra gyro bias: turn-on constant plus the instability process."""
        b, steps = shape
        bias = torch.zeros(b, steps + 1, dtype=torch.float64)
        if self.gyro_turn_on_std > 0.0:
            bias = bias + self.gyro_turn_on_std * torch.randn(b, 1, generator=gen, dtype=torch.float64)
        if self.gyro_instability_std > 0.0:
            bias = bias + gauss_markov(gen, shape, dt, self.gyro_instability_std, self.gyro_instability_tau)
        return bias

    def slip(self, gen: torch.Generator, accel: Tensor, dt: float) -> Tensor:
        """``[B, steps]`` slip ratio from the longitudinal acceleration ``accel [B, steps]`` (m/s^2)."""
        lam = self.slip_per_accel * accel
        if self.slip_burst_rate > 0.0:
            lo, hi = self.slip_burst_size

            def size(b: int) -> Tensor:
                sign = torch.where(torch.rand(b, 1, generator=gen, dtype=torch.float64) < 0.5, -1.0, 1.0)
                return sign * (lo + (hi - lo) * torch.rand(b, 1, generator=gen, dtype=torch.float64))

            lam = lam + random_windows(gen, tuple(accel.shape), dt, self.slip_burst_rate, self.slip_burst_duration, size)[..., 0]
        return lam

    def gps_error(self, gen: torch.Generator, shape: tuple[int, int], dt: float) -> Tensor:
        """``[B, steps, 2]`` GPS error beyond the white noise: multipath plus NLOS biases."""
        b, steps = shape
        err = torch.zeros(b, steps, 2, dtype=torch.float64)
        if self.multipath_std > 0.0:
            err = err + torch.stack([gauss_markov(gen, shape, dt, self.multipath_std, self.multipath_tau)[:, 1:] for _ in range(2)], -1)
        if self.nlos_rate > 0.0:

            def bias(n: int) -> Tensor:
                return self.nlos_std * torch.randn(n, 2, generator=gen, dtype=torch.float64)

            err = err + random_windows(gen, shape, dt, self.nlos_rate, self.nlos_duration, bias)
        return err

    def gps_available(self, gen: torch.Generator, shape: tuple[int, int], dt: float) -> Tensor:
        """``[B, steps]`` True where no outage hides the GPS."""
        return random_windows(gen, shape, dt, self.outage_rate, self.outage_duration)[..., 0] == 0.0
