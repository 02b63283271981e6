"""p001 simulator: static single-point GPS positioning with AR(1) coloured pseudorange noise.

A receiver sits on a known point; ``K`` satellites at the GPS orbit radius (26,560 km) are held at
fixed azimuth/elevation (the paper's 100 epochs at 10 s span 17 minutes; the geometry is frozen so
that the only time-varying errors are the clock and the coloured noise).  Each epoch
``k = 1..T`` (``t_k = k dt``):

.. math::
    \\rho_{k,j} = \\|s_j - p\\| + b_k + v_{k,j},\\qquad v_{k,j} = \\Psi v_{k-1,j} + \\eta_{k,j},
    \\quad \\eta \\sim N(0, R_\\eta)

with ``v_1`` drawn from the stationary law ``N(0, R_eta / (1 - Psi^2))``, and the receiver clock
``(b, d)`` a two-state random walk (bias PSD ``clock_bias_psd``, drift PSD ``clock_drift_psd``),
independent of the filter.  The receiver is static (zero velocity).

Noise families (``config``): one ``Psi`` (``psi``) and ``R_eta = eta_sigma^2`` for every
satellite (the paper: 0.7 and 3 m; ``p001_multipath``: 0.9 and 1.5 m), or, with
``config["elevation_noise"] = {sigma_zenith, sigma_exponent, tau_zenith, tau_exponent}``, per
satellite from its elevation (:func:`~experiments.papers.p001.elevation.elevation_noise`).  The
elevations are inputs too (``controls["elevation"]``, rad), as a receiver knows them from the
ephemeris.

Coordinates: positions are ECEF *offsets* from the known point ``frame_origin`` (ECEF axes), and
measurements are reduced pseudoranges ``rho - ||s - origin||`` computed in float64, so float32
filters keep millimetre resolution.  ``PseudorangeMeasurement(reduced=True)`` predicts exactly
these; ``reduced=False`` gives absolute ECEF positions and raw pseudoranges instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from difffilter import geometry as geo
from difffilter._util import generator
from difffilter.models.base import StateSpaceModel
from difffilter.models.layout import StateLayout, describe
from difffilter.models.navigation.clock import ConstantVelocityClock
from difffilter.models.navigation.pseudorange import GnssStateLayout, PseudorangeMeasurement
from experiments.papers import constellation as sky

from .elevation import ElevationPseudorange, elevation_noise

__all__ = ["LAW_KEYS", "P001_CONFIG", "P001_LAYOUT", "P001Geometry", "P001Scenario", "make_p001_model", "simulate_p001"]

#: Keys of ``config["elevation_noise"]`` (:func:`~experiments.papers.p001.elevation.elevation_noise`).
LAW_KEYS = ("sigma_zenith", "sigma_exponent", "tau_zenith", "tau_exponent")

P001_CONFIG: dict[str, float | tuple[float, ...]] = {
    "lat_deg": 30.5283,  # a known point (chosen; the paper's location was lost)
    "lon_deg": 114.3567,
    "height": 30.0,
    # Fixed 7-satellite geometry (deg): one near zenith, the rest spread in azimuth; PDOP ~ 1.9.
    "azimuth_deg": (0.0, 40.0, 110.0, 170.0, 225.0, 290.0, 330.0),
    "elevation_deg": (85.0, 30.0, 55.0, 20.0, 45.0, 25.0, 60.0),
    "num_epochs": 100,
    "dt": 10.0,  # s
    "psi": 0.7,  # AR(1) coefficient of the pseudorange noise
    "eta_sigma": 3.0,  # m, std of the AR(1) driving noise (R = 9 m^2)
    "clock_bias": 50.0,  # m, mean of the true initial clock bias (std 100 m)
    "clock_drift_sigma": 0.1,  # m/s, std of the true initial drift
    "clock_bias_psd": 0.01,  # m^2/s
    "clock_drift_psd": 1e-4,  # m^2/s^3
    # Filter configuration (values lost in the paper, chosen per papers/p001 file)
    "p0_position_var": 100.0,  # m^2
    "p0_velocity_var": 1.0,  # (m/s)^2
    "p0_clock_var": 100.0,  # m^2
    "p0_drift_var": 1.0,  # (m/s)^2
    "start_offset": 10.0,  # m, norm of the initial position error
    # The paper's Q was lost; its receiver is static by design (one receiver on a known point), so
    # the CV model's acceleration PSD is the truth, 0 (1e-10: the parameter is Positive).  The
    # earlier 1e-4 ("small Q") was a project choice the learned filters only undid.
    "filter_accel_psd": 1e-10,  # m^2/s^3
    "elevation_noise": None,  # or {sigma_zenith, sigma_exponent, tau_zenith, tau_exponent}
}


#: State of the p001 receiver model: ECEF offsets from the known point, velocity, clock bias and drift.
P001_LAYOUT = StateLayout(
    names=("x", "y", "z", "vx", "vy", "vz", "clock_bias", "clock_drift"),
    units=("m", "m", "m", "m/s", "m/s", "m/s", "m", "m/s"),
    position=(0, 1, 2),
)


@dataclass
class P001Scenario:
    """Simulated static epochs (batch-first).

    ``truth [B, T, 8]`` = ``[p (3, offset from frame_origin), v (3, zero), clock bias, drift]``;
    ``measurements [B, T, K]``; ``mask [B, T, K]`` (all True); ``controls`` = ``sat_pos
    [B, T, K, 3]`` (relative to ``frame_origin``), ``dt [B, T, 1]``; ``noise [B, T, K]`` the
    coloured noise ``v``; ``psi [B]`` and ``eta_var`` the true noise parameters;
    ``initial_mean [B, 8]`` (truth at ``t_0`` perturbed: position by ``start_offset`` metres in a
    random direction, clock by draws from P0), ``initial_cov [8, 8]`` = P0,
    ``initial_truth [B, 8]``, ``frame_origin [B, 3]`` ECEF.
    """

    truth: Tensor
    measurements: Tensor
    mask: Tensor
    controls: dict[str, Tensor]
    noise: Tensor
    psi: Tensor
    eta_var: float
    initial_mean: Tensor
    initial_cov: Tensor
    initial_truth: Tensor
    frame_origin: Tensor
    dt: float
    ar_coefficient: Tensor
    eta_variance: Tensor
    config: dict[str, object] = field(default_factory=dict)


def simulate_p001(
    batch_size: int = 1,
    seed: int | torch.Generator | None = 0,
    dtype: torch.dtype = torch.float64,
    *,
    randomize: bool = False,
    random_psi: tuple[float, float] | None = None,
    num_satellites: int = 7,
    num_epochs: int | None = None,
    reduced: bool = True,
    config: dict[str, object] | None = None,
) -> P001Scenario:
    """Simulate ``batch_size`` static receivers (see the module docstring).

    Args:
        randomize: random receiver location (|lat| < 60 deg) and random geometry per batch element
            (``num_satellites`` satellites, azimuths spread around the horizon with jitter,
            elevations 10-85 deg with one above 60 deg); otherwise the fixed paper geometry.
        random_psi: ``(low, high)``: draw ``Psi`` uniformly per batch element.
        num_epochs: ``T`` (default 100).
        reduced: reduced pseudoranges and origin-relative positions (default), else absolute.
    """
    cfg: dict = {**P001_CONFIG, **(config or {})}
    gen = generator(seed)
    f64 = torch.float64
    bsz, steps, dt = batch_size, int(num_epochs or cfg["num_epochs"]), float(cfg["dt"])

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=gen, dtype=f64)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen, dtype=f64)

    if randomize:
        k = num_satellites
        lat, lon = (rand(bsz) * 2 - 1) * math.radians(60), (rand(bsz) * 2 - 1) * math.pi
        spread = torch.arange(k, dtype=f64) / k * 2 * math.pi + (rand(bsz, k) - 0.5) * (math.pi / k)
        az = (spread + rand(bsz, 1) * 2 * math.pi) % (2 * math.pi)
        el = torch.deg2rad(10 + 75 * rand(bsz, k))
        el[:, 0] = torch.deg2rad(60 + 25 * rand(bsz))
    else:
        k = len(cfg["azimuth_deg"])
        lat = torch.full((bsz,), math.radians(cfg["lat_deg"]), dtype=f64)
        lon = torch.full((bsz,), math.radians(cfg["lon_deg"]), dtype=f64)
        az = torch.deg2rad(torch.tensor(cfg["azimuth_deg"], dtype=f64)).expand(bsz, k)
        el = torch.deg2rad(torch.tensor(cfg["elevation_deg"], dtype=f64)).expand(bsz, k)
    origin = geo.geodetic_to_ecef(torch.stack([lat, lon, torch.full_like(lat, float(cfg["height"]))], -1))
    sats = sky.satellites_from_azimuth_elevation(origin, az, el)  # [B, K, 3]
    rel = sats - origin[:, None, :]
    geom_range = torch.linalg.vector_norm(rel, dim=-1)  # receiver at the origin

    psi = torch.full((bsz,), float(cfg["psi"]), dtype=f64)
    if random_psi is not None:
        psi = random_psi[0] + (random_psi[1] - random_psi[0]) * rand(bsz)
    eta_sd: float | Tensor = float(cfg["eta_sigma"])
    psi_k, eta_var_k = psi[:, None].expand(bsz, k), torch.full((bsz, k), float(cfg["eta_sigma"]) ** 2, dtype=f64)
    law = cfg.get("elevation_noise")
    if law:
        if random_psi is not None:
            raise ValueError("random_psi and config['elevation_noise'] exclude each other")
        psi_k, eta_var_k = elevation_noise(el, dt, **{n: float(law[n]) for n in LAW_KEYS})
        eta_sd = eta_var_k.sqrt()[:, None, :]
        psi = torch.full((bsz,), math.nan, dtype=f64)
    eta = randn(bsz, steps, k) * eta_sd
    v = torch.empty(bsz, steps, k, dtype=f64)
    v[:, 0] = eta[:, 0] / torch.sqrt(1 - psi_k**2)
    for t in range(1, steps):
        v[:, t] = psi_k * v[:, t - 1] + eta[:, t]

    qb, qd = float(cfg["clock_bias_psd"]), float(cfg["clock_drift_psd"])
    qc = torch.tensor([[qb * dt + qd * dt**3 / 3, qd * dt**2 / 2], [qd * dt**2 / 2, qd * dt]], dtype=f64)
    lq = torch.linalg.cholesky(qc)
    clk = torch.empty(bsz, steps + 1, 2, dtype=f64)
    clk[:, 0, 0] = float(cfg["clock_bias"]) + 100.0 * randn(bsz)
    clk[:, 0, 1] = float(cfg["clock_drift_sigma"]) * randn(bsz)
    cn = randn(bsz, steps, 2)
    for t in range(steps):
        clk[:, t + 1, 0] = clk[:, t, 0] + dt * clk[:, t, 1]
        clk[:, t + 1, 1] = clk[:, t, 1]
        clk[:, t + 1] += cn[:, t] @ lq.mT
    truth0 = torch.cat([torch.zeros(bsz, steps + 1, 6, dtype=f64), clk], -1)
    z = geom_range[:, None, :] + clk[:, 1:, 0:1] + v
    sat_ctrl = rel
    if reduced:
        z = z - geom_range[:, None, :]
    else:
        sat_ctrl = sats
        truth0[..., 0:3] = origin[:, None, :]

    direction = randn(bsz, 3)
    direction = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
    p0 = torch.tensor([cfg["p0_position_var"]] * 3 + [cfg["p0_velocity_var"]] * 3 + [cfg["p0_clock_var"], cfg["p0_drift_var"]], dtype=f64)
    init = truth0[:, 0].clone()
    init[:, 0:3] += float(cfg["start_offset"]) * direction
    init[:, 6:8] += randn(bsz, 2) * torch.sqrt(p0[6:8])
    return P001Scenario(
        truth=truth0[:, 1:].to(dtype),
        measurements=z.to(dtype),
        mask=torch.ones(bsz, steps, k, dtype=torch.bool),
        controls={
            "sat_pos": sat_ctrl[:, None].expand(bsz, steps, k, 3).to(dtype),
            "dt": torch.full((bsz, steps, 1), dt, dtype=dtype),
            "elevation": el[:, None].expand(bsz, steps, k).to(dtype),
        },
        noise=v.to(dtype),
        psi=psi.to(dtype),
        eta_var=math.nan if law else float(eta_sd) ** 2,  # type: ignore[arg-type]
        initial_mean=init.to(dtype),
        initial_cov=torch.diag(p0).to(dtype),
        initial_truth=truth0[:, 0].to(dtype),
        frame_origin=origin,
        dt=dt,
        ar_coefficient=psi_k.to(dtype),
        eta_variance=eta_var_k.to(dtype),
        config={**cfg, "num_satellites": k, "reduced": reduced},
    )


def make_p001_model(
    *,
    num_satellites: int = 7,
    dt: float | None = None,
    eta_sigma: float | None = None,
    accel_psd: float | None = None,
    clock_bias_psd: float | None = None,
    clock_drift_psd: float | None = None,
    R_structure: str = "scalar",
    reduced: bool = True,
    elevation_noise: Mapping[str, float] | None = None,
    dtype: torch.dtype = torch.float64,
) -> torch.nn.Module:
    """CV + clock dynamics and reduced pseudoranges with the configured (hand-tuned) Q and R.

    ``R = eta_sigma^2 I`` is the noise of a *white*-noise filter (the standard UKF of p001); a
    coloured-noise filter wraps this model with its own ``Psi``.  The clock PSDs default to the
    simulator's truth, the acceleration PSD to ``filter_accel_psd``.

    ``elevation_noise`` (``{sigma_zenith, sigma_exponent, tau_zenith, tau_exponent}``): the
    measurement is an :class:`~experiments.papers.p001.elevation.ElevationPseudorange` with these
    starting values instead (``eta_sigma``, ``R_structure`` unused; a
    :class:`~difffilter.filters.ColoredNoiseUKF` with ``psi=None`` reads ``Psi`` from it), and the
    learnable set is the law's four values and Q.
    """
    cfg = P001_CONFIG
    dyn = ConstantVelocityClock(
        dt=float(cfg["dt"]) if dt is None else dt,  # type: ignore[arg-type]
        accel_psd=float(cfg["filter_accel_psd"]) if accel_psd is None else accel_psd,  # type: ignore[arg-type]
        clock_bias_psd=float(cfg["clock_bias_psd"]) if clock_bias_psd is None else clock_bias_psd,  # type: ignore[arg-type]
        clock_drift_psd=float(cfg["clock_drift_psd"]) if clock_drift_psd is None else clock_drift_psd,  # type: ignore[arg-type]
        dtype=dtype,
    )
    sigma = float(cfg["eta_sigma"]) if eta_sigma is None else eta_sigma  # type: ignore[arg-type]
    layout = GnssStateLayout.constant_velocity()
    meas: PseudorangeMeasurement
    if elevation_noise is not None:
        law = {n: float(elevation_noise[n]) for n in LAW_KEYS}
        meas = ElevationPseudorange(num_satellites=num_satellites, layout=layout, dt=dyn.dt, reduced=reduced, dtype=dtype, **law)
        noise_names = list(LAW_KEYS)
    else:
        meas = PseudorangeMeasurement(
            num_satellites=num_satellites, layout=layout, sigma_range=sigma, reduced=reduced, R_structure=R_structure, dtype=dtype
        )
        noise_names = ["R"]
    cfg_var = [cfg["p0_position_var"]] * 3 + [cfg["p0_velocity_var"]] * 3 + [cfg["p0_clock_var"], cfg["p0_drift_var"]]
    return describe(
        StateSpaceModel(dyn, meas),
        layout=P001_LAYOUT,
        learn=["accel_psd", "clock_bias_psd", "clock_drift_psd", *noise_names],
        initial_mean=[0.0] * 6 + [float(cfg["clock_bias"]), 0.0],  # type: ignore[arg-type]
        initial_var=cfg_var,  # type: ignore[arg-type]
        controls=P001Geometry(num_satellites=num_satellites),
    )  # type: ignore[return-value]


class P001Geometry:
    """In-family inputs of the p001 model: ``(batch_size, num_steps, generator, dtype) ->
    {"sat_pos", "dt"}`` of random static receivers (:func:`simulate_p001` with ``randomize``)."""

    def __init__(self, *, num_satellites: int) -> None:
        self.num_satellites = int(num_satellites)

    def __call__(self, batch_size: int, num_steps: int, gen: torch.Generator, dtype: torch.dtype) -> dict[str, Tensor]:
        sc = simulate_p001(batch_size, gen, dtype, randomize=True, num_satellites=self.num_satellites, num_epochs=num_steps)
        return sc.controls
