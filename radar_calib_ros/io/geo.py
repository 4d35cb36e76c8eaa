"""WGS 84 <-> local metric frame <-> UTM, and heading conventions.

Why a local frame: UTM grid distances are scaled by up to ~400 ppm against true distances
(k0 = 0.9996 on the central meridian), so a rigid radar-to-world fit done in UTM is biased
by centimetres at 100 m. The numerics therefore run in a transverse Mercator projection
centred on the site with unit scale (``+k=1``): at 1 km from its origin its scale error is
~1e-8. Only the final calibration is converted to UTM, position through latitude/longitude
and rotation by the difference of the two grids' meridian convergence at the radar.

Meridian convergence is computed numerically (the grid direction of a short step towards
true north) rather than from a sign convention; ``test/io/test_geo.py`` checks it against
``pyproj.Proj.get_factors(...).meridian_convergence``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyproj
from numpy.typing import ArrayLike, NDArray

from radar_calib_ros.errors import ConfigError

F64 = NDArray[np.float64]


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS 84 / UTM zone containing a point (326xx north, 327xx south)."""
    if not (-80.0 <= lat_deg <= 84.0):
        raise ConfigError(f'latitude {lat_deg:.4f} deg is outside UTM (80S-84N); set world.epsg')
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    # the grid's two exceptions: zone 32V widened over south-west Norway, and Svalbard's
    # zones 31X-37X (32X, 34X, 36X do not exist)
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon_deg < 12.0:
        zone = 32
    elif lat_deg >= 72.0 and 0.0 <= lon_deg < 42.0:
        zone = 31 if lon_deg < 9.0 else 33 if lon_deg < 21.0 else 35 if lon_deg < 33.0 else 37
    return (32600 if lat_deg >= 0.0 else 32700) + zone


#: A UTM zone whose point scale at the site is off 1 by more than this is too far from it
#: (0.14 m at 70 m of range): the site's own zone's is at most 0.001 off; a neighbour's
#: near the edge they share as little (common use), but 0.002-0.012 from the far side.
_FAR_ZONE_SCALE = 0.002


def zone_note(frame: LocalFrame) -> str | None:
    """A sentence where ``world.epsg`` names a UTM zone of the other hemisphere than the
    site's: the coordinates are right in it, but a northern zone gives a southern site
    negative northings (and a southern one a northern site 10 000 km of false northing),
    most likely a slip in the parameters file (a seventeenth probe's EPSG:32656 at 33.9 S:
    northing -3 755 140 m, not a word); or a zone so far from the site that its grid's
    scale there is off by more than ``_FAR_ZONE_SCALE``. None otherwise (a neighbouring
    zone near the edge it shares with the site's is common use)."""
    zone = pyproj.CRS.from_epsg(frame.epsg).utm_zone
    if zone is None or not (-80.0 <= frame.lat0_deg <= 84.0):
        return None
    south_zone, south_site = zone.upper().endswith('S'), frame.lat0_deg < 0.0
    own = utm_epsg(frame.lat0_deg, frame.lon0_deg)
    if south_zone == south_site:
        scale = frame.utm_scale()
        if abs(scale - 1.0) <= _FAR_ZONE_SCALE:
            return None
        # A zone far from the site: the radar's pose is right in it, but its grid is no
        # longer metres there, so what is placed from the radar lands off by the scale
        # (a sixty-first probe's 32634 for a site in 32N: 0.33-0.38 m at 70 m; 32623, a
        # slip for 32632: 14 m, the yaw 78 deg for 32), not a word said.
        return (f'world.epsg {frame.epsg} (UTM zone {zone}) lies far from the site '
                f'({abs(frame.lon0_deg):.1f} {"W" if frame.lon0_deg < 0.0 else "E"}): '
                f'its grid\'s scale there is {scale:.4f}, so positions placed from the '
                'radar with this result (x_world = R x_sensor + t) are '
                f'{1000.0 * abs(scale - 1.0):.1f} mm per metre of range off '
                f'({70.0 * abs(scale - 1.0):.2f} m at 70 m), though the radar\'s own pose is '
                f'right in that grid. The site\'s own zone is EPSG:{own}.')
    hemisphere = 'southern' if south_zone else 'northern'
    return (f'world.epsg {frame.epsg} is a UTM zone of the {hemisphere} hemisphere ({zone}), '
            f'but the site lies at {abs(frame.lat0_deg):.1f} '
            f'{"S" if south_site else "N"}: its northings are '
            f'{"negative" if south_site else "offset by the southern false northing"}. The '
            f'result is right in that grid; the site\'s own zone is EPSG:{own}.')


@dataclass(frozen=True)
class LocalFrame:
    """Metric site frame: x east, y north (of the local grid), z = ellipsoidal altitude.

    Parameters
    ----------
    lat0_deg, lon0_deg : float
        Origin (the first valid vehicle fix).
    epsg : int
        The UTM world frame results are reported in.
    """

    lat0_deg: float
    lon0_deg: float
    epsg: int
    _to_local: pyproj.Transformer = field(init=False, repr=False, compare=False)
    _to_utm: pyproj.Transformer = field(init=False, repr=False, compare=False)
    _local_proj: pyproj.Proj = field(init=False, repr=False, compare=False)
    _utm_proj: pyproj.Proj = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        local = (f'+proj=tmerc +lat_0={self.lat0_deg:.12f} +lon_0={self.lon0_deg:.12f} +k=1 '
                 '+x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs')
        try:
            utm_crs = pyproj.CRS.from_epsg(self.epsg)
        except pyproj.exceptions.CRSError as err:
            raise ConfigError(f'world.epsg {self.epsg} is not a known EPSG code') from err
        object.__setattr__(self, '_local_proj', pyproj.Proj(local))
        object.__setattr__(self, '_utm_proj', pyproj.Proj(utm_crs))
        object.__setattr__(self, '_to_local', pyproj.Transformer.from_crs(
            'EPSG:4326', pyproj.CRS.from_proj4(local), always_xy=True))
        object.__setattr__(self, '_to_utm', pyproj.Transformer.from_crs(
            'EPSG:4326', utm_crs, always_xy=True))

    @classmethod
    def at(cls, lat_deg: float, lon_deg: float, epsg: int = 0) -> LocalFrame:
        """Frame at a point; ``epsg`` 0 picks the UTM zone of that point."""
        return cls(float(lat_deg), float(lon_deg), epsg or utm_epsg(lat_deg, lon_deg))

    # positions ---------------------------------------------------------------------------
    def geodetic_to_local(self, lat_deg: ArrayLike, lon_deg: ArrayLike,
                          alt_m: ArrayLike) -> F64:
        """(n,) lat, lon [deg], alt [m] -> (n, 3) local [m]."""
        x, y = _project(self._to_local.transform, lon_deg, lat_deg)
        return np.column_stack([np.atleast_1d(x), np.atleast_1d(y),
                                np.atleast_1d(np.asarray(alt_m, float))])

    def local_to_geodetic(self, points_m: ArrayLike) -> tuple[F64, F64, F64]:
        """(n, 3) local -> lat [deg], lon [deg], alt [m], each (n,)."""
        p = np.atleast_2d(np.asarray(points_m, float))
        lon, lat = _project(self._to_local.transform, p[:, 0], p[:, 1], direction='INVERSE')
        return np.atleast_1d(lat), np.atleast_1d(lon), p[:, 2].copy()

    def geodetic_to_utm(self, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> F64:
        """(n,) lat, lon, alt -> (n, 3) easting, northing, altitude."""
        e, n = _project(self._to_utm.transform, lon_deg, lat_deg)
        return np.column_stack([np.atleast_1d(e), np.atleast_1d(n),
                                np.atleast_1d(np.asarray(alt_m, float))])

    def utm_to_geodetic(self, points_utm: ArrayLike) -> tuple[F64, F64, F64]:
        """(n, 3) easting, northing, altitude -> lat, lon, alt."""
        p = np.atleast_2d(np.asarray(points_utm, float))
        lon, lat = _project(self._to_utm.transform, p[:, 0], p[:, 1], direction='INVERSE')
        return np.atleast_1d(lat), np.atleast_1d(lon), p[:, 2].copy()

    def local_to_utm(self, points_m: ArrayLike) -> F64:
        """(n, 3) local -> (n, 3) UTM."""
        return self.geodetic_to_utm(*self.local_to_geodetic(points_m))

    def utm_to_local(self, points_utm: ArrayLike) -> F64:
        """(n, 3) UTM -> (n, 3) local."""
        return self.geodetic_to_local(*self.utm_to_geodetic(points_utm))

    # headings ----------------------------------------------------------------------------
    def local_convergence_rad(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> F64:
        """Clockwise angle from local grid north to true north at points [rad]."""
        return _convergence(self._local_proj, lat_deg, lon_deg)

    def utm_scale(self) -> float:
        """The UTM grid's point scale at the frame's origin (1 + its error per metre)."""
        return float(self._utm_proj.get_factors(self.lon0_deg, self.lat0_deg).meridional_scale)

    def utm_convergence_rad(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> F64:
        """Clockwise angle from UTM grid north to true north at points [rad]."""
        return _convergence(self._utm_proj, lat_deg, lon_deg)

    def true_yaw_to_local(self, yaw_true_rad: ArrayLike, lat_deg: ArrayLike,
                          lon_deg: ArrayLike) -> F64:
        """ENU yaw against true north -> yaw against the local grid (both ccw from east).

        A direction at azimuth A (cw from true north) has grid azimuth A + c, where c is the
        clockwise angle from grid north to true north; yaw = 90 deg - azimuth, so
        yaw_grid = yaw_true - c.
        """
        return np.asarray(yaw_true_rad, float) - self.local_convergence_rad(lat_deg, lon_deg)

    def rotation_local_to_utm(self, at_local_m: ArrayLike) -> F64:
        """(3, 3) rotation from local-grid axes to UTM-grid axes at a local point.

        yaw_utm = yaw_true - c_utm = yaw_local + c_local - c_utm: a rotation about z.
        """
        lat, lon, _ = self.local_to_geodetic(np.reshape(np.asarray(at_local_m, float), (1, 3)))
        angle = float(self.local_convergence_rad(lat, lon)[0]
                      - self.utm_convergence_rad(lat, lon)[0])
        c, s = np.cos(angle), np.sin(angle)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _project(fn: Any, x: ArrayLike, y: ArrayLike, **kwargs: Any) -> tuple[F64, F64]:
    """pyproj's transform of coordinate arrays, (n,) each. One point goes as two floats:
    pyproj 3.7 turns a one-element array into a scalar itself, which NumPy 1.25-1.26 (ROS 2
    Jazzy's on Ubuntu 24.04) warns is deprecated, on every calibration (a probe on a real
    Jazzy build; with warnings as errors the node reported it as an internal error)."""
    xs = np.atleast_1d(np.asarray(x, float))
    ys = np.atleast_1d(np.asarray(y, float))
    if xs.size == 1 and ys.size == 1:
        a, b = fn(float(xs[0]), float(ys[0]), **kwargs)
        return np.array([a], float), np.array([b], float)
    a, b = fn(xs, ys, **kwargs)
    return np.asarray(a, float), np.asarray(b, float)


def _convergence(proj: pyproj.Proj, lat_deg: ArrayLike, lon_deg: ArrayLike) -> F64:
    lat = np.atleast_1d(np.asarray(lat_deg, float))
    lon = np.atleast_1d(np.asarray(lon_deg, float))
    step = 1e-5  # deg of latitude, ~1.1 m: far below any curvature that matters here
    x0, y0 = _project(proj, lon, lat)
    x1, y1 = _project(proj, lon, lat + step)
    return np.asarray(np.arctan2(np.asarray(x1) - np.asarray(x0),
                                 np.asarray(y1) - np.asarray(y0)), np.float64)
