"""GPS + pedestrian dead reckoning scenario of p002 (Niu & Lian 2017) with GPS outages.

A pedestrian walks the 360 m path of :func:`~experiments.papers.p002.track.p002_track`; every detected
step is one filter step.  The truth is scripted (path geometry, random step lengths and step
timing), not drawn from the filter's model.  Sensors, per trajectory:

* step lengths i.i.d. ``U(lo, hi)`` (0.6-0.8 m), step periods ``(1 / cadence) (1 + 0.05 n)``
  with a cadence of 1.8 steps/s; an accelerometer step-length estimate with a per-walker scale
  error (3 %) and 0.03 m noise (used by the PDR-only baseline only);
* gyro heading increment per step ``dpsi_true + b dt + arw sqrt(dt) n`` with a constant bias
  ``|b|`` in 40-80 deg/h (random sign) and angle random walk 0.5 deg/sqrt(s);
* compass heading = truth + Gauss-Markov error (8 deg, correlation time 10 s) + white error,
  11.4 deg RMSE in all; optionally an interference stretch (an arc-length window) adding a
  48.4 deg Gauss-Markov error (49.7 deg RMSE in all, p002's electromagnet test);
* GPS fixes every 1 s from a cold-start delay on, per-axis noise ``N(0, 2.67^2)`` m; a fix is
  reported at the first step event after it, with the position at that event (i.e. fixes are
  assumed time-tagged and aligned, so no latency error);
* outages: time is cut into 5 s windows, each blocked with probability ``P``; fixes inside a
  blocked window are lost.

Heading is the azimuth of :mod:`experiments.papers.p002.model` (clockwise from north), unwrapped.  The
compass is delivered unwrapped next to the gyro-propagated heading (starting from the
initial-belief heading), what a real pipeline would do before filtering; the raw wrapped
reading is kept in ``compass_raw``.

Step indexing: event 0 is the start (the initial belief describes it); filter step ``t`` covers
the step from event ``t`` to event ``t + 1`` and returns event ``t + 1``.  The truth state at an
event is ``[E, N, L, psi]`` where ``L`` is the length of the step that *starts* at that event
(the quantity the model multiplies in the next prediction) and ``psi`` the path heading there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from difffilter._util import generator
from experiments.papers.p002.model import PDRModel, default_pdr_measurement_noise, wrap_angle

from .disturbances import arc_bursts, turn_heading_error
from .track import Track, p002_track

__all__ = ["BLOCKAGE_PROBS", "PDRScenario", "gps_availability", "simulate_p002", "simulate_p002_random"]

#: The outage probabilities of p002's table.
BLOCKAGE_PROBS: tuple[float, ...] = (0.8, 0.6, 0.4, 0.2, 0.05)


@dataclass
class PDRScenario:
    """Simulated p002 trajectories (batch-first, ``T`` step events).

    Attributes:
        truth: ``[B, T, 4]`` true ``[E, N, L, psi]`` at events ``1..T``.
        measurements: ``[B, T, 3]`` ``[E_gps, N_gps, compass]`` (NaN where GPS is missing).
        mask: ``[B, T, 3]`` True = observed (compass always, GPS when a fresh fix survived).
        controls: ``dtheta [B, T, 1]`` gyro heading increment (rad), ``dt [B, T, 1]`` step
            period (s), ``step_length [B, T, 1]`` accelerometer step-length estimate (m).
        times: ``[B, T]`` event times (s).
        initial_state: ``[B, 4]`` true state at event 0.
        initial_mean, initial_cov: ``[B, 4]``, ``[4, 4]`` belief before the first step.
        blocked: ``[B, T]`` whether the event lies in a blocked GPS window.
        blockage_prob: ``[B]`` outage probability ``P``.
        gyro_bias: ``[B]`` gyro bias (rad/s).
        compass_raw: ``[B, T]`` compass reading wrapped to ``(-pi, pi]``.
        dt: nominal step period (s).
        params: true sensor settings (``gps_std`` m, ``compass_std`` rad, ...).
    """

    truth: Tensor
    measurements: Tensor
    mask: Tensor
    controls: dict[str, Tensor]
    times: Tensor
    initial_state: Tensor
    initial_mean: Tensor
    initial_cov: Tensor
    blocked: Tensor
    blockage_prob: Tensor
    gyro_bias: Tensor
    compass_raw: Tensor
    dt: float
    params: dict[str, float] = field(default_factory=dict)

    def make_model(self, **kwargs: object) -> PDRModel:
        """:class:`PDRModel` in this data's dtype with ``R`` set from the true GPS and compass
        noise levels (interference excluded); keyword arguments override (``Q=...``)."""
        r = default_pdr_measurement_noise(
            self.measurements.dtype, gps_std=self.params["gps_std"], compass_std_deg=math.degrees(self.params["compass_std"])
        )
        opts: dict[str, object] = {"R": r, "dtype": self.measurements.dtype}
        opts.update(kwargs)
        return PDRModel(**opts)  # type: ignore[arg-type]


def _per_trajectory(value: float | Sequence[float] | Tensor, batch_size: int, name: str) -> Tensor:
    v = torch.as_tensor(value, dtype=torch.float64).flatten()
    if v.numel() == 1:
        return v.expand(batch_size).clone()
    if v.numel() != batch_size:
        raise ValueError(f"{name} must be a scalar or have {batch_size} entries, got {v.numel()}")
    return v.clone()


def _gauss_markov(gen: torch.Generator, dt: Tensor, std: Tensor, tau: float) -> Tensor:
    """Stationary first-order Gauss-Markov samples at steps with periods ``dt [B, T]``."""
    phi = torch.exp(-dt / tau)
    noise = torch.randn(dt.shape, generator=gen, dtype=torch.float64)
    out = torch.empty_like(dt)
    state = std * noise[:, 0]
    out[:, 0] = state
    for k in range(1, dt.shape[1]):
        state = phi[:, k] * state + std * torch.sqrt(1.0 - phi[:, k] ** 2) * noise[:, k]
        out[:, k] = state
    return out


def gps_availability(
    gen: torch.Generator, times: Tensor, cold_start: Tensor, blockage_prob: Tensor, *, gps_interval: float, outage_window: float
) -> tuple[Tensor, Tensor]:
    """p002's GPS availability at step events ``times [B, T + 1]`` (event 0 = the start): fixes at
    ``cold_start + j gps_interval``, reported at the first event after them; time cut into
    ``outage_window`` windows, each blocked with probability ``blockage_prob [B]``, which loses
    the fixes inside it.  Returns ``gps_ok [B, T]`` (a fresh, unblocked fix at events ``1..T``)
    and ``blocked [B, T]`` (the event lies in a blocked window)."""
    B = times.shape[0]

    def fixes_until(t: Tensor) -> Tensor:  # the fix count up to time t
        k = torch.floor((t - cold_start[:, None]) / gps_interval) + 1.0
        return k.clamp_min(0.0)

    count = fixes_until(times)
    fresh = count[:, 1:] > count[:, :-1]
    fix_time = cold_start[:, None] + (count[:, 1:] - 1.0).clamp_min(0.0) * gps_interval
    num_windows = int(torch.floor(times.max() / outage_window).item()) + 2
    window_blocked = torch.rand(B, num_windows, generator=gen, dtype=torch.float64) < blockage_prob[:, None]
    win = lambda t: torch.floor(t / outage_window).long().clamp(0, num_windows - 1)  # noqa: E731
    fix_blocked = torch.gather(window_blocked, 1, win(fix_time))
    blocked = torch.gather(window_blocked, 1, win(times[:, 1:]))
    return fresh & ~fix_blocked, blocked


def _simulate(
    gen: torch.Generator,
    *,
    batch_size: int,
    num_steps: int,
    dtype: torch.dtype,
    track: Track,
    blockage_prob: Tensor,
    cadence: Tensor,
    step_lo: Tensor,
    step_hi: Tensor,
    gyro_bias: Tensor,
    cold_start: Tensor,
    heading_offset: Tensor,
    mirror: Tensor,
    interference: Tensor,
    gyro_arw: float,
    compass_std: float,
    compass_correlated_std: float,
    compass_corr_time: float,
    interference_std: float,
    interference_burst_rate: float,
    interference_burst_min: float,
    interference_burst_max: float,
    turn_scale_std: float,
    turn_threshold: float,
    gps_std: float,
    gps_interval: float,
    outage_window: float,
    step_scale_std: float,
    step_noise_std: float,
    initial_position_std: float,
    initial_heading_std: float,
) -> PDRScenario:
    B, T = batch_size, num_steps
    f64 = {"dtype": torch.float64}
    u = lambda *shape: torch.rand(shape, generator=gen, **f64)  # noqa: E731
    n = lambda *shape: torch.randn(shape, generator=gen, **f64)  # noqa: E731

    # Walking: lengths[:, j] is the step from event j to j + 1; T + 1 of them so that the truth
    # L at the last event (the length of the step that would follow) exists.
    lengths = step_lo[:, None] + (step_hi - step_lo)[:, None] * u(B, T + 1)
    arc = torch.cat([torch.zeros(B, 1, **f64), lengths[:, :T].cumsum(1)], 1)  # [B, T+1]
    periods = (1.0 + 0.05 * n(B, T)).clamp(0.5, 1.5) / cadence[:, None]
    times = torch.cat([torch.zeros(B, 1, **f64), periods.cumsum(1)], 1)

    e_loc, n_loc, psi_loc = track.sample(arc)
    sign = torch.where(mirror, -1.0, 1.0)[:, None]
    e_loc, psi = sign * e_loc, heading_offset[:, None] + sign * psi_loc
    ca, sa = torch.cos(heading_offset)[:, None], torch.sin(heading_offset)[:, None]
    east, north = e_loc * ca + n_loc * sa, -e_loc * sa + n_loc * ca
    truth = torch.stack([east[:, 1:], north[:, 1:], lengths[:, 1:], psi[:, 1:]], -1)
    initial_state = torch.stack([east[:, 0], north[:, 0], lengths[:, 0], psi[:, 0]], -1)

    dpsi = psi.diff(dim=1)
    dtheta = dpsi + gyro_bias[:, None] * periods + gyro_arw * periods.sqrt() * n(B, T)
    if turn_scale_std > 0.0:
        dtheta = dtheta + turn_heading_error(gen, dpsi, turn_scale_std, turn_threshold)

    white_std = math.sqrt(max(compass_std**2 - compass_correlated_std**2, 0.0))
    err = _gauss_markov(gen, periods, torch.full((B,), compass_correlated_std, **f64), compass_corr_time) + white_std * n(B, T)
    s_evt = arc[:, 1:]
    inside = (s_evt >= interference[:, :1]) & (s_evt < interference[:, 1:])
    if interference_burst_rate > 0.0:
        inside = inside | arc_bursts(gen, s_evt, interference_burst_rate, (interference_burst_min, interference_burst_max))
    err = err + inside * _gauss_markov(gen, periods, torch.full((B,), interference_std, **f64), 3.0)
    compass_raw = wrap_angle(psi[:, 1:] + err)

    mean_step = 0.5 * (step_lo + step_hi)
    init_mean = torch.stack(
        [
            east[:, 0] + initial_position_std * n(B),
            north[:, 0] + initial_position_std * n(B),
            mean_step,
            psi[:, 0] + initial_heading_std * n(B),
        ],
        -1,
    )
    reference = init_mean[:, 3:4] + dtheta.cumsum(1)
    compass = reference + wrap_angle(compass_raw - reference)

    gps_ok, blocked = gps_availability(gen, times, cold_start, blockage_prob, gps_interval=gps_interval, outage_window=outage_window)
    gps = truth[..., :2] + gps_std * n(B, T, 2)
    gps = torch.where(gps_ok[..., None], gps, torch.full_like(gps, float("nan")))

    measurements = torch.cat([gps, compass[..., None]], -1)
    mask = torch.stack([gps_ok, gps_ok, torch.ones_like(gps_ok)], -1)
    scale = 1.0 + step_scale_std * n(B)
    step_est = lengths[:, :T] * scale[:, None] + step_noise_std * n(B, T)

    var0 = torch.tensor([initial_position_std**2, initial_position_std**2, 0.1**2, initial_heading_std**2], **f64)
    to = lambda x: x.to(dtype)  # noqa: E731
    return PDRScenario(
        truth=to(truth),
        measurements=to(measurements),
        mask=mask,
        controls={"dtheta": to(dtheta[..., None]), "dt": to(periods[..., None]), "step_length": to(step_est[..., None])},
        times=to(times[:, 1:]),
        initial_state=to(initial_state),
        initial_mean=to(init_mean),
        initial_cov=to(torch.diag(var0)),
        blocked=blocked,
        blockage_prob=to(blockage_prob),
        gyro_bias=to(gyro_bias),
        compass_raw=to(compass_raw),
        dt=float((1.0 / cadence).mean()),
        params={
            "gps_std": gps_std,
            "compass_std": compass_std,
            "interference_std": interference_std,
            "gyro_arw": gyro_arw,
            "gps_interval": gps_interval,
            "outage_window": outage_window,
        },
    )


def _defaults(**kw: float) -> dict[str, float]:
    out = {
        "gyro_arw": math.radians(0.5),
        "compass_std": math.radians(11.4),
        "compass_correlated_std": math.radians(8.0),
        "compass_corr_time": 10.0,
        "interference_std": math.radians(math.sqrt(49.7**2 - 11.4**2)),
        "interference_burst_rate": 0.0,
        "interference_burst_min": 5.0,
        "interference_burst_max": 20.0,
        "turn_scale_std": 0.0,
        "turn_threshold": math.radians(0.5),
        "gps_std": 2.67,
        "gps_interval": 1.0,
        "outage_window": 5.0,
        "step_scale_std": 0.03,
        "step_noise_std": 0.03,
        "initial_position_std": 1.0,
        "initial_heading_std": math.radians(10.0),
    }
    out.update(kw)
    return out


def simulate_p002(
    batch_size: int = 10,
    *,
    blockage_prob: float | Sequence[float] | Tensor = 0.2,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype = torch.float64,
    num_steps: int | None = None,
    cadence: float = 1.8,
    step_length_range: tuple[float, float] = (0.6, 0.8),
    gyro_bias_deg_per_h: tuple[float, float] = (40.0, 80.0),
    cold_start_delay: float = 5.0,
    interference: tuple[float, float] | None = None,
    heading_offset: float = 0.0,
    **sensor: float,
) -> PDRScenario:
    """The p002 walk (paper settings): ``batch_size`` runs of the 360 m path at outage
    probability ``blockage_prob`` (scalar or one per run).

    Args:
        num_steps: steps per run; default ``round(360 / mean step length)`` (514).
        gyro_bias_deg_per_h: range of the bias magnitude (sign random).
        cold_start_delay: time of the first GPS fix (s).
        interference: arc-length window ``(s0, s1)`` (m) of compass interference, or ``None``.
        heading_offset: rotation of the whole path (rad, clockwise).
        **sensor: overrides of ``gyro_arw`` (rad/sqrt(s)), ``compass_std``,
            ``compass_correlated_std``, ``interference_std`` (rad), ``compass_corr_time`` (s),
            ``interference_burst_rate`` (compass-interference bursts per metre walked, each
            ``U(interference_burst_min, interference_burst_max)`` m long: :func:`arc_bursts`),
            ``turn_scale_std`` (relative error of the gyro's heading change over each turn) and
            ``turn_threshold`` (rad per step: what counts as turning; :func:`turn_heading_error`),
            ``gps_std`` (m, per axis), ``gps_interval``, ``outage_window`` (s),
            ``step_scale_std``, ``step_noise_std``, ``initial_position_std`` (m),
            ``initial_heading_std`` (rad).
    """
    gen = generator(seed)
    track = p002_track()
    lo, hi = step_length_range
    steps = num_steps if num_steps is not None else round(track.length / (0.5 * (lo + hi)))
    B, f64 = batch_size, {"dtype": torch.float64}
    bmin, bmax = (math.radians(v) / 3600.0 for v in gyro_bias_deg_per_h)
    sign = torch.where(torch.rand(B, generator=gen, **f64) < 0.5, -1.0, 1.0)
    bias = sign * (bmin + (bmax - bmin) * torch.rand(B, generator=gen, **f64))
    window = torch.full((B, 2), float("nan"), **f64) if interference is None else torch.tensor([interference], **f64).expand(B, 2)
    return _simulate(
        gen,
        batch_size=B,
        num_steps=steps,
        dtype=dtype,
        track=track,
        blockage_prob=_per_trajectory(blockage_prob, B, "blockage_prob"),
        cadence=torch.full((B,), cadence, **f64),
        step_lo=torch.full((B,), lo, **f64),
        step_hi=torch.full((B,), hi, **f64),
        gyro_bias=bias,
        cold_start=torch.full((B,), cold_start_delay, **f64),
        heading_offset=torch.full((B,), heading_offset, **f64),
        mirror=torch.zeros(B, dtype=torch.bool),
        interference=window,
        **_defaults(**sensor),  # type: ignore[arg-type]
    )


def simulate_p002_random(
    batch_size: int = 32,
    *,
    seed: int | torch.Generator = 0,
    dtype: torch.dtype = torch.float64,
    num_steps: int = 514,
    blockage_probs: Sequence[float] = BLOCKAGE_PROBS,
    interference_prob: float = 0.3,
    **sensor: float,
) -> PDRScenario:
    """Randomised p002 walks for training sets: per run a random rotation (uniform) and
    direction (mirrored with probability 1/2) of the path, cadence ``U(1.6, 2.0)`` steps/s,
    step lengths ``U(c - 0.1, c + 0.1)`` with ``c ~ U(0.65, 0.75)`` m, gyro bias magnitude
    ``U(40, 100)`` deg/h, cold start ``U(3, 8)`` s, ``P`` drawn from ``blockage_probs`` and,
    with probability ``interference_prob``, a 40 m compass-interference stretch.  ``sensor``
    overrides as in :func:`simulate_p002`."""
    gen = generator(seed)
    B, f64 = batch_size, {"dtype": torch.float64}
    u = lambda *shape: torch.rand(shape, generator=gen, **f64)  # noqa: E731
    probs = torch.as_tensor(list(blockage_probs), **f64)
    p = probs[torch.randint(len(probs), (B,), generator=gen)]
    center = 0.65 + 0.1 * u(B)
    bias = torch.where(u(B) < 0.5, -1.0, 1.0) * torch.deg2rad(40.0 + 60.0 * u(B)) / 3600.0
    start = 320.0 * u(B)
    has = u(B) < interference_prob
    window = torch.where(has[:, None], torch.stack([start, start + 40.0], -1), torch.full((B, 2), float("nan"), **f64))
    return _simulate(
        gen,
        batch_size=B,
        num_steps=num_steps,
        dtype=dtype,
        track=p002_track(),
        blockage_prob=p,
        cadence=1.6 + 0.4 * u(B),
        step_lo=center - 0.1,
        step_hi=center + 0.1,
        gyro_bias=bias,
        cold_start=3.0 + 5.0 * u(B),
        heading_offset=math.pi * (2.0 * u(B) - 1.0),
        mirror=u(B) < 0.5,
        interference=window,
        **_defaults(**sensor),  # type: ignore[arg-type]
    )
