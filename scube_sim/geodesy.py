"""WGS-84 geodesy: geodetic <-> ECEF, and local East-North-Up (ENU) frames.

Units and frames:

- Geodetic: latitude and longitude in **degrees** (north / east positive), ellipsoidal height
  in metres above the WGS-84 ellipsoid.
- ECEF: Earth-centred, Earth-fixed Cartesian coordinates in metres (x through lat 0 / lon 0,
  z through the north pole), float64.
- ENU: a local tangent frame at an origin: x east, y north, z up (along the ellipsoid normal),
  metres, float64. Right-handed, so "yaw" about its z is counter-clockwise from east.

All functions accept a single point (3,) or an array (N, 3) and return float64 of the same shape.
"""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0  # semi-major axis, m
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_B = WGS84_A * (1.0 - WGS84_F)  # semi-minor axis, m
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared


def geodetic_to_ecef(lla) -> np.ndarray:
    """(..., 3) [lat deg, lon deg, height m] -> (..., 3) ECEF metres, float64."""
    lla = np.asarray(lla, dtype=np.float64)
    lat = np.deg2rad(lla[..., 0])
    lon = np.deg2rad(lla[..., 1])
    h = lla[..., 2]
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)  # prime-vertical radius of curvature
    x = (n + h) * cl * np.cos(lon)
    y = (n + h) * cl * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(xyz) -> np.ndarray:
    """(..., 3) ECEF metres -> (..., 3) [lat deg, lon deg, height m], float64.

    Bowring's closed form followed by two Newton-style refinements of the latitude: sub-millimetre
    (and better than 1e-11 deg) from the Earth's centre region outwards to orbit altitudes."""
    xyz = np.asarray(xyz, dtype=np.float64)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    # Bowring's initial estimate via the parametric latitude
    beta = np.arctan2(WGS84_A * z, WGS84_B * p)
    lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
                     p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
                         p - WGS84_E2 * WGS84_A * np.cos(beta) ** 3)
    sl, cl = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl * sl)
    # height: stable formula for all latitudes (no division by cos(lat) near the poles)
    h = p * cl + z * sl - WGS84_A * WGS84_A / n
    return np.stack([np.rad2deg(lat), np.rad2deg(lon), h], axis=-1)


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) float64 rotation R_ecef_enu whose columns are the east, north and up unit vectors
    (in ECEF) at geodetic (lat, lon) in degrees: ``v_ecef = R @ v_enu``, ``v_enu = R.T @ v_ecef``."""
    lat, lon = np.deg2rad(float(lat_deg)), np.deg2rad(float(lon_deg))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    east = np.array([-so, co, 0.0])
    north = np.array([-sl * co, -sl * so, cl])
    up = np.array([cl * co, cl * so, sl])
    return np.column_stack([east, north, up])


def ecef_to_enu(points, origin_ecef) -> np.ndarray:
    """(..., 3) ECEF metres -> (..., 3) ENU metres (x east, y north, z up) in the tangent frame
    at `origin_ecef` (3,) ECEF metres; the origin maps to (0, 0, 0)."""
    points = np.asarray(points, dtype=np.float64)
    origin = np.asarray(origin_ecef, dtype=np.float64).reshape(3)
    lat, lon, _ = ecef_to_geodetic(origin)
    r = enu_rotation(lat, lon)
    return (points - origin) @ r


def enu_to_ecef(points, origin_ecef) -> np.ndarray:
    """Inverse of `ecef_to_enu`: (..., 3) ENU metres at `origin_ecef` -> (..., 3) ECEF metres."""
    points = np.asarray(points, dtype=np.float64)
    origin = np.asarray(origin_ecef, dtype=np.float64).reshape(3)
    lat, lon, _ = ecef_to_geodetic(origin)
    return points @ enu_rotation(lat, lon).T + origin
