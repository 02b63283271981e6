"""GPS/DR vehicle scenarios of p000 (Yang & Zhang): 500 s at T = 0.1 s.

The truth comes from a kinematic vehicle (speed ``s`` and azimuth ``h``, clockwise from north)
driven by a script of segments, not from the filter's manoeuvre model: each segment holds a
longitudinal acceleration and a yaw rate that ramps linearly from a start to an end value
(constant turns, clothoids).  The acceleration and yaw-rate profiles are smoothed by a 1 s
moving average (a driver does not step the pedals), then integrated on a grid 10x finer than
``T`` (trapezoidal rule):

.. math::
    v_e = s \\sin h, \\; v_n = s \\cos h, \\quad
    a_e = \\dot s \\sin h + s \\dot h \\cos h, \\; a_n = \\dot s \\cos h - s \\dot h \\sin h.

Sensor errors: gyro drift ``eps`` is a Gauss-Markov process (stationary std ``sigma_eps``,
correlation time ``tau_eps``; it starts at 0 in the paper's straight-line case and stationary
otherwise); the odometer scale ``psi`` is a per-trajectory constant ``1 + sigma_psi N(0, 1)``
(exactly 1 in the straight-line case).  Measurements at ``t_k = k T``, ``k = 1..steps``:

* GPS east/north position + ``N(0, sigma_gps^2)``;
* gyro ``s^2 dh/dt / (g v_e^2 + v_n^2) + eps + N(0, sigma_gyro^2)`` (``= dh/dt`` for ``g = 1``;
  ``g`` is p000's nonlinearity factor applied to the synthetic sensor and the filter alike);
* odometer ``psi T sqrt(g v_e^2 + v_n^2) + N(0, sigma_odometer^2)``.

Scenarios: ``"straight"`` (p000's case: ``X(0) = [0 10 0 0 10 0 0 1]``, uniform straight line),
``"scripted"`` (a fixed 500 s drive with straights, turns, clothoids, accelerating and braking)
and ``"random"`` (a random segment schedule per trajectory, for training sets).  Optional GPS
outages set the mask of the two GPS components to False (their values become NaN).

Indexing: ``initial_state`` is the truth at ``t = 0`` (what the initial belief describes);
``truth[:, k - 1]`` and ``measurements[:, k - 1]`` are at ``t_k``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from difffilter._util import generator
from difffilter.sim.signals import cumtrapz, moving_average
from experiments.papers.p000.model import GPSDR_PAPER, GpsDrModel

from .errors import SensorErrors, gauss_markov

__all__ = ["GpsDrScenario", "SCRIPTED_DRIVE", "simulate_p000"]

#: The scripted drive: ``(duration s, longitudinal acceleration m/s^2, yaw rate at start deg/s,
#: yaw rate at end deg/s)``; starts at 12 m/s heading 30 deg and lasts 500 s.
SCRIPTED_DRIVE: tuple[tuple[float, float, float, float], ...] = (
    (40.0, 0.0, 0.0, 0.0),  # straight
    (8.0, 1.0, 0.0, 0.0),  # accelerate to 20 m/s
    (30.0, 0.0, 0.0, 0.0),
    (15.0, 0.0, 6.0, 6.0),  # right turn, 90 deg
    (20.0, 0.0, 0.0, 0.0),
    (10.0, -1.2, 0.0, 0.0),  # brake to 8 m/s
    (20.0, 0.0, -9.0, -9.0),  # left U-turn, 180 deg
    (30.0, 0.0, 0.0, 0.0),
    (12.0, 0.8, 0.0, 0.0),  # accelerate to 17.6 m/s
    (40.0, 0.0, 0.0, 8.0),  # clothoid into a right curve
    (20.0, 0.0, 8.0, -8.0),  # S-bend
    (20.0, 0.0, -8.0, 0.0),
    (25.0, 0.0, 0.0, 0.0),
    (8.0, -1.5, 0.0, 0.0),  # brake to 5.6 m/s
    (30.0, 0.0, -12.0, -12.0),  # slow left loop, 360 deg
    (15.0, 0.6, 0.0, 0.0),  # accelerate to 14.6 m/s
    (40.0, 0.0, 4.0, -4.0),  # long sweeping curve
    (117.0, 0.0, 0.0, 0.0),
)


@dataclass
class GpsDrScenario:
    """Simulated p000 trajectories (batch-first, ``T = steps``).

    Attributes:
        truth: ``[B, T, 8]`` true ``[s_e, v_e, a_e, s_n, v_n, a_n, eps, psi]`` at ``t_1..t_T``.
        measurements: ``[B, T, 4]`` ``[s_e_gps, s_n_gps, omega, s]`` (NaN where masked).
        mask: ``[B, T, 4]`` True = observed (False on GPS components during outages).
        controls: ``None`` (the model's ``dt`` is constant).
        initial_state: ``[B, 8]`` truth at ``t = 0``.
        dt: sample interval (s).
        params: the true sensor settings and ``g`` (SI units).
    """

    truth: Tensor
    measurements: Tensor
    mask: Tensor
    initial_state: Tensor
    dt: float
    params: dict[str, float] = field(default_factory=dict)
    controls: None = None

    def initial_belief(self, std: Sequence[float] | None = None) -> tuple[Tensor, Tensor]:
        """p000's belief: mean = the true initial state, ``cov = I_8`` (or ``diag(std^2)``)."""
        dtype = self.truth.dtype
        if std is None:
            return self.initial_state.clone(), torch.eye(8, dtype=dtype)
        s = torch.as_tensor(std, dtype=dtype)
        return self.initial_state.clone(), torch.diag(s * s)

    def make_model(self, **kwargs: object) -> GpsDrModel:
        """Hand-tuned :meth:`GpsDrModel.paper` with this data's ``dt``, ``g``, dtype and true
        sensor noise levels; keyword arguments override (``motion="singer"``...)."""
        opts: dict[str, object] = {k: self.params[k] for k in ("sigma_gps", "sigma_gyro", "sigma_odometer", "sigma_eps", "tau_eps")}
        opts.update(dt=self.dt, g=self.params["g"], dtype=self.truth.dtype)
        opts.update(kwargs)
        return GpsDrModel.paper(**opts)  # type: ignore[arg-type]


def _fill_segments(acc: Tensor, yaw: Tensor, segments: Sequence[tuple[float, float, float, float]], h: float) -> None:
    """Write one trajectory's segment script into fine-grid profiles ``acc``/``yaw`` ``[N]``."""
    n, t0 = acc.shape[0], 0.0
    for dur, a, w0, w1 in segments:
        i0, i1 = round(t0 / h), min(round((t0 + dur) / h), n)
        if i1 > i0:
            frac = torch.linspace(0.0, 1.0, i1 - i0, dtype=acc.dtype)
            acc[i0:i1] = a
            yaw[i0:i1] = math.radians(w0) + (math.radians(w1) - math.radians(w0)) * frac
        t0 += dur
    if round(t0 / h) < n:  # the script ended early: hold the last yaw rate, coast
        yaw[round(t0 / h) :] = yaw[max(round(t0 / h) - 1, 0)]


def _random_segments(gen: torch.Generator, horizon: float, speed0: float) -> list[tuple[float, float, float, float]]:
    """A random script: straights, speed changes within [3, 25] m/s, constant turns and
    clothoids with lateral acceleration below 4 m/s^2."""

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=torch.float64))

    segs: list[tuple[float, float, float, float]] = []
    t, speed = 0.0, speed0
    while t < horizon:
        kind = u(0.0, 1.0)
        if kind < 0.3:
            seg = (u(5.0, 30.0), 0.0, 0.0, 0.0)
        elif kind < 0.55:
            target = u(3.0, 25.0)
            rate = u(0.5, 2.0)
            seg = (max(abs(target - speed) / rate, 2.0), math.copysign(rate, target - speed), 0.0, 0.0)
            speed = speed + seg[0] * seg[1]
        else:
            wmax = min(12.0, math.degrees(4.0 / max(speed, 1.0)))
            w0 = u(-wmax, wmax)
            w1 = w0 if kind < 0.8 else u(-wmax, wmax)
            seg = (u(5.0, 25.0), 0.0, w0, w1)
        segs.append(seg)
        t += seg[0]
    return segs


def simulate_p000(
    *,
    batch_size: int = 1,
    seed: int | torch.Generator = 0,
    scenario: str = "scripted",
    steps: int = 5000,
    dt: float = GPSDR_PAPER["dt"],
    g: float = 1.0,
    sigma_gps: float = GPSDR_PAPER["sigma_gps"],
    sigma_gyro: float = GPSDR_PAPER["sigma_gyro"],
    sigma_odometer: float = GPSDR_PAPER["sigma_odometer"],
    sigma_eps: float = GPSDR_PAPER["sigma_eps"],
    tau_eps: float = GPSDR_PAPER["tau_eps"],
    sigma_psi: float = GPSDR_PAPER["sigma_psi"],
    gps_outages: Sequence[tuple[float, float]] = (),
    random_outages: int = 0,
    errors: SensorErrors | None = None,
    substeps: int = 10,
    dtype: torch.dtype = torch.float32,
) -> GpsDrScenario:
    """Simulate ``batch_size`` p000 drives (module docstring for the models).

    Args:
        batch_size: number of trajectories ``B``.
        seed: integer seed or ``torch.Generator`` (the same seed gives the same data).
        scenario: ``"straight"``, ``"scripted"`` or ``"random"``.
        steps: number of samples ``T`` (5000 = 500 s at 0.1 s).
        dt: sample interval (s).
        g: nonlinearity factor of the gyro and odometer (p000's second experiment: 1.5).
        sigma_*: sensor noise levels (SI units; p000's values by default), ``tau_eps`` (s).
        gps_outages: ``(start, end)`` windows in seconds without GPS, for every trajectory.
        random_outages: number of extra outages per trajectory, 10-30 s long at random times.
        errors: error processes the paper's filter does not model (:class:`SensorErrors`: gyro
            bias instability, wheel slip, GPS multipath/NLOS/outages); ``None``: none.  The odometer
            scale error of the "odometer" family is ``sigma_psi``.
        substeps: fine integration steps per sample.
        dtype: dtype of the returned tensors (the simulation runs in float64).
    """
    if scenario not in ("straight", "scripted", "random"):
        raise ValueError(f"scenario must be 'straight', 'scripted' or 'random', got {scenario!r}")
    gen = generator(seed)
    b, f64 = batch_size, torch.float64
    h = dt / substeps
    n = steps * substeps + 1
    acc = torch.zeros(b, n, dtype=f64)
    yaw = torch.zeros(b, n, dtype=f64)
    if scenario == "straight":
        speed0 = torch.full((b,), math.hypot(10.0, 10.0), dtype=f64)
        head0 = torch.full((b,), math.pi / 4, dtype=f64)
    elif scenario == "scripted":
        speed0 = torch.full((b,), 12.0, dtype=f64)
        head0 = torch.full((b,), math.radians(30.0), dtype=f64)
        for i in range(b):
            _fill_segments(acc[i], yaw[i], SCRIPTED_DRIVE, h)
    else:
        speed0 = 5.0 + 15.0 * torch.rand(b, generator=gen, dtype=f64)
        head0 = 2.0 * math.pi * torch.rand(b, generator=gen, dtype=f64)
        for i in range(b):
            _fill_segments(acc[i], yaw[i], _random_segments(gen, steps * dt, float(speed0[i])), h)
    if scenario != "straight":
        width = max(int(round(1.0 / h)), 1)
        acc, yaw = moving_average(acc, width), moving_average(yaw, width)
    speed = cumtrapz(acc, h, speed0)
    head = cumtrapz(yaw, h, head0)
    sh, ch = torch.sin(head), torch.cos(head)
    ve, vn = speed * sh, speed * ch
    ae, an = acc * sh + speed * yaw * ch, acc * ch - speed * yaw * sh
    se, sn = cumtrapz(ve, h, torch.zeros(b, dtype=f64)), cumtrapz(vn, h, torch.zeros(b, dtype=f64))
    idx = torch.arange(0, n, substeps)
    kin = torch.stack([se, ve, ae, sn, vn, an], -1)[:, idx]  # [B, steps + 1, 6]
    rate = (yaw * speed * speed / (g * ve * ve + vn * vn))[:, idx]

    straight = scenario == "straight"
    eps0 = torch.zeros(b, dtype=f64) if straight else sigma_eps * torch.randn(b, generator=gen, dtype=f64)
    eps = gauss_markov(gen, (b, steps), dt, sigma_eps, tau_eps, eps0)
    psi = torch.ones(b, dtype=f64) if straight else 1.0 + sigma_psi * torch.randn(b, generator=gen, dtype=f64)
    state = torch.cat([kin, eps[..., None], psi[:, None, None].expand(b, steps + 1, 1)], -1)

    truth = state[:, 1:]
    noise = torch.randn(b, steps, 4, generator=gen, dtype=f64) * torch.tensor([sigma_gps, sigma_gps, sigma_gyro, sigma_odometer], dtype=f64)
    speed_g = torch.sqrt(g * truth[..., 1] ** 2 + truth[..., 4] ** 2)
    clean = torch.stack([truth[..., 0], truth[..., 3], rate[:, 1:] + truth[..., 6], truth[..., 7] * dt * speed_g], -1)
    z = clean + noise

    if errors is not None:  # drawn after everything else: errors=None keeps the nominal data bit for bit
        bias = errors.gyro_bias(gen, (b, steps), dt)[:, 1:]
        truth = torch.cat([truth[..., :6], truth[..., 6:7] + bias[..., None], truth[..., 7:]], -1)
        slip = errors.slip(gen, acc[:, idx][:, 1:], dt)
        z = torch.stack([z[..., 0], z[..., 1], z[..., 2] + bias, z[..., 3] + slip * clean[..., 3]], -1)
        z = torch.cat([z[..., :2] + errors.gps_error(gen, (b, steps), dt), z[..., 2:]], -1)

    times = dt * torch.arange(1, steps + 1, dtype=f64)
    gps_ok = torch.ones(b, steps, dtype=torch.bool)
    for start, end in gps_outages:
        gps_ok &= ~((times >= start) & (times < end))[None]
    for _ in range(random_outages):
        length = 10.0 + 20.0 * torch.rand(b, generator=gen, dtype=f64)
        start = torch.rand(b, generator=gen, dtype=f64) * (steps * dt - length).clamp_min(0.0)
        gps_ok &= ~((times[None] >= start[:, None]) & (times[None] < (start + length)[:, None]))
    if errors is not None:
        gps_ok &= errors.gps_available(gen, (b, steps), dt)
    mask = torch.ones(b, steps, 4, dtype=torch.bool)
    mask[..., :2] = gps_ok[..., None]
    z = torch.where(mask, z, torch.full_like(z, float("nan")))
    params = {
        "sigma_gps": sigma_gps,
        "sigma_gyro": sigma_gyro,
        "sigma_odometer": sigma_odometer,
        "sigma_eps": sigma_eps,
        "tau_eps": tau_eps,
        "sigma_psi": sigma_psi,
        "g": g,
    }
    return GpsDrScenario(
        truth=truth.to(dtype), measurements=z.to(dtype), mask=mask, initial_state=state[:, 0].to(dtype), dt=dt, params=params
    )
