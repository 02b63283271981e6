"""A simulated GPS sky for the papers' scenarios: satellites placed at given azimuths and
elevations (p001) and a Walker-delta constellation of circular orbits (p003).  Geometry
(WGS-84, ECEF/ENU) is the library's :mod:`difffilter.geometry`."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from difffilter.geometry import EARTH_RATE, ecef_to_geodetic, enu_rotation

__all__ = ["GM_EARTH", "GPS_ORBIT_RADIUS", "CircularOrbitConstellation", "satellites_from_azimuth_elevation"]

GM_EARTH = 3.986004418e14  # m^3/s^2
GPS_ORBIT_RADIUS = 26_560_000.0  # m


def satellites_from_azimuth_elevation(
    receiver_ecef: Tensor, azimuth: Tensor, elevation: Tensor, radius: float = GPS_ORBIT_RADIUS
) -> Tensor:
    """ECEF positions ``[..., K, 3]`` of satellites on the sphere ``|s| = radius`` seen from
    ``receiver_ecef [..., 3]`` at the given azimuth/elevation ``[..., K]`` (rad).

    Solves ``|p + t d| = radius`` for the line-of-sight unit vector ``d`` and ``t > 0``.
    """
    llh = ecef_to_geodetic(receiver_ecef)
    rot = enu_rotation(llh[..., 0], llh[..., 1])  # [..., 3, 3]
    ce = torch.cos(elevation)
    d_enu = torch.stack([ce * torch.sin(azimuth), ce * torch.cos(azimuth), torch.sin(elevation)], -1)
    d = d_enu @ rot
    p = receiver_ecef[..., None, :]
    pd = (p * d).sum(-1, keepdim=True)
    t = -pd + torch.sqrt(pd * pd - (p * p).sum(-1, keepdim=True) + radius**2)
    return p + t * d


class CircularOrbitConstellation:
    """Walker-delta constellation of circular orbits (a stand-in for GPS, used by p003).

    ``planes x per_plane`` satellites at radius ``radius``, inclination ``inclination_deg``,
    ascending nodes spaced ``360/planes`` degrees, in-plane spacing ``360/per_plane`` and
    inter-plane phasing ``360 * phasing / (planes * per_plane)`` degrees (24/6/1 by default).
    Mean motion ``n = sqrt(GM / r^3)`` (about 11.97 h period at GPS radius).  ECEF position at
    time ``t``: ``R_3(-w_e t - theta_0) r_eci(t)``; ECEF velocity ``R_3(.) v_eci - w_e x r_ecef``.
    Light-time and relativistic effects are ignored: the simulated measurements are built from
    these same positions, so the filters see a self-consistent geometry.
    """

    def __init__(
        self, *, planes: int = 6, per_plane: int = 4, phasing: int = 1, inclination_deg: float = 55.0, radius: float = GPS_ORBIT_RADIUS
    ) -> None:
        self.planes, self.per_plane, self.radius = planes, per_plane, radius
        self.inclination = math.radians(inclination_deg)
        self.mean_motion = math.sqrt(GM_EARTH / radius**3)
        raan, arg = [], []
        for p in range(planes):
            for k in range(per_plane):
                raan.append(2 * math.pi * p / planes)
                arg.append(2 * math.pi * k / per_plane + 2 * math.pi * phasing * p / (planes * per_plane))
        self._raan = raan
        self._arg = arg

    @property
    def num_satellites(self) -> int:
        return self.planes * self.per_plane

    def state(self, t: Tensor, earth_angle: Tensor | None = None, orbit_phase: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """ECEF positions and velocities ``[..., N, 3]`` at times ``t [...]`` (s).

        ``earth_angle [...]`` (rad) rotates the Earth at ``t = 0`` and ``orbit_phase [...]``
        advances every satellite along its orbit: random values give random geometries.
        """
        dtype, dev = t.dtype, t.device
        raan = torch.tensor(self._raan, dtype=dtype, device=dev)
        arg = torch.tensor(self._arg, dtype=dtype, device=dev)
        phase = torch.zeros_like(t) if orbit_phase is None else orbit_phase
        theta0 = torch.zeros_like(t) if earth_angle is None else earth_angle
        u = arg + (self.mean_motion * t + phase)[..., None]
        ci, si = math.cos(self.inclination), math.sin(self.inclination)
        cu, su, cw, sw = torch.cos(u), torch.sin(u), torch.cos(raan), torch.sin(raan)
        r, n = self.radius, self.mean_motion
        pos_i = torch.stack([r * (cu * cw - su * ci * sw), r * (cu * sw + su * ci * cw), r * su * si], -1)
        vel_i = torch.stack([r * n * (-su * cw - cu * ci * sw), r * n * (-su * sw + cu * ci * cw), r * n * cu * si], -1)
        ang = (EARTH_RATE * t + theta0)[..., None]
        ca, sa = torch.cos(ang), torch.sin(ang)

        def to_ecef(v: Tensor) -> Tensor:
            return torch.stack([ca * v[..., 0] + sa * v[..., 1], -sa * v[..., 0] + ca * v[..., 1], v[..., 2]], -1)

        pos = to_ecef(pos_i)
        vel = to_ecef(vel_i) - torch.stack([-EARTH_RATE * pos[..., 1], EARTH_RATE * pos[..., 0], torch.zeros_like(pos[..., 2])], -1)
        return pos, vel
