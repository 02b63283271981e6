"""p003 flight simulator: 1800 s aircraft profile, strapdown INS errors, GPS pseudorange differences.

How the truth is produced (nothing is sampled from the filter's error model):

1. A scripted flight (:data:`PAPER_PHASES`, or a random schedule) defines speed ``V``, heading
   ``psi`` (clockwise from north), flight-path angle ``gamma`` on a fine grid (``imu_rate`` Hz).
   Every manoeuvre uses a ``sin^2`` shape, so accelerations and rates are continuous.  Attitude:
   pitch = ``gamma``, coordinated-turn roll ``atan(V psi' / g)``; body axes right-forward-up.
2. One strapdown mechanisation step (ENU, :mod:`~experiments.papers.p003.flight`) is applied to the truth: the true
   positions are integrated with it, and the true IMU increments (``dtheta``, ``dv`` in body axes)
   are obtained by *inverting* it, so error-free sensors reproduce the truth to rounding.
3. The INS runs the same mechanisation from perturbed initial conditions with corrupted increments:
   gyro constant drift + first-order Markov drift + white noise, accelerometer Markov bias + white
   noise (p003's values).  The 20-state error truth is INS minus truth (phi-angle from the attitude
   matrices), sampled at 1 Hz, and the clock follows its own two-state model.
4. Satellites: :class:`~experiments.papers.constellation.CircularOrbitConstellation` (24 satellites, 6 planes),
   the ``K`` with the highest minimum elevation over the flight; slots below 5 deg are masked.
   Measurements ``drho = |p_INS - s| - (|p_true - s| + dt_u + v)`` and
   ``drhodot = e_I.(v_INS - s') - (e_G.(v_true - s') + dt_ru + v')``.

Sensor noise (``noise``, :mod:`~experiments.papers.p003.noise`): ``"nominal"`` keeps p003's values
throughout (the paper-faithful scenario: the paper describes no noise change); ``"modes"`` raises
the IMU and GNSS noise by fixed factors during manoeuvres (two-level, the IMM's family);
``"physical"`` scales the IMU noise with the manoeuvre load and each satellite's GNSS noise with
its C/N0 behind a body-fixed antenna (masking satellites that lose lock).  ``imu_noise_scale`` and
``gnss_noise_scale`` record the multipliers that were applied.

Option ``feedback="imm"`` (closed-loop integration, as a GPS/SINS navigation computer runs it): at
every 1 Hz epoch a reference error-state filter inside the simulator (p003's hand-tuned two-mode IMM
of simplified UKFs, :func:`reference_imm`) processes that epoch's measurements, and its estimated
position, velocity and attitude errors are subtracted from the INS solution (the sensor-error states
are not fed back).  The INS errors then stay at the GNSS level instead of drifting freely (the
0.1 deg initial tilt alone drives a Schuler oscillation of ~10 km), so the linear error model stays
valid.  Controls get ``"feedback" [B, T, 20]``: the correction applied at the previous epoch, which
:class:`~experiments.papers.p003.sins.SinsErrorDynamics` subtracts (``x_k = Phi (x_{k-1} - c_{k-1})``), so
any filter under test sees the same corrected INS and knows the corrections.  ``truth``, the
measurements and the INS controls at epoch ``k`` are *before* that epoch's correction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from difffilter import geometry as geo
from difffilter._util import generator
from experiments.papers import constellation as sky

from .flight import (
    P003_CONFIG,
    PAPER_PHASES,
    attitude_matrix,
    clock_discrete,
    flight_profile,
    frame_terms,
    gnss_differences,
    manoeuvre_flags,
    markov_phases,
    position_step,
    random_phases,
    rotation_exp,
    rotation_log,
)
from .model import reference_imm
from .noise import NOISE_DEFAULTS, NOISE_FAMILIES, antenna_gain_db, body_elevation, cn0_sigma_scale, vibration_scale

__all__ = ["P003Scenario", "simulate_p003"]


@dataclass
class P003Scenario:
    """Simulated flights (batch-first, 1 Hz, ``T = duration`` steps at ``t_k = k`` s).

    ``truth [B, T, 20]`` error state (``experiments.papers.p003.sins`` layout), ``measurements [B, T, 2K]``
    (``[drho, drhodot]``), ``mask [B, T, 2K]``, ``controls`` (``llh, vel, f_n, C_bn, dt, sat_pos,
    sat_vel``), ``manoeuvre [B, T]`` (step ``k`` inside a manoeuvre phase), ``initial_mean [B, 20]``
    (zeros), ``initial_cov [20, 20]``, ``initial_truth [B, 20]`` (the error at ``t = 0``),
    ``nav_truth`` (``llh, vel, euler`` ``[B, T, 3]``; euler = heading, pitch, roll), ``phases`` per
    batch element, ``config``; ``imu_noise_scale [B, T]`` (rms over the step of the IMU white-noise
    sigma multiplier), ``gnss_noise_scale [B, T, K]`` (sigma multiplier of each satellite's range and
    rate noise) and ``cn0 [B, T, K]`` (dB-Hz; the nominal value except for ``noise="physical"``).
    """

    truth: Tensor
    measurements: Tensor
    mask: Tensor
    controls: dict[str, Tensor]
    manoeuvre: Tensor
    initial_mean: Tensor
    initial_cov: Tensor
    initial_truth: Tensor
    nav_truth: dict[str, Tensor]
    times: Tensor
    dt: float
    phases: list[list[tuple[float, float, str, float]]]
    config: dict[str, float] = field(default_factory=dict)
    imu_noise_scale: Tensor | None = None
    gnss_noise_scale: Tensor | None = None
    cn0: Tensor | None = None


def _feed_back(
    ref: torch.nn.Module,
    belief: dict[str, Tensor],
    k: int,
    ins_llh: np.ndarray,
    ins_v: np.ndarray,
    ins_c: np.ndarray,
    f_n: np.ndarray,
    fb: np.ndarray,
    z_out: Tensor,
    vis2: Tensor,
    t_llh: Tensor,
    t_vel: Tensor,
    sp: Tensor,
    sv: Tensor,
    clock: Tensor,
    range_noise: Tensor,
    rate_noise: Tensor,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Tensor]]:
    """One closed-loop epoch ``k >= 1``: measure with the (uncorrected) INS, run the reference filter
    (which subtracts the previous correction ``fb[:, k - 1]`` itself), record its position/velocity/
    attitude estimate as ``fb[:, k]`` (metres) and return the corrected INS state and the belief."""
    llh_t, vel_t = torch.from_numpy(ins_llh), torch.from_numpy(ins_v)
    drho, rate = gnss_differences(llh_t, vel_t, t_llh, t_vel, sp[:, k], sv[:, k], clock[:, k])
    z = torch.cat([drho - range_noise[:, k - 1], rate - rate_noise[:, k - 1]], -1)
    z_out[:, k - 1] = z
    bsz = ins_llh.shape[0]
    u = {
        "llh": llh_t, "vel": vel_t, "f_n": torch.from_numpy(f_n), "C_bn": torch.from_numpy(ins_c),
        "dt": torch.ones(bsz, 1, dtype=torch.float64), "sat_pos": sp[:, k], "sat_vel": sv[:, k],
        "feedback": torch.from_numpy(fb[:, k - 1]),
    }  # fmt: skip
    with torch.no_grad():
        belief, _, _ = ref.step(belief, z, vis2[:, k - 1], u)
    c = belief["mean"].numpy()
    fb[:, k, :9] = c[:, :9]
    _, _, rm, rn = frame_terms(ins_llh, ins_v)
    dllh = np.stack([c[:, 0] / rm, c[:, 1] / (rn * np.cos(ins_llh[:, 0])), c[:, 2]], -1)
    return ins_llh - dllh, ins_v - c[:, 3:6], rotation_exp(c[:, 6:9]) @ ins_c, belief


def simulate_p003(
    batch_size: int = 1,
    seed: int | torch.Generator | None = 0,
    dtype: torch.dtype = torch.float64,
    *,
    profile: str = "paper",
    duration: float | None = None,
    imu_rate: int = 10,
    num_satellites: int = 8,
    noise: str = "nominal",
    sensor_errors: bool = True,
    imu_noise: bool = True,
    initial_errors: bool = True,
    measurement_noise: bool = True,
    position_in_metres: bool = False,
    feedback: str = "none",
    config: dict[str, float] | None = None,
) -> P003Scenario:
    """Simulate ``batch_size`` flights (see the module docstring).

    Args:
        profile: ``"paper"`` (:data:`PAPER_PHASES` from 32.0209 N, 118.7667 E, heading 135 deg,
            fixed satellite geometry), ``"random"`` (:func:`~experiments.papers.p003.flight.random_phases`
            from rest, random start point, heading and satellite geometry per batch element) or
            ``"markov"`` (as random, but airborne at 60-150 m/s with the Markov schedule of
            :func:`~experiments.papers.p003.flight.markov_phases`, ``config`` keys ``markov_enter``,
            ``markov_leave``).
        duration: seconds (default 1800); the paper profile is cut there.
        noise: ``"nominal"``, ``"modes"`` or ``"physical"`` (module docstring; parameters in
            :data:`~experiments.papers.p003.noise.NOISE_DEFAULTS`, overridden by ``config``).
        sensor_errors / initial_errors / measurement_noise: switch off for tests (with both error
            switches off the INS equals the truth to rounding); ``imu_noise=False`` keeps the
            biases but drops the white noises and Markov driving noises (deterministic errors).
        position_in_metres: express truth and covariances in the ``experiments.papers.p003.sins`` metre layout.
        feedback: ``"none"`` (open-loop INS, free-inertial drift) or ``"imm"`` (closed loop, see
            the module docstring; adds ``controls["feedback"]``).
    """
    if feedback not in ("none", "imm"):
        raise ValueError(f"feedback must be 'none' or 'imm', got {feedback!r}")
    if noise not in NOISE_FAMILIES:
        raise ValueError(f"noise must be one of {NOISE_FAMILIES}, got {noise!r}")
    gen = generator(seed)
    cfg = {**P003_CONFIG, **NOISE_DEFAULTS, **(config or {})}
    dur = float(duration if duration is not None else cfg["duration"])
    steps, n_in = int(round(dur)), int(round(dur)) * imu_rate
    dti, bsz, k_sat = 1.0 / imu_rate, batch_size, num_satellites

    def randn(*shape: int) -> np.ndarray:
        return torch.randn(*shape, generator=gen, dtype=torch.float64).numpy()

    rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,), generator=gen)))
    tg = np.arange(n_in + 1) * dti
    if profile == "paper":
        phases = [list(PAPER_PHASES) for _ in range(bsz)]
        lat0 = np.full(bsz, math.radians(cfg["lat_deg"]))
        lon0 = np.full(bsz, math.radians(cfg["lon_deg"]))
        psi0 = np.full(bsz, math.radians(cfg["heading_deg"]))
        earth_angle, orbit_phase, speed0 = np.zeros(bsz), np.zeros(bsz), np.zeros(bsz)
    elif profile in ("random", "markov"):
        speed0 = np.zeros(bsz) if profile == "random" else rng.uniform(60.0, 150.0, bsz)
        if profile == "random":
            phases = [random_phases(rng, dur) for _ in range(bsz)]
        else:
            kw = {"p_enter": cfg["markov_enter"], "p_leave": cfg["markov_leave"]}
            phases = [markov_phases(rng, dur, speed=float(v), **kw) for v in speed0]
        lat0, lon0 = np.radians(rng.uniform(-60, 60, bsz)), np.radians(rng.uniform(-180, 180, bsz))
        psi0, earth_angle, orbit_phase = rng.uniform(0, 2 * np.pi, (3, bsz))
    else:
        raise ValueError(f"profile must be 'paper', 'random' or 'markov', got {profile!r}")
    prof = [flight_profile(p, tg, float(s), float(v)) for p, s, v in zip(phases, psi0, speed0, strict=True)]
    speed, psi, psid, gamma = (np.stack([p[k] for p in prof]) for k in ("speed", "psi", "psid", "gamma"))
    vel = speed[..., None] * np.stack([np.cos(gamma) * np.sin(psi), np.cos(gamma) * np.cos(psi), np.sin(gamma)], -1)
    roll = np.arctan(speed * psid / 9.80665)
    c_true = attitude_matrix(psi, gamma, roll)  # [B, N+1, 3, 3]
    llh = np.zeros((bsz, n_in + 1, 3))
    llh[:, 0] = np.stack([lat0, lon0, np.full(bsz, cfg["height"])], -1)
    for i in range(n_in):
        _, _, rm_i, rn_i = frame_terms(llh[:, i], vel[:, i])
        llh[:, i + 1] = position_step(llh[:, i], vel[:, i], vel[:, i + 1], dti, rm_i, rn_i)
    # true IMU increments: the mechanisation step inverted
    w_in, acc, _, _ = frame_terms(llh[:, :-1], vel[:, :-1])
    c0t = np.swapaxes(c_true[:, :-1], -1, -2)
    dtheta = rotation_log(c0t @ rotation_exp(w_in * dti) @ c_true[:, 1:])
    dvel = (c0t @ (vel[:, 1:] - vel[:, :-1] - acc * dti)[..., None])[..., 0]
    # sensor errors
    dph, mg = math.radians(1.0) / 3600.0, 9.80665e-3
    on = 1.0 if sensor_errors else 0.0
    man_in = np.stack([manoeuvre_flags(p, tg[:-1] + 0.5 * dti) for p in phases])
    if noise == "modes":
        imu_scale = np.where(man_in, cfg["mode_imu_scale"], 1.0)
    elif noise == "physical":
        imu_scale = vibration_scale((vel[:, 1:] - vel[:, :-1]) / dti, cfg["vibration_gain"])
    else:
        imu_scale = np.ones((bsz, n_in))
    noisy = on * float(imu_noise)
    white_scale = imu_scale[..., None] * math.sqrt(dti) * noisy
    eps_b = randn(bsz, 3) * cfg["gyro_constant_dph"] * dph * on
    eps_r = randn(bsz, 3) * cfg["gyro_markov_dph"] * dph * on
    nabla = randn(bsz, 3) * cfg["accel_bias_mg"] * mg * on
    gyro_w = randn(bsz, n_in, 3) * cfg["gyro_white_dph"] * dph * white_scale
    acc_w = randn(bsz, n_in, 3) * cfg["accel_white_mg"] * mg * white_scale
    drive = randn(bsz, n_in, 6) * noisy
    ag, aa = math.exp(-dti / cfg["gyro_markov_time"]), math.exp(-dti / cfg["accel_markov_time"])
    sg = cfg["gyro_markov_dph"] * dph * math.sqrt(1 - ag * ag)
    sa = cfg["accel_bias_mg"] * mg * math.sqrt(1 - aa * aa)
    # initial errors (north/east/up metres, m/s, rad)
    ie = 1.0 if initial_errors else 0.0
    d_neu = randn(bsz, 3) * cfg["init_position"] * ie
    d_v = randn(bsz, 3) * cfg["init_velocity"] * ie
    phi0 = randn(bsz, 3) * math.radians(cfg["init_attitude_deg"]) * ie
    _, _, rm0, rn0 = frame_terms(llh[:, 0], vel[:, 0])
    ins_llh = llh[:, 0] + np.stack([d_neu[:, 0] / rm0, d_neu[:, 1] / (rn0 * np.cos(llh[:, 0, 0])), d_neu[:, 2]], -1)
    ins_v, ins_c = vel[:, 0] + d_v, rotation_exp(-phi0) @ c_true[:, 0]
    # clock, satellites and measurement noise (drawn in this order, before the INS loop: the
    # closed loop needs each epoch's measurement inside it)
    phi_c, q_c = clock_discrete(1.0, cfg["clock_time"], cfg["clock_bias_psd"], cfg["clock_drift_psd"])
    lq, cn = np.linalg.cholesky(q_c), randn(bsz, steps, 2)
    clk = np.zeros((bsz, steps + 1, 2))
    clk[:, 0] = randn(bsz, 2) * np.array([cfg["clock_bias"], cfg["clock_drift"]])
    for k in range(steps):
        clk[:, k + 1] = clk[:, k] @ phi_c.T + cn[:, k] @ lq.T
    f64 = torch.float64
    ke = np.arange(steps + 1) * imu_rate
    t_llh, t_vel, t_c = llh[:, ke], vel[:, ke], c_true[:, ke]
    tt = torch.arange(steps + 1, dtype=f64).expand(bsz, steps + 1)
    sp, sv = sky.CircularOrbitConstellation().state(tt, torch.tensor(earth_angle)[:, None], torch.tensor(orbit_phase)[:, None])
    p_true = geo.geodetic_to_ecef(torch.from_numpy(t_llh))
    elev = geo.azimuth_elevation(p_true, sp)[1]
    best = torch.argsort(elev[:, 1:].amin(1), dim=-1, descending=True)[:, :k_sat]  # [B, K]
    pick = best[:, None, :, None].expand(bsz, steps + 1, k_sat, 3)
    sp, sv, elev = sp.gather(2, pick), sv.gather(2, pick), elev.gather(2, best[:, None].expand(bsz, steps + 1, k_sat))
    man = np.stack([manoeuvre_flags(p, np.arange(1, steps + 1) - 0.5) for p in phases])
    cn0 = np.full((bsz, steps, k_sat), cfg["cn0_nominal"])
    if noise == "modes":
        gnss_scale = np.broadcast_to(np.where(man, cfg["mode_gnss_scale"], 1.0)[..., None], cn0.shape).copy()
    elif noise == "physical":
        rot = geo.enu_rotation(torch.from_numpy(t_llh[:, 1:, 0]), torch.from_numpy(t_llh[:, 1:, 1])).numpy()
        los = ((sp[:, 1:] - p_true[:, 1:, None]).numpy()[..., None, :] @ np.swapaxes(rot, -1, -2)[:, :, None])[..., 0, :]
        gain = antenna_gain_db(body_elevation(los, t_c[:, 1:]), cfg["antenna_knee_deg"], cfg["antenna_slope_db"])
        cn0, gnss_scale = cn0 + gain, cn0_sigma_scale(gain)
    else:
        gnss_scale = np.ones(cn0.shape)
    nscale = torch.from_numpy(gnss_scale) * float(measurement_noise)
    range_noise = torch.from_numpy(randn(bsz, steps, k_sat)) * cfg["sigma_range"] * nscale
    rate_noise = torch.from_numpy(randn(bsz, steps, k_sat)) * cfg["sigma_rate"] * nscale
    vis = (elev[:, 1:] > math.radians(cfg["elevation_mask_deg"])) & torch.from_numpy(cn0 >= cfg["cn0_lock"])
    clock = torch.from_numpy(clk)
    closed = feedback == "imm"
    fb = np.zeros((bsz, steps + 1, 20))  # metres layout; fb[:, k] = correction applied at epoch k
    z_closed = torch.zeros(bsz, steps, 2 * k_sat, dtype=f64)
    if closed:
        ref = reference_imm(cfg, k_sat)
        sd_ref = np.concatenate(
            [
                np.full(3, cfg["init_position"]),
                np.full(3, cfg["init_velocity"]),
                np.full(3, math.radians(cfg["init_attitude_deg"])),
                np.full(6, cfg["gyro_constant_dph"] * math.radians(1.0) / 3600.0),
                np.full(3, cfg["accel_bias_mg"] * 9.80665e-3),
                [cfg["clock_bias"], cfg["clock_drift"]],
            ]
        )
        belief = ref.initial_belief(torch.zeros(bsz, 20, dtype=f64), torch.diag(torch.from_numpy(sd_ref**2)), bsz)
        vis2 = torch.cat([vis, vis], -1)
    rec = {k: np.zeros((bsz, steps + 1, 3)) for k in ("llh", "vel", "f_n", "eps_r", "nabla")}
    rec_c = np.zeros((bsz, steps + 1, 3, 3))
    rec["llh"][:, 0], rec["vel"][:, 0], rec["eps_r"][:, 0], rec["nabla"][:, 0], rec_c[:, 0] = ins_llh, ins_v, eps_r, nabla, ins_c
    f_acc = np.zeros((bsz, 3))
    for i in range(n_in):
        w_in, acc, rm_i, rn_i = frame_terms(ins_llh, ins_v)
        dvb = dvel[:, i] + nabla * dti + acc_w[:, i]
        dvn = (ins_c @ dvb[..., None])[..., 0]
        f_acc += dvn
        v_new = ins_v + dvn + acc * dti
        ins_c = rotation_exp(-w_in * dti) @ ins_c @ rotation_exp(dtheta[:, i] + (eps_b + eps_r) * dti + gyro_w[:, i])
        ins_llh = position_step(ins_llh, ins_v, v_new, dti, rm_i, rn_i)
        ins_v = v_new
        eps_r = ag * eps_r + sg * drive[:, i, :3]
        nabla = aa * nabla + sa * drive[:, i, 3:]
        if (i + 1) % imu_rate == 0:
            k = (i + 1) // imu_rate
            rec["llh"][:, k], rec["vel"][:, k], rec["eps_r"][:, k], rec["nabla"][:, k], rec_c[:, k] = ins_llh, ins_v, eps_r, nabla, ins_c
            rec["f_n"][:, k], f_acc = f_acc, np.zeros((bsz, 3))
            if closed:
                ins_llh, ins_v, ins_c, belief = _feed_back(
                    ref, belief, k, ins_llh, ins_v, ins_c, rec["f_n"][:, k], fb, z_closed, vis2,
                    torch.from_numpy(t_llh[:, k]), torch.from_numpy(t_vel[:, k]), sp, sv, clock, range_noise, rate_noise,
                )  # fmt: skip
    # --- error truth at the 1 Hz epochs ------------------------------------------------------------
    err = np.zeros((bsz, steps + 1, 20))
    err[..., 0:3], err[..., 3:6] = rec["llh"] - t_llh, rec["vel"] - t_vel
    err[..., 6:9] = -rotation_log(rec_c @ np.swapaxes(t_c, -1, -2))
    err[..., 9:12], err[..., 12:15], err[..., 15:18] = eps_b[:, None], rec["eps_r"], rec["nabla"]
    err[..., 18:20] = clk
    # --- measurements -------------------------------------------------------------------------
    if closed:
        z = z_closed
    else:
        drho, rate = gnss_differences(
            torch.from_numpy(rec["llh"]), torch.from_numpy(rec["vel"]), torch.from_numpy(t_llh), torch.from_numpy(t_vel), sp, sv, clock
        )
        z = torch.cat([drho[:, 1:] - range_noise, rate[:, 1:] - rate_noise], -1)
    # --- units and initial belief -------------------------------------------------------------
    _, _, rm, rn = frame_terms(rec["llh"], rec["vel"])
    scale = np.stack([rm, rn * np.cos(rec["llh"][..., 0]), np.ones_like(rm)], -1)
    if position_in_metres:
        err[..., 0:3] *= scale
    else:
        fb[..., 0:3] /= scale
    sd0 = np.concatenate(
        [
            np.full((bsz, 3), cfg["init_position"]) / (1.0 if position_in_metres else scale[:, 0]),
            np.full((bsz, 3), cfg["init_velocity"]),
            np.full((bsz, 3), math.radians(cfg["init_attitude_deg"])),
            np.full((bsz, 6), cfg["gyro_constant_dph"] * dph),
            np.full((bsz, 3), cfg["accel_bias_mg"] * mg),
            np.tile([cfg["clock_bias"], cfg["clock_drift"]], (bsz, 1)),
        ],
        -1,
    )
    euler = np.stack([psi, gamma, roll], -1)[:, ke]

    def cast(v: np.ndarray | Tensor) -> Tensor:
        return torch.as_tensor(v).to(dtype)

    controls = {
        "llh": cast(rec["llh"][:, 1:]),
        "vel": cast(rec["vel"][:, 1:]),
        "f_n": cast(rec["f_n"][:, 1:]),
        "C_bn": cast(rec_c[:, 1:]),
        "dt": torch.ones(bsz, steps, 1, dtype=dtype),
        "sat_pos": cast(sp[:, 1:]),
        "sat_vel": cast(sv[:, 1:]),
    }
    if closed:
        controls["feedback"] = cast(fb[:, :-1])
    return P003Scenario(
        truth=cast(err[:, 1:]),
        measurements=z.to(dtype),
        mask=torch.cat([vis, vis], -1),
        controls=controls,
        manoeuvre=torch.from_numpy(man),
        initial_mean=torch.zeros(bsz, 20, dtype=dtype),
        initial_cov=torch.diag_embed(cast(sd0**2)),
        initial_truth=cast(err[:, 0]),
        nav_truth={"llh": cast(t_llh[:, 1:]), "vel": cast(t_vel[:, 1:]), "euler": cast(euler[:, 1:])},
        times=torch.arange(1, steps + 1, dtype=dtype),
        dt=1.0,
        phases=phases,
        config={**cfg, "imu_rate": float(imu_rate), "num_satellites": float(k_sat)},
        imu_noise_scale=cast(np.sqrt((imu_scale**2).reshape(bsz, steps, imu_rate).mean(-1))),
        gnss_noise_scale=cast(gnss_scale),
        cn0=cast(cn0),
    )
