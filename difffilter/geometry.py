"""WGS-84 geometry: geodetic, ECEF and ENU coordinates, gravity, satellite azimuth and elevation.

Conventions: geodetic coordinates ``llh [..., 3]`` are (latitude rad, longitude rad, height m);
ECEF and local ENU coordinates are metres.  :func:`enu_rotation` returns ``C [..., 3, 3]`` whose
rows are the east, north and up unit vectors in ECEF, so ``enu = C (ecef - origin)`` and
``ecef = origin + C^T enu``.  Every function is written with ``...`` indexing, keeps the dtype of
its inputs and is differentiable.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "EARTH_RATE",
    "SPEED_OF_LIGHT",
    "WGS84_A",
    "WGS84_E2",
    "WGS84_F",
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
]

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
EARTH_RATE = 7.2921151467e-5  # rad/s
SPEED_OF_LIGHT = 299792458.0  # m/s


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
