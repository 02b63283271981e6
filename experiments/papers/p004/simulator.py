"""GNSS/IMU vehicle scenario of p004 (Li, Zhu, Wang & Lyu): 400 s at 1 s from (0, 0) to (900, 0).

The drive (azimuth ``psi`` clockwise from north, speeds in m/s, yaw rates in deg/s, times in s)
starts at the paper's initial conditions (speed 10, acceleration 2, turn rate 0, heading north):

====================  ==========================================================================
0 - 3                 accelerate north at 2 m/s^2 to 16
3 - 30                straight north; 30 - 36 brake to 12
30 - 45               constant right turn, 6 deg/s (to east)
45 - 75               eastward weave, turn rate 6 sin(2 pi t / 30 s) (varying), speed ``v_E``
75 - 90               constant right turn, 6 deg/s (to south)
90 - 120              straight south at ``v_S`` (brakes to 9 at 115 - 120)
120 - 180             full left loop, -6 deg/s at 9
180 - 215             straight south at ``v_S`` (brakes to 10 at 210 - 215)
215 - 230             constant left turn (to east); 235 - 250 clothoid, turn rate -3 -> -9 deg/s
250 - 290             straight north (12 from 255), brake to 9 at 285 - 290
290 - 350             full right loop, 6 deg/s at 9
360 - 375             constant right turn (to east); 380 - 390 brake to 6, straight to the end
====================  ==========================================================================

Speeds are piecewise linear between knots; speeds and turn rates are then smoothed by 4 s and
3 s moving averages (pedals and steering take time, and it keeps the 1 s trapezoidal position
update of the filter within a few cm of the truth).
The heading profile does not depend on the speeds, so the end point is linear in the speed
knots: the two free speeds ``v_E`` and ``v_S`` are solved exactly (a 2x2 linear system) so that
every trajectory ends at (900, 0) (about 7.1 and 16.2 m/s for the template).  The randomised
variant scales each turn rate by ``U(0.7, 1.3)`` (loops flip direction with probability 1/2), the
weave amplitude by ``U(0.5, 1.5)`` and the fixed speed knots by ``U(0.8, 1.2)``, then solves the
same system (redrawing when ``v_E`` or ``v_S`` falls outside [3, 25] m/s).

Sensors (module :mod:`experiments.papers.p004.model` for the frames and the IMU convention): the
IMU delivers interval means ``accel = C_bn(t_{k-1}) (Delta v / T - g_n) + b_a + N(0, sigma_accel^2)``
and ``gyro = Delta theta / T + b_g + N(0, sigma_gyro^2)`` with per-trajectory constant biases
``b_a ~ N(0, (0.05 mg)^2)``, ``b_g ~ N(0, (0.1 deg/h)^2)`` per axis; GNSS gives position
(``sigma_gnss``, 0.1 m for "20 dB", see ``GNSS_IMU_PAPER``), optionally velocity and heading.
The vehicle is level (``z = 0``, no roll or pitch); the truth is integrated on a 100x finer grid.

Families beyond the paper's sensors (keyword arguments; defaults reproduce the paper's draws):

* ``bias_walk = (accel, gyro)``: the biases also walk during the drive (in-run instability of a
  MEMS IMU), ``b_k = b_{k-1} + sigma_walk sqrt(T) n_k``; the reading over ``(t_{k-1}, t_k]``
  carries ``b_{k-1}`` and the truth at ``t_k`` holds ``b_k`` (the filter's convention).
* ``canyon_windows``: ``(start, end)`` seconds in an urban canyon, where the GNSS error is a
  first-order Gauss-Markov process (std ``canyon_sigma`` per axis, correlation time
  ``canyon_tau``: multipath) instead of white ``sigma_gnss``.  The receiver's reported accuracy,
  ``controls["gnss_accuracy"] [B, T, 1]`` (always present), is ``sigma_gnss`` in open sky and
  ``canyon_sigma`` in the canyon: it knows the size of its error, not its correlation.

Indexing: ``initial_state`` is the truth at ``t = 0``; ``truth[:, k - 1]``, ``measurements[:, k - 1]``
and ``controls[...][:, k - 1]`` (the IMU over ``(t_{k-1}, t_k]``) belong to ``t_k = k T``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from difffilter._util import generator
from difffilter.models.base import wrap_angle
from difffilter.sim.signals import cumtrapz, moving_average
from experiments.papers.p004.model import GNSS_IMU_PAPER, GRAVITY, GnssImuModel

from .switching import imu_switching_statistics

__all__ = ["GnssImuScenario", "P004_SPEED_KNOTS", "P004_TURNS", "simulate_p004"]

#: Turn-rate segments ``(start s, end s, kind, a, b)``: ``const`` rate ``a``; ``ramp`` from ``a`` to
#: ``b``; ``weave`` ``a sin(2 pi (t - start) / b)`` (deg/s, clockwise positive).
P004_TURNS: tuple[tuple[float, float, str, float, float], ...] = (
    (30.0, 45.0, "const", 6.0, 0.0),
    (45.0, 75.0, "weave", 6.0, 30.0),
    (75.0, 90.0, "const", 6.0, 0.0),
    (120.0, 180.0, "const", -6.0, 0.0),
    (215.0, 230.0, "const", -6.0, 0.0),
    (235.0, 250.0, "ramp", -3.0, -9.0),
    (290.0, 350.0, "const", 6.0, 0.0),
    (360.0, 375.0, "const", 6.0, 0.0),
)
#: Speed knots ``(time s, speed m/s)``; ``"E"`` and ``"S"`` are solved for the end point.
P004_SPEED_KNOTS: tuple[tuple[float, float | str], ...] = (
    (0.0, 10.0), (3.0, 16.0), (30.0, 16.0), (36.0, 12.0), (45.0, "E"), (75.0, "E"), (80.0, 12.0),
    (95.0, "S"), (115.0, "S"), (120.0, 9.0), (180.0, 9.0), (185.0, "S"), (210.0, "S"), (215.0, 10.0),
    (250.0, 10.0), (255.0, 12.0), (285.0, 12.0), (290.0, 9.0), (350.0, 9.0), (380.0, 9.0), (390.0, 6.0),
    (400.0, 6.0),
)  # fmt: skip
END_POINT = (900.0, 0.0)
#: Widths (s) of the centred moving averages applied to the speeds and the turn rates.  The speed
#: window stays within the first 3 s + its extrapolation, so the initial acceleration is exactly 2.
SPEED_SMOOTHING, TURN_SMOOTHING = 4.0, 3.0


@dataclass
class GnssImuScenario:
    """Simulated p004 drives (batch-first, ``T`` samples).

    Attributes:
        truth: ``[B, T, 16]`` ``[p, v, q, b_a, b_g]`` (planar: ``[B, T, 8]``
            ``[p_e, p_n, v_e, v_n, psi, b_f, b_l, b_g]``).
        measurements: ``[B, T, m]`` GNSS ``[p, (v), (psi)]`` (NaN where masked).
        mask: ``[B, T, m]`` True = observed.
        controls: ``{"accel": [B, T, 3 or 2], "gyro": [B, T, 3 or 1]}``.
        initial_state: ``[B, n]`` truth at ``t = 0``.
        heading: ``[B, T]`` true azimuth (rad, unwrapped).
        dt: sample interval (s).
        planar: which state layout.
        params: sensor settings and options used.
    """

    truth: Tensor
    measurements: Tensor
    mask: Tensor
    controls: dict[str, Tensor]
    initial_state: Tensor
    heading: Tensor
    dt: float
    planar: bool
    params: dict[str, float] = field(default_factory=dict)

    @property
    def position(self) -> Tensor:
        """``[B, T, 2]`` true east/north position."""
        return self.truth[..., :2]

    def initial_belief(self) -> tuple[Tensor, Tensor]:
        """Mean = true initial state with unknown (zero) biases; ``cov`` = diag of GNSS-level
        position, 0.1 m/s velocity, ``sigma_heading`` heading (3-D: ``(sigma_heading / 2)^2`` on
        each quaternion component) and the bias priors of the truth."""
        p, dtype = self.params, self.truth.dtype
        mean = self.initial_state.clone()
        if self.planar:
            mean[..., 5:] = 0.0
            std = [p["sigma_gnss"]] * 2 + [0.1] * 2 + [p["sigma_heading"]] + [p["sigma_accel_bias"]] * 2 + [p["sigma_gyro_bias"]]
        else:
            mean[..., 10:] = 0.0
            std = [p["sigma_gnss"]] * 3 + [0.1] * 3 + [p["sigma_heading"] / 2] * 4
            std += [p["sigma_accel_bias"]] * 3 + [p["sigma_gyro_bias"]] * 3
        s = torch.tensor(std, dtype=dtype)
        return mean, torch.diag(s * s)

    def make_model(self, **kwargs: object) -> GnssImuModel:
        """Hand-tuned :class:`GnssImuModel` with this data's layout, observations, dtype and true
        noise levels (a level of 0, from a noise-free simulation, falls back to the default of
        ``GNSS_IMU_PAPER``); keyword arguments override."""
        names = ("sigma_accel", "sigma_gyro", "sigma_gnss", "sigma_gnss_velocity", "sigma_heading")
        opts: dict[str, object] = {k: self.params[k] if self.params[k] > 0 else GNSS_IMU_PAPER[k] for k in names}
        opts.update(
            planar=self.planar,
            dt=self.dt,
            velocity=bool(self.params["velocity"]),
            heading=bool(self.params["heading"]),
            dtype=self.truth.dtype,
        )
        opts.update(kwargs)
        return GnssImuModel(**opts)  # type: ignore[arg-type]

    def switching_statistics(self, sigma_gnss: float | None = None, sigma_imu: float | None = None) -> tuple[Tensor, Tensor]:
        """p004's ``(gamma, mu)`` per step from the IMU readings (gravity removed), ``[]``/``[B, T]``."""
        p = self.params
        accel = self.controls["accel"]
        return imu_switching_statistics(
            accel,
            self.controls["gyro"],
            p["sigma_accel"],
            p["sigma_gyro"],
            p["sigma_gnss"] if sigma_gnss is None else sigma_gnss,
            p["sigma_accel"] if sigma_imu is None else sigma_imu,
            gravity=None if self.planar else GRAVITY,
        )


def _turn_rates(t: Tensor, turns: Sequence[tuple[float, float, str, float, float]]) -> Tensor:
    """Clockwise turn rate (rad/s) on the grid ``t [N]`` for one script."""
    w = torch.zeros_like(t)
    for t0, t1, kind, a, b in turns:
        m = (t >= t0) & (t < t1)
        if kind == "const":
            w[m] = a
        elif kind == "ramp":
            w[m] = a + (b - a) * (t[m] - t0) / (t1 - t0)
        elif kind == "weave":
            w[m] = a * torch.sin(2 * math.pi * (t[m] - t0) / b)
        else:  # pragma: no cover - table error
            raise ValueError(kind)
    return torch.deg2rad(w)


def _hat_functions(t: Tensor, knot_times: Sequence[float]) -> Tensor:
    """Piecewise-linear interpolation basis ``[K, N]`` (speed = sum_i s_i hat_i(t))."""
    kt = torch.tensor(knot_times, dtype=t.dtype)
    idx = torch.searchsorted(kt, t, right=True).clamp(1, len(knot_times) - 1)
    # linear extrapolation before the first knot (so smoothing keeps the initial acceleration),
    # constant after the last one
    frac = ((t - kt[idx - 1]) / (kt[idx] - kt[idx - 1])).clamp(max=1.0)
    hats = torch.zeros(len(knot_times), t.shape[0], dtype=t.dtype)
    cols = torch.arange(t.shape[0])
    hats[idx - 1, cols] = 1.0 - frac
    hats[idx, cols] += frac
    return hats


def _solve_speeds(hats: Tensor, heading: Tensor, knots: Sequence[tuple[float, float | str]], h: float) -> tuple[Tensor, Tensor]:
    """Speed profile ``[N]`` reaching :data:`END_POINT` and the free speeds ``(v_E, v_S)``."""
    dirs = torch.stack([torch.sin(heading), torch.cos(heading)], -1)  # [N, 2]
    w = hats[..., None] * dirs  # displacement of each knot's unit speed, [K, N, 2]
    disp = 0.5 * h * (w[:, 1:] + w[:, :-1]).sum(1)  # [K, 2]
    fixed = torch.tensor([0.0 if isinstance(v, str) else v for _, v in knots], dtype=hats.dtype)
    a = torch.stack([disp[[i for i, (_, v) in enumerate(knots) if v == name]].sum(0) for name in ("E", "S")], -1)
    free = torch.linalg.solve(a, torch.tensor(END_POINT, dtype=hats.dtype) - fixed @ disp)
    values = fixed.clone()
    for i, (_, v) in enumerate(knots):
        if isinstance(v, str):
            values[i] = free[0] if v == "E" else free[1]
    return values @ hats, free


def _in_windows(times: Tensor, windows: Sequence[tuple[float, float]]) -> Tensor:
    """``[T]`` True where a time lies in one of the ``(start, end)`` windows."""
    inside = torch.zeros(times.shape, dtype=torch.bool)
    for start, end in windows:
        if not float(start) < float(end):
            raise ValueError(f"windows must be (start, end) with start < end, got {(start, end)}")
        inside |= (times >= float(start)) & (times < float(end))
    return inside


def _gauss_markov(b: int, steps: int, d: int, sigma: float, tau: float, dt: float, gen: torch.Generator) -> Tensor:
    """``[b, steps, d]`` stationary first-order Gauss-Markov samples (std ``sigma``, correlation time ``tau``)."""
    if not (sigma > 0.0 and tau > 0.0):
        raise ValueError(f"canyon_sigma and canyon_tau must be positive, got {sigma}, {tau}")
    phi = math.exp(-dt / tau)
    drive = torch.randn(b, steps, d, generator=gen, dtype=torch.float64)
    out = torch.empty_like(drive)
    out[:, 0] = sigma * drive[:, 0]
    for k in range(1, steps):
        out[:, k] = phi * out[:, k - 1] + sigma * math.sqrt(1.0 - phi * phi) * drive[:, k]
    return out


def _random_script(gen: torch.Generator) -> tuple[list[tuple[float, float, str, float, float]], list[tuple[float, float | str]]]:
    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=torch.float64))

    turns = []
    for t0, t1, kind, a, b in P004_TURNS:
        flip = -1.0 if (t1 - t0 >= 60.0 and u(0.0, 1.0) < 0.5) else 1.0  # loops: either direction
        scale = u(0.5, 1.5) if kind == "weave" else u(0.7, 1.3)
        turns.append((t0, t1, kind, flip * scale * a, b if kind == "weave" else flip * scale * b))
    knots = [(t, v if isinstance(v, str) else v * u(0.8, 1.2)) for t, v in P004_SPEED_KNOTS]
    knots[:2] = P004_SPEED_KNOTS[:2]  # keep the paper's initial speed and acceleration
    return turns, knots


def simulate_p004(
    *,
    batch_size: int = 1,
    seed: int | torch.Generator = 0,
    randomize: bool = False,
    planar: bool = False,
    velocity: bool = False,
    heading: bool = False,
    gnss_outages: Sequence[tuple[float, float]] = (),
    bias_walk: tuple[float, float] = (0.0, 0.0),
    canyon_windows: Sequence[tuple[float, float]] = (),
    canyon_sigma: float = 1.0,
    canyon_tau: float = 10.0,
    substeps: int = 100,
    dtype: torch.dtype = torch.float32,
    **settings: float,
) -> GnssImuScenario:
    """Simulate ``batch_size`` p004 drives (module docstring for the script and sensors).

    Args:
        batch_size: number of trajectories ``B``.
        seed: integer seed or ``torch.Generator``.
        randomize: random variant of the script (per trajectory) instead of the fixed one.
        planar: planar state layout / IMU (see :class:`~experiments.papers.p004.model.PlanarGnssImuDynamics`).
        velocity, heading: add GNSS velocity / dual-antenna heading observations.
        gnss_outages: ``(start, end)`` windows in seconds without GNSS.
        bias_walk: true in-run bias random walks ``(accel m/s^2/sqrt(s), gyro rad/s/sqrt(s))``.
        canyon_windows, canyon_sigma, canyon_tau: urban-canyon windows (s), their GNSS error std
            (m) and correlation time (s) (module docstring).
        substeps: fine integration steps per sample.
        dtype: dtype of the returned tensors (the simulation runs in float64).
        **settings: overrides of :data:`~experiments.papers.p004.model.GNSS_IMU_PAPER`.
    """
    p = {**GNSS_IMU_PAPER, **settings}
    gen = generator(seed)
    f64, b, dt = torch.float64, batch_size, float(p["dt"])
    steps = int(round(P004_SPEED_KNOTS[-1][0] / dt))
    h = dt / substeps
    w_speed, w_turn = int(round(SPEED_SMOOTHING / h)), int(round(TURN_SMOOTHING / h))
    # the grid extends a window beyond both ends so the centred smoothing is exact there
    t = h * torch.arange(-w_speed, steps * substeps + 1 + w_speed, dtype=f64)
    crop = slice(w_speed, w_speed + steps * substeps + 1)
    hats = moving_average(_hat_functions(t, [k for k, _ in P004_SPEED_KNOTS]), w_speed)[:, crop]
    speeds, heads = [], []
    for _ in range(b):
        turns, knots = P004_TURNS, P004_SPEED_KNOTS
        for _attempt in range(50):
            if randomize:
                turns, knots = _random_script(gen)  # type: ignore[assignment]
            rate = moving_average(_turn_rates(t, turns), w_turn)[crop]
            head = cumtrapz(rate, h, torch.zeros((), dtype=f64))
            speed, free = _solve_speeds(hats, head, knots, h)
            if not randomize or bool(((free >= 3.0) & (free <= 25.0)).all()):
                break
        speeds.append(speed)
        heads.append(head)
    speed, head = torch.stack(speeds), torch.stack(heads)  # [B, N]
    vel = speed[..., None] * torch.stack([torch.sin(head), torch.cos(head)], -1)  # [B, N, 2]
    pos = torch.stack([cumtrapz(vel[..., i], h, torch.zeros(b, dtype=f64)) for i in range(2)], -1)
    idx = torch.arange(0, steps * substeps + 1, substeps)
    pos, vel, psi = pos[:, idx], vel[:, idx], head[:, idx]  # [B, T + 1, ...]

    mean_acc = (vel[:, 1:] - vel[:, :-1]) / dt  # [B, T, 2] navigation frame
    s0, c0 = torch.sin(psi[:, :-1]), torch.cos(psi[:, :-1])
    f_fwd = mean_acc[..., 0] * s0 + mean_acc[..., 1] * c0
    f_left = -mean_acc[..., 0] * c0 + mean_acc[..., 1] * s0
    yaw_rate = -(psi[:, 1:] - psi[:, :-1]) / dt  # counter-clockwise about up
    ba = p["sigma_accel_bias"] * torch.randn(b, 3, generator=gen, dtype=f64)
    bg = p["sigma_gyro_bias"] * torch.randn(b, 3, generator=gen, dtype=f64)
    na = p["sigma_accel"] * torch.randn(b, steps, 3, generator=gen, dtype=f64)
    ng = p["sigma_gyro"] * torch.randn(b, steps, 3, generator=gen, dtype=f64)
    walk_a, walk_g = (float(w) for w in bias_walk)
    if not (walk_a >= 0.0 and walk_g >= 0.0 and math.isfinite(walk_a + walk_g)):
        raise ValueError(f"bias_walk must be two non-negative numbers, got {bias_walk}")
    ba_t, bg_t = ba[:, None].expand(b, steps + 1, 3), bg[:, None].expand(b, steps + 1, 3)  # biases at t_0..t_T
    if walk_a > 0.0 or walk_g > 0.0:
        steps_a = walk_a * math.sqrt(dt) * torch.randn(b, steps, 3, generator=gen, dtype=f64)
        steps_g = walk_g * math.sqrt(dt) * torch.randn(b, steps, 3, generator=gen, dtype=f64)
        ba_t = ba[:, None] + torch.cat([torch.zeros(b, 1, 3, dtype=f64), steps_a.cumsum(1)], 1)
        bg_t = bg[:, None] + torch.cat([torch.zeros(b, 1, 3, dtype=f64), steps_g.cumsum(1)], 1)
    zeros = torch.zeros_like(f_fwd)
    accel = torch.stack([f_fwd, f_left, zeros + GRAVITY], -1) + ba_t[:, :-1] + na
    gyro = torch.stack([zeros, zeros, yaw_rate], -1) + bg_t[:, :-1] + ng

    zero_t = torch.zeros_like(psi)
    if planar:
        state = torch.cat([pos, vel, psi[..., None], ba_t[..., :2], bg_t[..., 2:]], -1)
        controls = {"accel": accel[..., :2], "gyro": gyro[..., 2:]}
    else:
        yaw = 0.5 * (math.pi / 2 - psi)
        quat = torch.stack([torch.cos(yaw), zero_t, zero_t, torch.sin(yaw)], -1)
        state = torch.cat(
            [
                pos,
                zero_t[..., None],
                vel,
                zero_t[..., None],
                quat,
                ba_t,
                bg_t,
            ],
            -1,
        )
        controls = {"accel": accel, "gyro": gyro}

    d = 2 if planar else 3
    truth = state[:, 1:]
    times = dt * torch.arange(1, steps + 1, dtype=f64)
    gnss_err = p["sigma_gnss"] * torch.randn(b, steps, d, generator=gen, dtype=f64)
    accuracy = torch.full((b, steps, 1), float(p["sigma_gnss"]), dtype=f64)
    if canyon_windows:
        canyon = _in_windows(times, canyon_windows)
        gnss_err = torch.where(canyon[None, :, None], _gauss_markov(b, steps, d, canyon_sigma, canyon_tau, dt, gen), gnss_err)
        accuracy[:, canyon] = float(canyon_sigma)
    parts = [truth[..., :d] + gnss_err]
    if velocity:
        parts.append(truth[..., d : 2 * d] + p["sigma_gnss_velocity"] * torch.randn(b, steps, d, generator=gen, dtype=f64))
    if heading:
        noisy = psi[:, 1:] + p["sigma_heading"] * torch.randn(b, steps, generator=gen, dtype=f64)
        parts.append(wrap_angle(noisy)[..., None])
    z = torch.cat(parts, -1)
    ok = ~_in_windows(times, gnss_outages)
    mask = ok[None, :, None].expand(b, steps, z.shape[-1]).clone()
    z = torch.where(mask, z, torch.full_like(z, float("nan")))
    params = {**p, "planar": float(planar), "velocity": float(velocity), "heading": float(heading), "randomize": float(randomize)}
    params.update({"true_accel_bias_walk": walk_a, "true_gyro_bias_walk": walk_g, "canyon": float(bool(canyon_windows))})
    controls["gnss_accuracy"] = accuracy
    return GnssImuScenario(
        truth=truth.to(dtype),
        measurements=z.to(dtype),
        mask=mask,
        controls={k: v.to(dtype) for k, v in controls.items()},
        initial_state=state[:, 0].to(dtype),
        heading=psi[:, 1:].to(dtype),
        dt=dt,
        planar=planar,
        params=params,
    )
