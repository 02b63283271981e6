"""p003's 20-state GPS/SINS error model at the simulator's sensor specification
(:func:`make_p003_model`) and the simulator's own closed-loop navigation filter
(:func:`reference_imm`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from difffilter import geometry as geo
from difffilter.filters import SimplifiedUKF
from difffilter.mixers import IMM
from difffilter.models.base import StateSpaceModel
from difffilter.models.layout import StateLayout, describe
from experiments.papers.p003.sins import DEG_PER_HOUR, MILLI_G, SinsErrorDynamics, sins_noise_psd
from experiments.papers.p003.sins_measurement import SinsPseudorangeMeasurement

from .flight import P003_CONFIG, PAPER_PHASES

__all__ = ["SINS_LAYOUT", "make_p003_model", "reference_imm", "sins_layout", "sojourn_transition"]

_ERRORS = ("dv_E", "dv_N", "dv_U", "phi_E", "phi_N", "phi_U", "eps_bx", "eps_by", "eps_bz")
_ERRORS += ("eps_rx", "eps_ry", "eps_rz", "nabla_x", "nabla_y", "nabla_z", "dt_u", "dt_ru")
_UNITS = ("m/s",) * 3 + ("rad",) * 3 + ("rad/s",) * 6 + ("m/s^2",) * 3 + ("m", "m/s")


def sins_layout(position_in_metres: bool = True) -> StateLayout:
    """The 20-state error layout of :mod:`experiments.papers.p003.sins` (position errors in
    north/east/up metres, or latitude/longitude radians and height)."""
    head = (("dN", "dE", "dh"), ("m", "m", "m")) if position_in_metres else (("dL", "dlambda", "dh"), ("rad", "rad", "m"))
    return StateLayout(names=head[0] + _ERRORS, units=head[1] + _UNITS, position=(0, 1, 2))


#: :func:`sins_layout` in metres (the experiments' choice).
SINS_LAYOUT = sins_layout(True)


def sojourn_transition(phases: Sequence[tuple[float, float, str, float]] = PAPER_PHASES, dt: float = 1.0) -> list[list[float]]:
    """The IMM design rule ``p_ii = 1 - T / tau_i`` (Bar-Shalom, Li & Kirubarajan, *Estimation with
    Applications to Tracking and Navigation*, 2001, IMM design: ``tau_i`` the expected sojourn time
    of mode ``i``, ``T`` the sampling interval) with ``tau_i`` the mean length of the level/static
    (mode 0) and manoeuvre (mode 1) phases of ``phases``: for p003's profile 1675 s / 8 = 209.4 s
    and 125 s / 7 = 17.9 s."""
    level = [p[1] - p[0] for p in phases if p[2] in ("static", "level")]
    manoeuvre = [p[1] - p[0] for p in phases if p[2] not in ("static", "level")]
    if not level or not manoeuvre:
        raise ValueError("the schedule must have level and manoeuvre phases")
    out = []
    for j, segments in enumerate((level, manoeuvre)):
        stay = 1.0 - dt / (sum(segments) / len(segments))
        out.append([stay, 1.0 - stay] if j == 0 else [1.0 - stay, stay])
    return out


def reference_imm(config: dict[str, float] | None = None, num_satellites: int = 8) -> torch.nn.Module:
    """The simulator's closed-loop navigation filter (``feedback="imm"``): p003's hand-tuned IMM of
    two simplified UKFs in metre units, float64 - low mode at the sensor specification, high mode
    PSD x 1e4 and R x 100 (p003's sigma ratios), ``Pi`` = :func:`sojourn_transition` of p003's
    profile, initial (0.9, 0.1)."""
    modes = [
        SimplifiedUKF(make_p003_model(num_satellites=num_satellites, q_scale=qs, r_scale=rs, position_in_metres=True, config=config))
        for qs, rs in ((1.0, 1.0), (1.0e4, 100.0))
    ]
    pi = torch.tensor(sojourn_transition(), dtype=torch.float64)
    return IMM(modes, transition=pi, initial_probs=torch.tensor([0.9, 0.1], dtype=torch.float64)).double()


def make_p003_model(
    *,
    num_satellites: int = 8,
    q_scale: float = 1.0,
    r_scale: float = 1.0,
    linearized: bool = False,
    position_in_metres: bool = False,
    discretization: str = "expm",
    Q_structure: str = "scalar",
    R_structure: str = "scalar",
    config: dict[str, float] | None = None,
    dtype: torch.dtype = torch.float64,
) -> torch.nn.Module:
    """The 20-state error model with the simulator's noise levels times ``q_scale`` (on the PSD,
    i.e. ``sigma_Q^2``) and ``r_scale`` (on ``R``).  p003's modes: low = ``(1, 1)``, high =
    ``(100**2, 10**2)`` (``sigma_Q(high) = 100 sigma_Q(low)``, ``sigma_R(high) = 10 sigma_R(low)``)."""
    cfg = {**P003_CONFIG, **(config or {})}
    psd = sins_noise_psd(
        gyro_white=cfg["gyro_white_dph"] * DEG_PER_HOUR, gyro_markov=cfg["gyro_markov_dph"] * DEG_PER_HOUR,
        gyro_markov_time=cfg["gyro_markov_time"], accel_white=cfg["accel_white_mg"] * MILLI_G,
        accel_markov=cfg["accel_bias_mg"] * MILLI_G, accel_markov_time=cfg["accel_markov_time"],
        clock_bias_psd=cfg["clock_bias_psd"], clock_drift_psd=cfg["clock_drift_psd"],
        position_in_metres=position_in_metres, dtype=dtype,
    )  # fmt: skip
    dyn = SinsErrorDynamics(
        Q=torch.diag(psd) * q_scale, Q_structure=Q_structure, gyro_markov_time=cfg["gyro_markov_time"],
        accel_markov_time=cfg["accel_markov_time"], clock_time=cfg["clock_time"], discretization=discretization,
        position_in_metres=position_in_metres, dtype=dtype,
    )  # fmt: skip
    var = [cfg["sigma_range"] ** 2 * r_scale] * num_satellites + [cfg["sigma_rate"] ** 2 * r_scale] * num_satellites
    meas = SinsPseudorangeMeasurement(
        num_satellites=num_satellites, linearized=linearized, R=torch.diag(torch.tensor(var, dtype=dtype)),
        R_structure=R_structure, position_in_metres=position_in_metres, dtype=dtype,
    )  # fmt: skip
    # default belief: zero error with the simulator's initial spreads (its `sd0`)
    rm, rn = geo.radii_of_curvature(torch.tensor(math.radians(cfg["lat_deg"]), dtype=torch.float64))
    d = cfg["init_position"]
    pos = [d] * 3 if position_in_metres else [d / float(rm), d / (float(rn) * math.cos(math.radians(cfg["lat_deg"]))), d]
    sd = pos + [cfg["init_velocity"]] * 3 + [math.radians(cfg["init_attitude_deg"])] * 3 + [cfg["gyro_constant_dph"] * DEG_PER_HOUR] * 6
    sd += [cfg["accel_bias_mg"] * MILLI_G] * 3 + [cfg["clock_bias"], cfg["clock_drift"]]
    model = StateSpaceModel(dyn, meas)
    var = [s * s for s in sd]
    return describe(model, layout=sins_layout(position_in_metres), learn=["Q", "R"], initial_mean=[0.0] * 20, initial_var=var)
