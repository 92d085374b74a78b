"""Local metric frames for geodetic tracks (WGS84), computed with pymap3d.

A frame is the local tangent plane at an origin (lat0, lon0): east and north in metres are
the ENU coordinates of the report projected to height 0 (so horizontal distances are those
on the ellipsoid), and the third axis, when the data carry altitude, is the altitude above
the origin's (ENU "up" would also hold the Earth's curvature drop, d² / 2R: 4.9 km at
250 km). A horizontal displacement at angular distance θ from the origin is foreshortened
by at most 1 − cos θ ≈ θ² / 2 (7.7e-4 at 250 km): :func:`~torchsde_lti.data.load_tracks`
keeps every track within ``max_extent`` of its own origin. ENU is built from trigonometric
functions of latitude and longitude, so the antimeridian, unwrapped longitudes and high
latitudes need no special case.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EARTH_MEAN_RADIUS", "angular_distance", "local_positions", "local_velocities"]

#: IUGG mean Earth radius (m), for distances used as thresholds (gaps, jumps, extents).
EARTH_MEAN_RADIUS = 6_371_008.8
#: One international knot in m/s.
KNOT = 1852.0 / 3600.0


def _pymap3d():  # noqa: ANN202 - module
    try:
        import pymap3d
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ModuleNotFoundError("geodetic frames need pymap3d: pip install 'torchsde_lti[data]'") from err
    return pymap3d


def angular_distance(lat1: np.ndarray, lon1: np.ndarray, lat2: np.ndarray, lon2: np.ndarray) -> np.ndarray:
    """Great-circle angle between points, in radians (haversine, pymap3d), broadcast shapes."""
    from pymap3d.haversine import anglesep

    return np.radians(anglesep(lon1, lat1, lon2, lat2))


def local_positions(
    lat: np.ndarray,
    lon: np.ndarray,
    lat0: np.ndarray,
    lon0: np.ndarray,
    alt: np.ndarray | None = None,
    alt0: np.ndarray | None = None,
) -> np.ndarray:
    """Positions in the frames at (lat0, lon0): (N, 2) east, north, or (N, 3) with altitude.

    Args:
        lat, lon: (N,) degrees; lat0, lon0: (N,) or scalars, each report's frame origin.
        alt, alt0: (N,) metres and its origin's altitude; None = 2-D.
    """
    pm = _pymap3d()
    zero = np.zeros_like(np.asarray(lat, dtype=np.float64))
    east, north, _ = pm.geodetic2enu(lat, lon, zero, lat0, lon0, zero)
    if alt is None:
        return np.stack([east, north], axis=-1)
    return np.stack([east, north, np.asarray(alt, dtype=np.float64) - (0.0 if alt0 is None else alt0)], axis=-1)


def local_velocities(
    speed: np.ndarray, course: np.ndarray, lat: np.ndarray, lon: np.ndarray, lat0: np.ndarray, lon0: np.ndarray
) -> np.ndarray:
    """Velocity (N, 2) east, north in m/s in each report's frame at (lat0, lon0).

    speed (m/s) and course (degrees clockwise from true north) are taken in the report's own
    east/north, [s sin c, s cos c, 0], then rotated into the frame (ENU at the report -> ECEF
    -> ENU at the origin). NaN in, NaN out; speed 0 gives 0 whatever the course.
    """
    pm = _pymap3d()
    c = np.radians(course)
    still = speed == 0.0
    ve = np.where(still, 0.0, speed * np.sin(c))
    vn = np.where(still, 0.0, speed * np.cos(c))
    u, v, w = pm.enu2uvw(ve, vn, np.zeros_like(ve), lat, lon)
    e, n, _ = pm.uvw2enu(u, v, w, lat0, lon0)
    return np.stack([e, n], axis=-1)
