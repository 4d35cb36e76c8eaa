"""Stage 4: the ground plane and R_alpha_beta."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from radar_calib_ros.config import GroundConfig
from radar_calib_ros.core import ground_plane
from radar_calib_ros.core.ground_plane import fit_ground_plane, level_rotation
from radar_calib_ros.errors import InsufficientDataError

ROLL_DEG, PITCH_DEG, HEIGHT_M = 1.5, 8.0, 7.0


def _scene(seed: int, n: int = 150_000, ghosts: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Moving targets of a roadside radar: vehicles on eight lanes 10-80 m ahead, reflections
    anywhere from the road to 1.5 m up, multipath ghosts mirrored below the road, and the
    radar's noise in spherical coordinates (range 0.15 m, azimuth 0.3 deg, elevation 1.5
    deg). Returns the targets in the sensor frame and the true road normal there."""
    rng = np.random.default_rng(seed)
    lanes = np.array([-12.0, -8.5, -5.0, -1.5, 1.5, 5.0, 8.5, 12.0])
    x = rng.uniform(10.0, 80.0, n)
    y = rng.choice(lanes, n) + rng.uniform(-0.9, 0.9, n)
    z = rng.uniform(0.0, 1.5, n)
    ghost = rng.random(n) < ghosts
    z[ghost] = -z[ghost]
    world = np.column_stack([x, y, z - HEIGHT_M])
    rotation = Rotation.from_euler('xyz', [ROLL_DEG, PITCH_DEG, 0.0], degrees=True).as_matrix()
    sensor = world @ rotation                        # rotation.T @ p for each row
    r = np.linalg.norm(sensor, axis=1)
    az = np.arctan2(sensor[:, 1], sensor[:, 0]) + np.radians(rng.normal(0.0, 0.3, n))
    el = np.arcsin(sensor[:, 2] / r) + np.radians(rng.normal(0.0, 1.5, n))
    r = r + rng.normal(0.0, 0.15, n)
    noisy = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                             r * np.sin(el)])
    return noisy, rotation.T @ np.array([0.0, 0.0, 1.0])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def test_recovers_known_roll_and_pitch() -> None:
    points, up = _scene(seed=7)
    plane = fit_ground_plane(points, GroundConfig())
    assert _angle_deg(plane.normal, up) < 0.05
    assert plane.normal @ up > 0.0                    # pointing up, to the sensor's side
    # the mean reflection height sits in the offset, not in the normal
    assert -HEIGHT_M < plane.offset_m < -HEIGHT_M + 1.0
    np.testing.assert_allclose(plane.rotation_level @ plane.normal, [0.0, 0.0, 1.0],
                               atol=1e-12)
    assert plane.used.size > 0.5 * points.shape[0]


def test_yaw_of_the_radar_does_not_change_the_plane() -> None:
    """Equivariance of the public fit under rotations about the sensor's vertical axis
    (they keep every target's elevation and its error direction)."""
    points, _ = _scene(seed=3, n=40_000)
    plane = fit_ground_plane(points, GroundConfig())
    yaw = Rotation.from_euler('z', 37.0, degrees=True).as_matrix()
    turned = fit_ground_plane(points @ yaw.T, GroundConfig())
    np.testing.assert_allclose(turned.normal, yaw @ plane.normal, atol=1e-9)
    assert turned.offset_m == pytest.approx(plane.offset_m, abs=1e-9)


@settings(deadline=None, max_examples=20)
@given(st.integers(0, 2**31 - 1))
def test_plane_fit_equivariant_under_rigid_motion(seed: int) -> None:
    """The fit itself (SVD start, cells, gate, corrected least squares) moves with the
    cloud when the error directions move with it."""
    rng = np.random.default_rng(seed)
    points, _ = _scene(seed=seed % 1000, n=5_000)
    directions = ground_plane.elevation_directions(points)
    cell = rng.integers(0, 8, points.shape[0])
    start, _ = ground_plane._svd_plane(points, np.ones(points.shape[0]))
    normal, centroid, keep = ground_plane._robust_plane(points, directions, start, cell)
    rotation = Rotation.random(random_state=rng).as_matrix()
    shift = rng.uniform(-50.0, 50.0, 3)
    moved = points @ rotation.T + shift
    start_m, _ = ground_plane._svd_plane(moved, np.ones(points.shape[0]))
    normal_m, centroid_m, keep_m = ground_plane._robust_plane(
        moved, directions @ rotation.T, start_m, cell)
    np.testing.assert_array_equal(keep, keep_m)
    sign = np.sign(normal_m @ (rotation @ normal))
    np.testing.assert_allclose(sign * normal_m, rotation @ normal, atol=1e-9)
    np.testing.assert_allclose(centroid_m, rotation @ centroid + shift, atol=1e-7)


def test_normal_points_to_the_sensor_side() -> None:
    points, _ = _scene(seed=1, n=20_000)
    for flip in (1.0, -1.0):                         # the road below, then above the radar
        plane = fit_ground_plane(points * [1.0, 1.0, flip], GroundConfig())
        assert plane.offset_m < 0.0
        assert plane.normal[2] * flip > 0.0


def test_a_road_at_the_radars_own_height_keeps_the_normal_up() -> None:
    """Traffic on a bridge beside the radar (an independent overpass: the bridge's cars
    0-1 m above a radar 6.5 m up) puts the targets' plane at or above the sensor: which
    side the sensor is on says nothing, and the recording was refused as a mirror image.
    Near the sensor, up is the sensor's z; far from it, the sensor's side as before."""
    points, up = _scene(seed=3, n=20_000)
    raised = points + up * (HEIGHT_M - 0.3)       # the road 0.3 m under the radar
    plane = fit_ground_plane(raised, GroundConfig())
    assert plane.normal @ up > 0.0 and _angle_deg(plane.normal, up) < 0.2
    assert abs(plane.offset_m) < ground_plane._SIDE_MARGIN_M


def test_static_facade_and_sparse_clutter_do_not_tilt_the_plane() -> None:
    points, up = _scene(seed=11, n=60_000)
    rng = np.random.default_rng(11)
    # a sparse scatter of clutter all over the field of view, 4 % of the targets
    clutter = np.column_stack([rng.uniform(10.0, 80.0, 2500), rng.uniform(-40.0, 40.0, 2500),
                               rng.uniform(-8.0, 4.0, 2500)])
    plane = fit_ground_plane(np.concatenate([points, clutter]), GroundConfig())
    assert _angle_deg(plane.normal, up) < 0.1


def test_one_dense_path_along_the_boresight_does_not_stand_the_plane_on_edge() -> None:
    """A cyclist riding to and fro beside the pole, along the boresight, for the whole
    recording is the densest place by far: kept alone, its line left the plane free to turn
    about it, and its elevation noise stood it on edge (an independent probe: a vertical
    'ground' 1 m beside the radar, the recording refused as 'vehicle never in view'). The
    road's lanes 8 m aside bring the plane back."""
    rng = np.random.default_rng(5)
    n_path, n_road = 40_000, 4_000
    path = np.column_stack([rng.uniform(3.0, 40.0, n_path), rng.normal(-1.0, 0.1, n_path),
                            rng.uniform(0.3, 1.2, n_path)])
    road = np.column_stack([rng.uniform(10.0, 90.0, n_road),
                            rng.choice([6.25, 9.75], n_road) + rng.uniform(-0.9, 0.9, n_road),
                            rng.uniform(0.0, 1.2, n_road)])
    world = np.concatenate([path, road]) - np.array([0.0, 0.0, HEIGHT_M])
    r = np.linalg.norm(world, axis=1)
    az = np.arctan2(world[:, 1], world[:, 0]) + np.radians(rng.normal(0.0, 0.3, r.size))
    el = np.arcsin(world[:, 2] / r) + np.radians(rng.normal(0.0, 1.5, r.size))
    points = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                              r * np.sin(el)])
    up = np.array([0.0, 0.0, 1.0])
    # the path alone is as good as a line: the paper's 20 % keeps only it
    dense_only = fit_ground_plane(points[:n_path], GroundConfig())
    assert _angle_deg(dense_only.normal, up) > 10.0
    plane = fit_ground_plane(points, GroundConfig())
    assert _angle_deg(plane.normal, up) < 3.0 and plane.normal @ up > 0.0
    assert np.count_nonzero(plane.used >= n_path) > 0.1 * n_road


def test_too_few_or_collinear_targets_cannot_make_a_plane() -> None:
    with pytest.raises(InsufficientDataError):
        fit_ground_plane(np.array([[1.0, 0.0, -5.0], [2.0, 0.0, -5.0], [np.nan, 0, 0]]),
                         GroundConfig())
    line = np.column_stack([np.linspace(5.0, 50.0, 200), np.zeros(200), np.full(200, -6.0)])
    with pytest.raises(InsufficientDataError):
        fit_ground_plane(line, GroundConfig())


@settings(deadline=None, max_examples=200)
@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(0.05, 1.0))
def test_level_rotation_is_the_smallest_rotation_to_z(nx: float, ny: float, nz: float) -> None:
    normal = np.array([nx, ny, nz]) / np.linalg.norm([nx, ny, nz])
    rotation = level_rotation(normal)
    np.testing.assert_allclose(rotation @ normal, [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    # no yaw: the axis is horizontal, so the horizontal direction normal x z is kept
    axis = np.cross(normal, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(rotation @ axis, axis, atol=1e-12)
    # and the rotation angle is just the tilt of the normal
    angle = math.acos(max(-1.0, min(1.0, (np.trace(rotation) - 1.0) / 2.0)))
    assert angle == pytest.approx(math.acos(normal[2]), abs=1e-7)


def _tracked_scene(seed: int, rain_per_frame: int,
                   lanes: tuple[float, ...] = (-12.0, -8.5, -5.0, -1.5, 1.5, 5.0, 8.5, 12.0),
                   rise_m: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Road users driving along eight lanes 10-80 m ahead (a track each, 10 targets a frame
    at 15 Hz, reflections 0-1.5 m above the road), plus rain: ``rain_per_frame`` returns a
    frame anywhere within 15 m of the radar and +-10 deg of its beam, whose clusters chain
    into "tracks" of ten frames. Returns sensor-frame targets, frame times [s], track ids
    and the true road normal in the sensor frame."""
    rng = np.random.default_rng(seed)
    rotation = Rotation.from_euler('xyz', [ROLL_DEG, PITCH_DEG, 0.0], degrees=True).as_matrix()
    lanes = np.asarray(lanes)
    points, times, tracks = [], [], []
    for k in range(60):                              # 60 road users, 5 s each
        lane, speed, t0 = rng.choice(lanes), rng.uniform(6.0, 14.0), rng.uniform(0.0, 120.0)
        t = t0 + np.arange(75) / 15.0
        x = 80.0 - speed * (t - t0) if lane < 0 else 10.0 + speed * (t - t0)
        tt = np.repeat(t, 10)
        p = np.column_stack([np.repeat(x, 10) + rng.uniform(-2.0, 2.0, tt.size),
                             lane + rng.uniform(-0.9, 0.9, tt.size),
                             rng.uniform(0.0, 1.5, tt.size) - HEIGHT_M
                             + (rise_m if lane < 0 else 0.0)])
        points.append(p), times.append(tt), tracks.append(np.full(tt.size, k))
    n_frames = 15 * 125
    for f in range(0, n_frames, 10):                 # rain: a new "track" every ten frames
        tt = np.repeat(f / 15.0 + np.arange(10) / 15.0, rain_per_frame)
        r = 15.0 * rng.random(tt.size) ** (1 / 3)    # uniform in the volume
        az = np.radians(rng.uniform(-60, 60, tt.size))
        el = np.radians(rng.uniform(-10, 10, tt.size))
        sensor = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                                  r * np.sin(el)])
        points.append(sensor @ rotation.T), times.append(tt)
        tracks.append(np.full(tt.size, 1000 + f))
    world = np.concatenate(points)
    sensor = world @ rotation                        # rotation.T @ p for each row
    return (sensor, np.concatenate(times), np.concatenate(tracks),
            rotation.T @ np.array([0.0, 0.0, 1.0]))


def test_road_user_tracks_are_told_from_rain() -> None:
    points, times, tracks, _ = _tracked_scene(3, rain_per_frame=40)
    keep = ground_plane.road_user_targets(points, times, tracks)
    road_user = tracks < 1000
    assert keep[road_user].mean() > 0.95 and keep[~road_user].mean() < 0.02
    # a target in no track is no road user's
    assert not ground_plane.road_user_targets(points, times, np.full(tracks.size, -1)).any()


def test_rain_near_the_radar_does_not_tilt_the_road_plane() -> None:
    """An independent recording's 40 rain returns a frame within 15 m tilted the plane of
    all moving targets by 6.6 deg; the road users' tracks alone still show the road, and on
    a dry day the plane is left exactly as the paper's."""
    points, times, tracks, up = _tracked_scene(3, rain_per_frame=40)
    assert _angle_deg(fit_ground_plane(points, GroundConfig()).normal, up) > 2.0
    plane, clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert clutter is not None and clutter.tilt_deg > 2.0 and 0.5 < clutter.share < 0.9
    assert _angle_deg(plane.normal, up) < 0.2 and plane.normal @ up > 0.0
    # chosen over another as far off: as uncertain as that, for a fit along one road
    assert plane.tilt_sigma_deg == pytest.approx(min(clutter.tilt_deg, 10.0))
    assert (tracks[plane.used] < 1000).all()        # indices into the given targets
    dry = tracks < 1000
    plane, clutter = ground_plane.fit_road_plane(points[dry], times[dry], tracks[dry],
                                                 GroundConfig())
    assert clutter is None
    np.testing.assert_array_equal(plane.normal,
                                  fit_ground_plane(points[dry], GroundConfig()).normal)


def test_road_users_along_one_road_do_not_replace_the_plane() -> None:
    """The road users' tracks along one road, driven both ways, with the cars' reflections
    0.3 m higher in the lane towards the radar (their fronts): their plane turns about the
    road by 5 deg and is no surer of the road than that of all moving targets (a
    forty-seventh probe's car alone on one arm: its plane 4.7 deg off, held in the final
    fit). It does not replace the plane; across eight lanes it does (above)."""
    points, times, tracks, up = _tracked_scene(3, rain_per_frame=40, lanes=(-1.75, 1.75),
                                               rise_m=0.3)
    road_users = ground_plane.road_user_targets(points, times, tracks)
    assert _angle_deg(fit_ground_plane(points[road_users], GroundConfig()).normal, up) > 3.0
    # (of the moving targets, those on tracks slower than a cyclist are left out first)
    fast = ground_plane.track_speeds(points, times, tracks) >= 2.5
    all_moving = fit_ground_plane(points[fast], GroundConfig())
    plane, clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert clutter is None
    np.testing.assert_array_equal(plane.normal, all_moving.normal)


def _lanes_with_clutter(lanes_m: tuple[float, ...], clutter_deg: float | None,
                        clutter_half_width_m: float = 25.0
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vehicle alone driving lanes at these offsets across the road (x along it), each
    way in turn at 10 m/s, 15 Hz, 8 targets a frame inside its footprint; plus, where given,
    6000 untracked moving targets over the view (``clutter_half_width_m`` either side of the
    road) on a plane ``clutter_deg`` off about x."""
    rng = np.random.default_rng(0)
    points, times, tracks = [], [], []
    for k in range(6):
        t = np.arange(0.0, 6.0, 1.0 / 15.0) + 10.0 * k
        x = 10.0 + 10.0 * (t - t[0]) if k % 2 == 0 else 70.0 - 10.0 * (t - t[0])
        tt = np.repeat(t, 8)
        points.append(np.column_stack([np.repeat(x, 8) + rng.uniform(-2.0, 2.0, tt.size),
                                       lanes_m[k % len(lanes_m)]
                                       + rng.uniform(-0.4, 0.4, tt.size),
                                       rng.uniform(0.0, 1.2, tt.size) - 5.0]))
        times.append(tt)
        tracks.append(np.full(tt.size, k))
    if clutter_deg is not None:
        n = 6000
        clutter = np.column_stack([rng.uniform(10.0, 70.0, n),
                                   rng.uniform(-clutter_half_width_m, clutter_half_width_m, n),
                                   np.zeros(n)])
        clutter[:, 2] = (math.tan(math.radians(clutter_deg)) * clutter[:, 1] - 5.0
                         + rng.normal(0, 0.1, n))
        points.append(clutter)
        times.append(rng.uniform(0.0, 60.0, n))
        tracks.append(np.full(n, -1))
    return np.concatenate(points), np.concatenate(times), np.concatenate(tracks)


def test_a_road_plane_the_road_users_cannot_show_carries_an_uncertainty() -> None:
    """Road users in one lane only (the vehicle alone on a one-way street): nothing moving
    shows the turn about that lane, so the plane kept carries the largest uncertainty, clutter
    or none. Three lanes with moving clutter on a plane 6 deg off: the two planes stage 4
    cannot tell apart carry their difference, or a plane along one road's uncertainty where
    that is more; without the clutter they agree and the plane carries none."""
    cap = ground_plane._PLANE_SIGMA_MAX_DEG
    for clutter_deg in (None, 6.0):
        plane, moving_clutter = ground_plane.fit_road_plane(
            *_lanes_with_clutter((0.0,), clutter_deg), GroundConfig())
        assert moving_clutter is None and plane.tilt_sigma_deg == cap
    lanes = (-3.5, 0.0, 3.5)
    clean, _ = ground_plane.fit_road_plane(*_lanes_with_clutter(lanes, None), GroundConfig())
    assert clean.tilt_sigma_deg == 0.0
    points, times, tracks = _lanes_with_clutter(lanes, 6.0)
    plane, moving_clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert moving_clutter is None                    # kept, not replaced
    roads = fit_ground_plane(points[tracks >= 0], GroundConfig())
    # the kept plane's densest targets are the vehicle's lanes: it is as uncertain about
    # their road as a plane along one road is, where that is more than the difference
    used = points[plane.used] - points[plane.used].mean(axis=0)
    width = ground_plane._width(used @ ground_plane._plane_basis(plane.normal)[:, :2])
    assert plane.tilt_sigma_deg == pytest.approx(
        max(_angle_deg(plane.normal, roads.normal), ground_plane._one_road_sigma_deg(width)),
        abs=1e-6)
    assert 1.5 < plane.tilt_sigma_deg < cap


def test_two_planes_along_one_road_are_as_uncertain_as_one_roads() -> None:
    """Moving false alarms along the road itself (not across the view): the plane of all
    moving targets lies along that road too, and its difference from the road users' says
    nothing of either; both turn about the road as a plane of targets along one road does
    (a seventy-first probe: 1.8 deg apart, both 8 deg off, the roll reported at 1.9)."""
    points, times, tracks = _lanes_with_clutter((-3.5, 0.0, 3.5), 6.0,
                                                clutter_half_width_m=3.0)
    plane, moving_clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert moving_clutter is None
    roads = fit_ground_plane(points[tracks >= 0], GroundConfig())
    apart = _angle_deg(plane.normal, roads.normal)
    used = points[plane.used] - points[plane.used].mean(axis=0)
    width = ground_plane._width(used @ ground_plane._plane_basis(plane.normal)[:, :2])
    assert width < ground_plane._ROAD_PLANE_MIN_WIDTH_M
    assert plane.tilt_sigma_deg == pytest.approx(ground_plane._one_road_sigma_deg(width))
    assert plane.tilt_sigma_deg > max(apart, 1.5)


def _pedestrians(seed: int, n: int = 60, beside_m: float = -6.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pedestrians walking at 1.4 m/s on a pavement ``beside_m`` to the side of the road of
    ``_tracked_scene`` for 10 s each (a track each, 4 targets a frame at their torso, 0.8-1.8
    m above the road): sensor-frame targets, frame times [s], track ids (from 5000)."""
    rng = np.random.default_rng(seed)
    rotation = Rotation.from_euler('xyz', [ROLL_DEG, PITCH_DEG, 0.0], degrees=True).as_matrix()
    points, times, tracks = [], [], []
    for k in range(n):
        t0 = rng.uniform(0.0, 120.0)
        t = t0 + np.arange(150) / 15.0
        x = rng.uniform(10.0, 60.0) + 1.4 * (t - t0) * rng.choice([-1.0, 1.0])
        tt = np.repeat(t, 4)
        points.append(np.column_stack([np.repeat(x, 4) + rng.uniform(-0.3, 0.3, tt.size),
                                       beside_m + rng.uniform(-1.0, 1.0, tt.size),
                                       rng.uniform(0.8, 1.8, tt.size) - HEIGHT_M]))
        times.append(tt)
        tracks.append(np.full(tt.size, 5000 + k))
    return np.concatenate(points) @ rotation, np.concatenate(times), np.concatenate(tracks)


def test_pedestrians_on_the_pavement_do_not_turn_the_road_plane() -> None:
    """Cars along one road both ways, pedestrians on the pavement to one side: their torsos
    a metre above the cars' reflections turn the plane of all moving targets about the road
    by degrees (a sixty-third probe's old-town streets: the roll held at that plane 1.2-4.7
    deg off). Tracks slower than a cyclist are left out: the plane is the cars' alone."""
    points, times, tracks, up = _tracked_scene(3, rain_per_frame=0, lanes=(-1.75, 1.75))
    walkers = _pedestrians(1)
    both = [np.concatenate(pair) for pair in zip((points, times, tracks), walkers)]
    assert _angle_deg(fit_ground_plane(both[0], GroundConfig()).normal, up) > 3.0
    speed = ground_plane.track_speeds(*both)
    assert (speed[both[2] >= 5000] < 2.0).all() and (speed[both[2] < 5000] > 5.0).all()
    plane, _ = ground_plane.fit_road_plane(*both, GroundConfig())
    cars = fit_ground_plane(points, GroundConfig())
    assert _angle_deg(plane.normal, cars.normal) < 0.05
    assert (both[2][plane.used] < 5000).all()        # indices into the given targets


def test_unique_track_frame_pairs_are_those_of_numpy_unique() -> None:
    """The (track, frame time) cells are found by one lexicographic sort: the same rows,
    order and inverse as ``np.unique(..., axis=0)``, so the per-track sums add up alike."""
    rng = np.random.default_rng(2)
    track = rng.integers(0, 30, 5000).astype(float)
    time_s = np.round(rng.random(5000) * 20.0, 2)
    pairs, inverse = ground_plane._unique_pairs(track, time_s)
    expected, expected_inverse = np.unique(np.column_stack([track, time_s]), axis=0,
                                           return_inverse=True)
    np.testing.assert_array_equal(pairs, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.ravel())


def test_false_alarms_that_lift_the_plane_above_the_radar_give_way_to_the_road_users() -> None:
    """False alarms with random radial velocities, a few a frame uniform in range over the
    beam, fill the view's volume: the plane of all moving targets then runs level with the
    radar or above it, which no road's does (a sixty-seventh probe's T-junction: 1.5 m
    above it, the pitch 13-20 deg off with its sign turned). Along one road the road users'
    plane is kept instead, as uncertain as a plane along one road is (the other's distance
    from it says nothing of it: rain put it 10-76 deg off, and 10 deg were reported)."""
    points, times, tracks, up = _tracked_scene(3, rain_per_frame=0, lanes=(-1.75, 1.75))
    few = tracks < 4                                 # four road users, 3000 targets
    points, times, tracks = points[few], times[few], tracks[few]
    rng = np.random.default_rng(5)
    n = 20_000
    r = rng.uniform(3.0, 100.0, n)
    az = rng.uniform(-1.0, 1.0, n)
    el = rng.uniform(-0.2, 0.2, n)
    alarms = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                              r * np.sin(el)])
    points = np.concatenate([points, alarms])
    times = np.concatenate([times, rng.uniform(0.0, 125.0, n)])
    tracks = np.concatenate([tracks, np.full(n, -1)])
    fast = ground_plane.track_speeds(points, times, tracks) >= 2.5
    assert fit_ground_plane(points[fast], GroundConfig()).offset_m > -0.5
    plane, clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert plane.offset_m < -HEIGHT_M + 1.5 and plane.normal @ up > 0.0
    assert _angle_deg(plane.normal, up) < 3.0
    assert clutter is not None and plane.tilt_sigma_deg == pytest.approx(
        min(clutter.tilt_deg, ground_plane._PLANE_SIGMA_MAX_DEG))   # one lane each way
    assert (tracks[plane.used] >= 0).all()
    # four lanes, 3.5 m apart: the road users' plane about their road is surer than the
    # false alarms' distance from it says
    points, times, tracks, up = _tracked_scene(3, rain_per_frame=0,
                                               lanes=(-5.25, -1.75, 1.75, 5.25))
    few = tracks < 4
    points = np.concatenate([points[few], alarms])
    times = np.concatenate([times[few], rng.uniform(0.0, 125.0, n)])
    tracks = np.concatenate([tracks[few], np.full(n, -1)])
    plane, clutter = ground_plane.fit_road_plane(points, times, tracks, GroundConfig())
    assert clutter is not None and plane.tilt_sigma_deg < clutter.tilt_deg
    assert (ground_plane._one_road_sigma_deg(ground_plane._ROAD_PLANE_MIN_WIDTH_M)
            < plane.tilt_sigma_deg < ground_plane._one_road_sigma_deg(2.0))
    assert _angle_deg(plane.normal, up) < 2.0 * plane.tilt_sigma_deg
