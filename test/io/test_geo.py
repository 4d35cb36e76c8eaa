"""io.geo: UTM zones, meridian convergence against pyproj, local-frame round trips.

Sign relation (checked below): ``LocalFrame.utm_convergence_rad`` is the clockwise angle
from grid north to true north; pyproj's ``Proj.get_factors(...).meridian_convergence`` is
the clockwise angle from true north to grid north (positive east of the central meridian
in the northern hemisphere). Hence ours == -radians(pyproj's).
"""
from __future__ import annotations

import math

import numpy as np
import pyproj
import pytest

from radar_calib_ros.errors import ConfigError
from radar_calib_ros.io.geo import LocalFrame, utm_epsg

SITES = [  # (lat, lon): both hemispheres, both sides of central meridians, high latitude
    (48.137, 8.2), (48.137, 11.9), (52.52, 13.405), (-33.92, 18.42), (-33.92, 22.9),
    (-45.0, 170.1), (1.3, 103.8), (64.5, -21.9), (-0.5, -78.4), (70.0, 25.0)]


@pytest.mark.parametrize('lat, lon, epsg', [
    (48.137, 11.575, 32632), (48.0, 5.99, 32631), (-33.92, 18.42, 32734), (0.0, 0.0, 32631),
    (-0.001, -0.001, 32730), (40.7, -74.0, 32618), (-45.0, 179.99, 32760),
    (60.0, 4.0, 32632), (58.0, 11.9, 32632), (55.9, 4.0, 32631),  # zone 32V is widened
    (78.2, 15.6, 32633), (78.0, 8.9, 32631), (78.0, 30.0, 32635), (80.0, 40.0, 32637)])
def test_utm_zone(lat: float, lon: float, epsg: int) -> None:
    assert utm_epsg(lat, lon) == epsg


def test_utm_zone_outside_utm() -> None:
    with pytest.raises(ConfigError, match='outside UTM'):
        utm_epsg(85.0, 10.0)


@pytest.mark.parametrize('lat, lon', SITES)
def test_utm_convergence_against_pyproj(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    proj = pyproj.Proj(pyproj.CRS.from_epsg(frame.epsg))
    expected_deg = proj.get_factors(lon, lat).meridian_convergence
    ours_deg = math.degrees(frame.utm_convergence_rad(lat, lon)[0])
    assert ours_deg == pytest.approx(-expected_deg, abs=1e-6)
    # and the geometry: west of the central meridian in the north, true north lies
    # clockwise of grid north
    central = -183.0 + 6.0 * (frame.epsg % 100)
    west = lon < central
    assert (ours_deg > 0) == (west == (lat > 0))


def test_convergence_in_western_zone_32n_is_about_07_deg() -> None:
    frame = LocalFrame.at(48.0, 8.0)
    assert math.degrees(frame.utm_convergence_rad(48.0, 8.0)[0]) == pytest.approx(
        math.sin(math.radians(48.0)) * 1.0, abs=0.01)


@pytest.mark.parametrize('lat, lon', SITES)
def test_local_convergence_against_pyproj_local_tmerc(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    point_lat, point_lon = lat + 0.01, lon + 0.02
    proj = pyproj.Proj(f'+proj=tmerc +lat_0={lat} +lon_0={lon} +k=1 +ellps=WGS84')
    expected = -proj.get_factors(point_lon, point_lat).meridian_convergence
    assert math.degrees(frame.local_convergence_rad(point_lat, point_lon)[0]) == \
        pytest.approx(expected, abs=1e-6)
    # zero on the local frame's own meridian
    assert abs(frame.local_convergence_rad(lat + 0.01, lon)[0]) < 1e-9


@pytest.mark.parametrize('lat, lon', SITES)
def test_utm_positions_match_pyproj(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    rng = np.random.default_rng(1)
    lats = lat + rng.uniform(-0.01, 0.01, 20)
    lons = lon + rng.uniform(-0.01, 0.01, 20)
    alts = rng.uniform(0, 500, 20)
    transformer = pyproj.Transformer.from_crs('EPSG:4326', f'EPSG:{frame.epsg}',
                                              always_xy=True)
    e, n = transformer.transform(lons, lats)
    np.testing.assert_allclose(frame.geodetic_to_utm(lats, lons, alts),
                               np.column_stack([e, n, alts]), rtol=0, atol=1e-6)


@pytest.mark.parametrize('lat, lon', SITES)
def test_local_round_trips(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    rng = np.random.default_rng(2)
    local = rng.uniform(-1500, 1500, size=(30, 3))
    lat_b, lon_b, alt_b = frame.local_to_geodetic(local)
    np.testing.assert_allclose(frame.geodetic_to_local(lat_b, lon_b, alt_b), local, atol=1e-6)
    utm = frame.local_to_utm(local)
    np.testing.assert_allclose(frame.utm_to_local(utm), local, atol=1e-6)
    # the origin is the site itself
    np.testing.assert_allclose(frame.geodetic_to_local(lat, lon, 0.0), [[0.0, 0.0, 0.0]],
                               atol=1e-9)


def test_local_frame_is_true_to_scale_but_utm_is_not() -> None:
    """Why the numerics run in the local frame: UTM near the central meridian shrinks
    distances by ~400 ppm, the local frame keeps them to ~1e-8 within a kilometre."""
    lat, lon = 48.137, 9.01  # near the central meridian of zone 32
    frame = LocalFrame.at(lat, lon)
    geod = pyproj.Geod(ellps='WGS84')
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[300.0, 400.0, 0.0]])  # 500 m away in the local frame
    lats, lons, _ = frame.local_to_geodetic(np.vstack([a, b]))
    _, _, true_m = geod.inv(lons[0], lats[0], lons[1], lats[1])
    assert np.linalg.norm(b - a) == pytest.approx(true_m, rel=1e-7)
    utm = frame.local_to_utm(np.vstack([a, b]))
    assert np.linalg.norm(utm[1, :2] - utm[0, :2]) / true_m == pytest.approx(0.9996, abs=2e-5)


@pytest.mark.parametrize('lat, lon', [(48.137, 8.2), (-33.92, 22.9), (64.5, -21.9)])
def test_true_yaw_to_local_follows_a_geodesic_direction(lat: float, lon: float) -> None:
    """A step at true azimuth A, 2 km from the frame origin, has local yaw = 90 deg - A -
    local convergence (here ~0.02 deg, far above the tolerance)."""
    frame = LocalFrame.at(lat, lon)
    geod = pyproj.Geod(ellps='WGS84')
    start_lat, start_lon, _ = frame.local_to_geodetic([[2000.0, 1500.0, 0.0]])
    for azimuth_deg in (0.0, 37.0, 135.0, -100.0):
        end_lon, end_lat, _ = geod.fwd(start_lon[0], start_lat[0], azimuth_deg, 1.0)
        p = frame.geodetic_to_local([start_lat[0], end_lat], [start_lon[0], end_lon], [0, 0])
        yaw_local = math.atan2(p[1, 1] - p[0, 1], p[1, 0] - p[0, 0])
        yaw_true = math.radians(90.0 - azimuth_deg)
        converted = frame.true_yaw_to_local(yaw_true, start_lat, start_lon)[0]
        error = (converted - yaw_local + math.pi) % (2 * math.pi) - math.pi
        assert abs(error) < 2e-7
        assert abs((yaw_true - yaw_local + math.pi) % (2 * math.pi) - math.pi) > 1e-4


@pytest.mark.parametrize('lat, lon', [(48.137, 7.1), (-33.92, 22.9)])
def test_rotation_local_to_utm_maps_directions(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    at = np.array([800.0, -600.0, 0.0])
    rotation = frame.rotation_local_to_utm(at)
    step = np.array([3.0, 4.0, 0.0])
    utm = frame.local_to_utm(np.vstack([at, at + step]))
    direction_utm = (utm[1] - utm[0]) / np.linalg.norm(utm[1] - utm[0])
    np.testing.assert_allclose(rotation @ step / 5.0, direction_utm, atol=1e-7)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)


def test_unknown_epsg_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match='world.epsg 1 is not a known EPSG'):
        LocalFrame(48.0, 11.0, 1)


def test_a_zone_of_the_other_hemisphere_is_noted() -> None:
    """A northern zone for a southern site (negative northings) and the other way round
    are named with the site's own zone; the site's zone, a neighbour near the edge they
    share and ETRS89 are not."""
    from radar_calib_ros.io.geo import zone_note
    north = zone_note(LocalFrame.at(-33.9, 151.2, 32656))
    assert north is not None and 'northern hemisphere (56N)' in north
    assert '33.9 S' in north and 'negative' in north and 'EPSG:32756' in north
    south = zone_note(LocalFrame.at(48.1, 9.0, 32732))
    assert south is not None and 'southern hemisphere' in south and 'EPSG:32632' in south
    for lat, lon, epsg in ((-33.9, 151.2, 32756), (-33.9, 151.2, 32755), (48.1, 11.6, 32633),
                           (48.1, 9.0, 25832), (0.5, 108.0, 32649)):
        assert zone_note(LocalFrame.at(lat, lon, epsg)) is None


def test_a_zone_far_from_the_site_is_noted_with_its_scale() -> None:
    """A zone two away, or a neighbour from the far side of the site's zone: the radar's
    pose is right in it, but positions placed from the radar land off by the grid's scale
    (a sixty-first probe's 32634 and 32623 for Munich: 0.35 m and 14 m at 70 m, unsaid)."""
    from radar_calib_ros.io.geo import zone_note
    two_away = zone_note(LocalFrame.at(48.1, 11.6, 32634))
    assert two_away is not None and 'UTM zone 34N' in two_away
    assert '1.0056' in two_away and '0.39 m at 70 m' in two_away and 'EPSG:32632' in two_away
    slip = zone_note(LocalFrame.at(48.1, 11.6, 32623))
    assert slip is not None and '204.0 mm per metre' in slip
    far_side = zone_note(LocalFrame.at(48.1, 9.0, 32633))
    assert far_side is not None and '1.0021' in far_side
