"""WGS-84 geometry and a simple GNSS constellation (papers p001, p003 and the smartLoc data).

Conventions: geodetic coordinates ``llh [..., 3]`` are (latitude rad, longitude rad, height m);
ECEF and local ENU coordinates are metres.  :func:`enu_rotation` returns ``C [..., 3, 3]`` whose
rows are the east, north and up unit vectors in ECEF, so ``enu = C (ecef - origin)`` and
``ecef = origin + C^T enu``.  Every function is written with ``...`` indexing, keeps the dtype of
its inputs and is differentiable.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "EARTH_RATE",
    "GPS_ORBIT_RADIUS",
    "GM_EARTH",
    "SPEED_OF_LIGHT",
    "WGS84_A",
    "WGS84_E2",
    "WGS84_F",
    "CircularOrbitConstellation",
    "azimuth_elevation",
    "ecef_displacement",
    "ecef_to_enu",
    "ecef_to_geodetic",
    "enu_rotation",
    "enu_to_ecef",
    "geodetic_jacobian",
    "geodetic_to_ecef",
    "normal_gravity",
    "radii_of_curvature",
    "satellites_from_azimuth_elevation",
]

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
EARTH_RATE = 7.2921151467e-5  # rad/s
SPEED_OF_LIGHT = 299792458.0  # m/s
GM_EARTH = 3.986004418e14  # m^3/s^2
GPS_ORBIT_RADIUS = 26_560_000.0  # m


def radii_of_curvature(lat: Tensor) -> tuple[Tensor, Tensor]:
    """Meridian ``R_M`` and prime-vertical ``R_N`` radii of curvature at latitude ``lat`` (rad)."""
    q = 1.0 - WGS84_E2 * torch.sin(lat) ** 2
    rn = WGS84_A / torch.sqrt(q)
    return rn * (1.0 - WGS84_E2) / q, rn


def normal_gravity(lat: Tensor, h: Tensor) -> Tensor:
    """Magnitude of normal gravity ``g(L, h) = g_0 (1 + 5.27094e-3 sin^2 L + 2.32718e-5 sin^4 L) - 3.086e-6 h``."""
    s2 = torch.sin(lat) ** 2
    return 9.7803267714 * (1.0 + 5.27094e-3 * s2 + 2.32718e-5 * s2 * s2) - 3.086e-6 * h


def geodetic_to_ecef(llh: Tensor) -> Tensor:
    """``llh [..., 3]`` -> ECEF ``[..., 3]``: ``((N+h) cos L cos l, (N+h) cos L sin l, (N(1-e^2)+h) sin L)``."""
    lat, lon, h = llh.unbind(-1)
    _, rn = radii_of_curvature(lat)
    cl = torch.cos(lat)
    return torch.stack([(rn + h) * cl * torch.cos(lon), (rn + h) * cl * torch.sin(lon), (rn * (1.0 - WGS84_E2) + h) * torch.sin(lat)], -1)


def ecef_to_geodetic(xyz: Tensor, iterations: int = 6) -> Tensor:
    """ECEF ``[..., 3]`` -> ``llh [..., 3]`` by fixed-point iteration on latitude (mm-exact after 4 steps)."""
    x, y, z = xyz.unbind(-1)
    p = torch.sqrt(x * x + y * y)
    lon = torch.atan2(y, x)
    lat = torch.atan2(z, p * (1.0 - WGS84_E2))
    for _ in range(iterations):
        _, rn = radii_of_curvature(lat)
        h = p / torch.cos(lat) - rn
        lat = torch.atan2(z, p * (1.0 - WGS84_E2 * rn / (rn + h)))
    _, rn = radii_of_curvature(lat)
    h = p / torch.cos(lat) - rn
    return torch.stack([lat, lon, h], -1)


def enu_rotation(lat: Tensor, lon: Tensor) -> Tensor:
    """``C [..., 3, 3]`` with rows east, north, up (ECEF components): ``enu = C ecef``."""
    sl, cl, so, co = torch.sin(lat), torch.cos(lat), torch.sin(lon), torch.cos(lon)
    zero = torch.zeros_like(sl)
    east = torch.stack([-so, co, zero], -1)
    north = torch.stack([-sl * co, -sl * so, cl], -1)
    up = torch.stack([cl * co, cl * so, sl], -1)
    return torch.stack([east, north, up], -2)


def ecef_to_enu(xyz: Tensor, origin_ecef: Tensor) -> Tensor:
    """ENU coordinates ``[..., 3]`` of ECEF points relative to ``origin_ecef [..., 3]``."""
    llh0 = ecef_to_geodetic(origin_ecef)
    rot = enu_rotation(llh0[..., 0], llh0[..., 1])
    return ((xyz - origin_ecef)[..., None, :] @ rot.mT)[..., 0, :]


def enu_to_ecef(enu: Tensor, origin_ecef: Tensor) -> Tensor:
    """Inverse of :func:`ecef_to_enu`."""
    llh0 = ecef_to_geodetic(origin_ecef)
    rot = enu_rotation(llh0[..., 0], llh0[..., 1])
    return origin_ecef + (enu[..., None, :] @ rot)[..., 0, :]


def geodetic_jacobian(llh: Tensor) -> Tensor:
    """``d ecef / d (L, l, h)`` ``[..., 3, 3]``: columns ``(R_M+h) n``, ``(R_N+h) cos L e``, ``u``."""
    lat, lon, h = llh.unbind(-1)
    rm, rn = radii_of_curvature(lat)
    rot = enu_rotation(lat, lon)
    return torch.stack([(rm + h)[..., None] * rot[..., 1, :], ((rn + h) * torch.cos(lat))[..., None] * rot[..., 0, :], rot[..., 2, :]], -1)


def _sin_diff(a: Tensor, d: Tensor) -> Tensor:
    # sin(a) - sin(a - d) without cancellation
    return 2.0 * torch.cos(a - 0.5 * d) * torch.sin(0.5 * d)


def _cos_diff(a: Tensor, d: Tensor) -> Tensor:
    return -2.0 * torch.sin(a - 0.5 * d) * torch.sin(0.5 * d)


def ecef_displacement(llh: Tensor, dllh: Tensor) -> Tensor:
    """``ecef(llh) - ecef(llh - dllh)`` ``[..., 3]``, exact and free of cancellation.

    The direct difference of two ~6.4e6 m vectors loses every digit below 0.5 m in float32; here
    each factor difference is written with the sum-to-product identities (``cos a - cos b``,
    ``N(L) - N(L')`` through ``q' - q = e^2 (s - s')(s + s')``), so the result has full relative
    precision even for millimetre displacements.
    """
    lat, lon, h = llh.unbind(-1)
    dlat, dlon, dh = dllh.unbind(-1)
    lat2, h2 = lat - dlat, h - dh
    s, s2 = torch.sin(lat), torch.sin(lat2)
    q, q2 = 1.0 - WGS84_E2 * s * s, 1.0 - WGS84_E2 * s2 * s2
    rq, rq2 = torch.sqrt(q), torch.sqrt(q2)
    ds = _sin_diff(lat, dlat)
    dn = WGS84_A * (WGS84_E2 * ds * (s + s2)) / (rq * rq2 * (rq + rq2))  # N - N'
    n2 = WGS84_A / rq2
    a2 = n2 + h2
    da = dn + dh
    cl, cl2 = torch.cos(lat), torch.cos(lat2)
    co, so = torch.cos(lon), torch.sin(lon)
    dcl = _cos_diff(lat, dlat)
    dco, dso = _cos_diff(lon, dlon), _sin_diff(lon, dlon)
    bx, by = cl * co, cl * so
    dbx = dcl * co + cl2 * dco
    dby = dcl * so + cl2 * dso
    dx = da * bx + a2 * dbx
    dy = da * by + a2 * dby
    # Z = (N (1 - e^2) + h) sin L
    az2 = n2 * (1.0 - WGS84_E2) + h2
    dz = (dn * (1.0 - WGS84_E2) + dh) * s + az2 * ds
    return torch.stack([dx, dy, dz], -1)


def azimuth_elevation(receiver_ecef: Tensor, sat_ecef: Tensor) -> tuple[Tensor, Tensor]:
    """Azimuth (clockwise from north) and elevation (rad) of satellites ``[..., K, 3]`` seen
    from ``receiver_ecef [..., 3]``; both ``[..., K]``."""
    llh = ecef_to_geodetic(receiver_ecef)
    rot = enu_rotation(llh[..., 0], llh[..., 1])
    los = (sat_ecef - receiver_ecef[..., None, :]) @ rot.mT
    e, n, u = los.unbind(-1)
    return torch.atan2(e, n), torch.atan2(u, torch.sqrt(e * e + n * n))


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
