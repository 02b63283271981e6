"""p003's flight: the phase schedule, its kinematics, and the numpy strapdown mechanisation
helpers of the simulator (float64; arrays ``[..., 3]`` / ``[..., 3, 3]``), plus the GNSS
pseudorange differences INS - truth (see :mod:`experiments.papers.p003.simulator`)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from difffilter import geometry as geo

__all__ = [
    "LOAD_LIMITS",
    "P003_CONFIG",
    "PAPER_PHASES",
    "attitude_matrix",
    "clock_discrete",
    "flight_profile",
    "frame_terms",
    "gnss_differences",
    "manoeuvre_flags",
    "markov_phases",
    "position_step",
    "random_phases",
    "rotation_exp",
    "rotation_log",
]

#: (start s, end s, kind, magnitude): accelerate -> delta-V (m/s), climb/descend -> peak flight-path
#: angle (deg), turn -> heading change (deg, left negative).  Times from the paper; magnitudes chosen.
PAPER_PHASES: tuple[tuple[float, float, str, float], ...] = (
    (0, 10, "static", 0.0),
    (10, 20, "accelerate", 60.0),
    (20, 60, "level", 0.0),
    (60, 90, "climb", 10.0),
    (90, 150, "level", 0.0),
    (150, 160, "accelerate", 40.0),
    (160, 500, "level", 0.0),
    (500, 520, "turn", -60.0),
    (520, 1000, "level", 0.0),
    (1000, 1020, "turn", 60.0),
    (1020, 1200, "level", 0.0),
    (1200, 1220, "climb", 10.0),
    (1220, 1500, "level", 0.0),
    (1500, 1515, "climb", -10.0),
    (1515, 1800, "level", 0.0),
)

_E2, _A, _W = geo.WGS84_E2, geo.WGS84_A, geo.EARTH_RATE


P003_CONFIG: dict[str, float] = {
    "lat_deg": 32.0209,  # [fix] the paper swaps E/N
    "lon_deg": 118.7667,
    "height": 0.0,
    "heading_deg": 135.0,
    "duration": 1800.0,
    "gyro_constant_dph": 0.1,  # deg/h, 1-sigma per axis
    "gyro_markov_dph": 0.1,
    "gyro_markov_time": 3600.0,
    "gyro_white_dph": 0.01,  # std of 1 Hz samples
    "accel_bias_mg": 0.1,  # first-order Markov, 1-sigma
    "accel_markov_time": 3600.0,
    "accel_white_mg": 0.1,
    "init_attitude_deg": 0.1,
    "init_position": 30.0,  # m per axis
    "init_velocity": 0.5,  # m/s per axis
    "clock_bias": 100.0,  # m, "clock-equivalent pseudorange error"
    "clock_drift": 1.0,  # m/s (not in the paper)
    "clock_time": 3600.0,
    "clock_bias_psd": 0.01,  # m^2/s (TCXO, see experiments.papers.p003.sins.sins_noise_psd)
    "clock_drift_psd": 0.04,  # m^2/s^3
    "sigma_range": 3.0,  # m (not in the paper)
    "sigma_rate": 0.05,  # m/s
    "elevation_mask_deg": 5.0,
}


def rotation_exp(v: np.ndarray) -> np.ndarray:
    """Rodrigues ``exp([v x]) = cos(t) I + sin(t)/t [v x] + (1 - cos t)/t^2 v v^T`` for ``v [..., 3]``."""
    th = np.sqrt((v * v).sum(-1))
    small = th < 1e-4
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    r = b[..., None, None] * v[..., :, None] * v[..., None, :]
    c = np.cos(th)
    av = a[..., None] * v
    x, y, z = av[..., 0], av[..., 1], av[..., 2]
    r[..., 0, 0] += c
    r[..., 1, 1] += c
    r[..., 2, 2] += c
    r[..., 0, 1] -= z
    r[..., 0, 2] += y
    r[..., 1, 0] += z
    r[..., 1, 2] -= x
    r[..., 2, 0] -= y
    r[..., 2, 1] += x
    return r


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector of ``r`` (angles well below pi)."""
    c = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    vee = 0.5 * np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    s = np.sin(th)
    f = np.where(th < 1e-6, 1.0 + th**2 / 6.0, th / np.where(th < 1e-6, 1.0, s))
    return vee * f[..., None]


def frame_terms(llh: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``w_in = w_ie + w_en`` (ENU), ``g^n - (2 w_ie + w_en) x v`` and the radii ``R_M + h``,
    ``R_N + h``: everything one mechanisation step needs at ``(llh, v)``."""
    lat, h = llh[..., 0], llh[..., 2]
    sl, cl = np.sin(lat), np.cos(lat)
    q = 1.0 - _E2 * sl * sl
    rn0 = _A / np.sqrt(q)
    rm, rn = rn0 * (1.0 - _E2) / q + h, rn0 + h
    ve, vn, vu = v[..., 0], v[..., 1], v[..., 2]
    wx, wy, wz = -vn / rm, _W * cl + ve / rn, _W * sl + ve * sl / (cl * rn)
    ax, ay, az = wx, wy + _W * cl, wz + _W * sl  # 2 w_ie + w_en
    s2 = sl * sl
    g = 9.7803267714 * (1.0 + 5.27094e-3 * s2 + 2.32718e-5 * s2 * s2) - 3.086e-6 * h
    acc = np.stack([-(ay * vu - az * vn), -(az * ve - ax * vu), -(ax * vn - ay * ve) - g], -1)
    return np.stack([wx, wy, wz], -1), acc, rm, rn


def position_step(llh: np.ndarray, v0: np.ndarray, v1: np.ndarray, dt: float, rm: np.ndarray, rn: np.ndarray) -> np.ndarray:
    vm = 0.5 * (v0 + v1)
    return llh + np.stack([vm[..., 1] / rm, vm[..., 0] / (rn * np.cos(llh[..., 0])), vm[..., 2]], -1) * dt


def attitude_matrix(psi: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Body (right, forward, up) to ENU: ``R_z(-psi) R_x(pitch) R_y(roll)``."""
    cz, sz, cx, sx, cy, sy = np.cos(-psi), np.sin(-psi), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    o, z = np.ones_like(psi), np.zeros_like(psi)
    rz = np.stack([np.stack([cz, -sz, z], -1), np.stack([sz, cz, z], -1), np.stack([z, z, o], -1)], -2)
    rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cx, -sx], -1), np.stack([z, sx, cx], -1)], -2)
    ry = np.stack([np.stack([cy, z, sy], -1), np.stack([z, o, z], -1), np.stack([-sy, z, cy], -1)], -2)
    return rz @ rx @ ry


#: Load limits of the randomised schedules (m/s^2): longitudinal 0.5 g, lateral g tan(50 deg) (a
#: 50 deg coordinated bank, the paper profile's turns reach 47 deg) and normal 0.5 g.  A manoeuvre is
#: stretched until its ``sin^2`` peak stays inside them.
LOAD_LIMITS: dict[str, float] = {"accelerate": 0.5 * 9.80665, "turn": 9.80665 * math.tan(math.radians(50.0)), "climb": 0.5 * 9.80665}


def _min_duration(kind: str, mag: float, speed: float) -> float:
    """Shortest duration (s) of a ``sin^2`` manoeuvre of magnitude ``mag`` at ``speed`` within
    :data:`LOAD_LIMITS`: peaks ``2 dV / d``, ``2 V dpsi / d`` and ``pi V gamma / d``."""
    if kind == "accelerate":
        return 2.0 * abs(mag) / LOAD_LIMITS[kind]
    if kind == "turn":
        return 2.0 * max(speed, 1.0) * math.radians(abs(mag)) / LOAD_LIMITS[kind]
    return math.pi * max(speed, 1.0) * math.radians(abs(mag)) / LOAD_LIMITS[kind]


def random_phases(rng: np.random.Generator, duration: float) -> list[tuple[float, float, str, float]]:
    """A random schedule from rest: 10 s static, a take-off acceleration to 50-90 m/s, then level
    segments of 20-200 s between manoeuvres (speed change, climb/descent of 4-12 deg or turn of
    30-120 deg) of 10-30 s, each stretched to stay inside :data:`LOAD_LIMITS`.  A manoeuvre that
    would run past ``duration`` is replaced by level flight, so the schedule ends there."""
    phases: list[tuple[float, float, str, float]] = [(0.0, 10.0, "static", 0.0)]
    speed, t = 0.0, 10.0
    first = True
    while t < duration:
        if first:
            d, kind, mag = float(rng.uniform(10, 20)), "accelerate", float(rng.uniform(50, 90))
            first = False
        else:
            d = float(rng.uniform(20, 200))
            phases.append((t, min(t + d, duration), "level", 0.0))
            t += d
            if t >= duration:
                break
            kind = str(rng.choice(["accelerate", "climb", "turn"]))
            d = float(rng.uniform(10, 30))
            if kind == "accelerate":
                mag = float(rng.uniform(-40, 40))
                mag = float(np.clip(speed + mag, 40.0, 200.0) - speed)
            elif kind == "climb":
                mag = float(rng.choice([-1, 1]) * rng.uniform(4, 12))
            else:
                mag = float(rng.choice([-1, 1]) * rng.uniform(30, 120))
        d = max(d, _min_duration(kind, mag, speed))
        if t + d > duration:
            phases.append((t, duration, "level", 0.0))
            break
        phases.append((t, t + d, kind, mag))
        speed += mag if kind == "accelerate" else 0.0
        t += d
    return phases


def markov_phases(
    rng: np.random.Generator, duration: float, *, p_enter: float, p_leave: float, speed: float
) -> list[tuple[float, float, str, float]]:
    """An airborne schedule (cruise at ``speed`` from ``t = 0``) whose 1 Hz manoeuvre flags are a
    two-state Markov chain: level segments last ``Geometric(p_enter)`` whole seconds, manoeuvres
    ``Geometric(p_leave)`` (so ``P(manoeuvre at k+1 | level at k) = p_enter`` and
    ``P(level at k+1 | manoeuvre at k) = p_leave`` exactly, starting level).  Each manoeuvre
    (speed change, climb/descent or turn, equally likely) gets a magnitude of 30-100 % of what
    :data:`LOAD_LIMITS` allow in its duration (speed kept in 60-200 m/s, climbs within 12 deg,
    turns within 180 deg).  The last phase may end after ``duration``."""
    for name, p in (("p_enter", p_enter), ("p_leave", p_leave)):
        if not 0.0 < p <= 1.0:
            raise ValueError(f"{name} must lie in (0, 1], got {p}")
    phases: list[tuple[float, float, str, float]] = []
    t, v = 0.0, float(speed)
    while t < duration:
        d = float(rng.geometric(p_enter))
        phases.append((t, t + d, "level", 0.0))
        t += d
        if t >= duration:
            break
        d = float(rng.geometric(p_leave))
        kind, u, sign = str(rng.choice(["accelerate", "climb", "turn"])), float(rng.uniform(0.3, 1.0)), float(rng.choice([-1.0, 1.0]))
        if kind == "accelerate":
            mag = float(np.clip(v + sign * u * LOAD_LIMITS[kind] * d / 2.0, 60.0, 200.0) - v)
        elif kind == "turn":
            mag = sign * min(180.0, u * math.degrees(LOAD_LIMITS[kind] * d / (2.0 * v)))
        else:
            mag = sign * min(12.0, u * math.degrees(LOAD_LIMITS[kind] * d / (math.pi * v)))
        phases.append((t, t + d, kind, mag))
        v += mag if kind == "accelerate" else 0.0
        t += d
    return phases


def flight_profile(phases: list[tuple[float, float, str, float]], t: np.ndarray, psi0: float, speed0: float = 0.0) -> dict[str, np.ndarray]:
    """Truth kinematics on the time grid ``t [N]`` (s) for a phase list like :data:`PAPER_PHASES`:
    ``speed`` (m/s, starting at ``speed0``), ``psi`` heading (rad, clockwise from north, starting
    at ``psi0``), ``psid`` its rate and ``gamma`` flight-path angle (rad).  Each manoeuvre has a
    ``sin^2`` profile."""
    speed, psi, psid, gamma = np.full_like(t, speed0), np.full_like(t, psi0), np.zeros_like(t), np.zeros_like(t)
    for t0, t1, kind, mag in phases:
        d = t1 - t0
        tau = np.clip((t - t0) / d, 0.0, 1.0)
        inside = (t > t0) & (t < t1)
        ramp = tau - np.sin(2 * np.pi * tau) / (2 * np.pi)  # integral of 2 sin^2(pi tau)
        bump = np.where(inside, np.sin(np.pi * tau) ** 2, 0.0)
        if kind == "accelerate":
            speed += mag * ramp
        elif kind == "turn":
            psi += math.radians(mag) * ramp
            psid += math.radians(mag) / d * 2.0 * bump
        elif kind == "climb":
            gamma += math.radians(mag) * bump
    return {"speed": speed, "psi": psi, "psid": psid, "gamma": gamma}


def manoeuvre_flags(phases: list[tuple[float, float, str, float]], t: np.ndarray) -> np.ndarray:
    """True where ``t`` lies strictly inside a phase other than ``static``/``level``."""
    out = np.zeros(t.shape, dtype=bool)
    for t0, t1, kind, _ in phases:
        if kind not in ("static", "level"):
            out |= (t > t0) & (t < t1)
    return out


def clock_discrete(dt: float, tau: float, qb: float, qd: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact (Van Loan) discretisation of ``b' = d + w_b``, ``d' = -d/tau + w_d``."""
    f = torch.tensor([[0.0, 1.0], [0.0, -1.0 / tau]], dtype=torch.float64)
    q = torch.diag(torch.tensor([qb, qd], dtype=torch.float64))
    m = torch.zeros(4, 4, dtype=torch.float64)
    m[:2, :2], m[:2, 2:], m[2:, 2:] = -f, q, f.T
    e = torch.linalg.matrix_exp(m * dt)
    phi = e[2:, 2:].T
    return phi.numpy(), (phi @ e[:2, 2:]).numpy()


def gnss_differences(
    ins_llh: Tensor, ins_vel: Tensor, t_llh: Tensor, t_vel: Tensor, sp: Tensor, sv: Tensor, clock: Tensor
) -> tuple[Tensor, Tensor]:
    """Noise-free ``drho, drhodot [..., K]`` for INS/true ``llh, vel [..., 3]``, satellites
    ``sp, sv [..., K, 3]`` and clock ``[..., 2]`` (see the module docstring)."""
    p_ins, p_true = geo.geodetic_to_ecef(ins_llh), geo.geodetic_to_ecef(t_llh)
    ci = geo.enu_rotation(ins_llh[..., 0], ins_llh[..., 1])
    ct = geo.enu_rotation(t_llh[..., 0], t_llh[..., 1])
    vi_e = (ins_vel[..., None, :] @ ci)[..., 0, :]
    vt_e = (t_vel[..., None, :] @ ct)[..., 0, :]
    a, b = p_ins[..., None, :] - sp, p_true[..., None, :] - sp
    na, nb = a.norm(dim=-1), b.norm(dim=-1)
    drho = na - nb - clock[..., 0, None]
    rate = (a * (vi_e[..., None, :] - sv)).sum(-1) / na - (b * (vt_e[..., None, :] - sv)).sum(-1) / nb - clock[..., 1, None]
    return drho, rate
