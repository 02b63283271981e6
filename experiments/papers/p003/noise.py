"""p003's sensor-noise families: what multiplies the simulator's nominal IMU and GNSS noise.

The paper gives the sensor values (gyro and accelerometer white noise, pseudorange-rate noise) and
a two-mode IMM whose high mode has ``sigma_Q x 100`` and ``sigma_R x 10``; it does not say what
makes the noise change.  The simulator (:func:`~experiments.papers.p003.simulator.simulate_p003`,
argument ``noise``) offers three families:

``"nominal"`` - the paper-faithful one: the paper's sensor values at all times, nothing switches.

``"modes"`` - two-level noise tied to the manoeuvre phases (the family of p003's two-mode IMM,
    with other values than the paper's): during a manoeuvre the IMU white noises grow by
    ``mode_imu_scale`` (airframe and engine vibration at high thrust and load) and both GNSS noises
    by ``mode_gnss_scale`` (the receiver widens its code and carrier tracking-loop bandwidths to keep
    lock under dynamics: thermal-noise variance grows with the loop bandwidth, ``sqrt(10)`` in sigma
    for a ten-fold bandwidth).  With ``profile="markov"`` the phases form a Markov chain, so the
    truth lies in the IMM family (:func:`true_transition`).

``"physical"`` - noise that follows its physical causes, continuously and per satellite:

    * IMU vibration: the white-noise sigma is ``1 + vibration_gain |a| / g`` times nominal, ``a`` the
      kinematic acceleration (speed changes, turn centripetal and pull-up accelerations), so it rises
      and falls with the load inside a manoeuvre instead of switching;
    * antenna shading: a fuselage-top antenna loses gain for satellites near or below its horizon
      (:func:`antenna_gain_db` of the satellite's elevation in the body frame); banked turns and
      pitch changes move satellites there.  The carrier-to-noise density drops by the lost gain from
      ``cn0_nominal`` and both GNSS noise variances grow as ``1 / (C/N0)`` (code and frequency-lock
      loop thermal noise, squaring loss neglected); below ``cn0_lock`` the channel loses lock and
      the satellite is masked.

    Nothing in it is two-level: the paper's nominal mode values (and any two-mode IMM) only
    approximate it.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "NOISE_DEFAULTS",
    "NOISE_FAMILIES",
    "antenna_gain_db",
    "body_elevation",
    "cn0_sigma_scale",
    "true_transition",
    "vibration_scale",
]

NOISE_FAMILIES = ("nominal", "modes", "physical")

#: Parameters of the families (merged into the simulator's config; override through ``config``).
NOISE_DEFAULTS: dict[str, float] = {
    "mode_imu_scale": 10.0,  # "modes": IMU white-noise sigma x 10 in manoeuvres (p003's high mode: x 100)
    "mode_gnss_scale": math.sqrt(10.0),  # "modes": GNSS sigma x sqrt(10) (10 x loop bandwidth; p003: x 10)
    "markov_enter": 1.0 / 60.0,  # profile "markov": P(level -> manoeuvre) per second (60 s mean level segment)
    "markov_leave": 1.0 / 15.0,  # P(manoeuvre -> level) per second (15 s mean manoeuvre)
    "vibration_gain": 10.0,  # "physical": IMU white-noise sigma x (1 + 10 |a| / g)
    "antenna_knee_deg": 10.0,  # full antenna gain above 10 deg body-frame elevation
    "antenna_slope_db": 1.0,  # dB lost per degree below the knee
    "cn0_nominal": 45.0,  # dB-Hz at full gain (the nominal sigma_range / sigma_rate hold there)
    "cn0_lock": 30.0,  # dB-Hz: below it the channel loses lock (satellite masked)
}

_G = 9.80665


def true_transition(p_enter: float, p_leave: float) -> list[list[float]]:
    """The 1 Hz Markov matrix ``[[1 - p_enter, p_enter], [p_leave, 1 - p_leave]]`` of a
    ``"markov"`` schedule (mode 0 level, 1 manoeuvre)."""
    return [[1.0 - p_enter, p_enter], [p_leave, 1.0 - p_leave]]


def vibration_scale(acceleration: np.ndarray, gain: float) -> np.ndarray:
    """IMU white-noise sigma multiplier ``1 + gain |a| / g`` for kinematic accelerations
    ``acceleration [..., 3]`` (m/s^2)."""
    return 1.0 + float(gain) * np.linalg.norm(acceleration, axis=-1) / _G


def body_elevation(los_enu: np.ndarray, c_bn: np.ndarray) -> np.ndarray:
    """Elevation (rad) of lines of sight ``los_enu [..., K, 3]`` above the body x-y plane (the
    antenna horizon of a fuselage-top antenna; body axes right-forward-up) for the body-to-ENU
    attitude ``c_bn [..., 3, 3]``: ``asin(u_b[2])`` with ``u_b = C_bn^T u``."""
    u = los_enu / np.linalg.norm(los_enu, axis=-1, keepdims=True)
    up_body_in_enu = c_bn[..., :, 2]  # third column: the body z axis in ENU
    return np.arcsin(np.clip((u * up_body_in_enu[..., None, :]).sum(-1), -1.0, 1.0))


def antenna_gain_db(elevation: np.ndarray, knee_deg: float, slope_db: float) -> np.ndarray:
    """Antenna gain relative to zenith (dB, <= 0): ``-slope_db * max(0, knee_deg - elevation)``
    with the body-frame ``elevation`` in radians."""
    return -float(slope_db) * np.maximum(0.0, float(knee_deg) - np.degrees(elevation))


def cn0_sigma_scale(gain_db: np.ndarray) -> np.ndarray:
    """Noise sigma multiplier for a ``gain_db`` drop in C/N0: thermal-noise variance ``~ 1 / (C/N0)``,
    so sigma scales by ``10 ** (-gain_db / 20)``."""
    return np.power(10.0, -np.asarray(gain_db) / 20.0)
